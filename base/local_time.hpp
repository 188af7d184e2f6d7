// The wall-clock time as text in the local time zone: dates in the model database, calibration and reports.
#pragma once

#include <cstdint>
#include <ctime>
#include <string>

namespace cellsight::base {

// Milliseconds since the Unix epoch (CLOCK_REALTIME, vDSO: no system call, no allocation; safe on the loop's
// threads), for the times the operator's screen shows.
[[nodiscard]] inline std::int64_t wall_clock_ms() {
  timespec now{};
  ::clock_gettime(CLOCK_REALTIME, &now);
  constexpr std::int64_t kMsPerS = 1000, kNsPerMs = 1'000'000;
  return static_cast<std::int64_t>(now.tv_sec) * kMsPerS + now.tv_nsec / kNsPerMs;
}

// Now, formatted by strftime (thread-safe: localtime_r). Default "YYYY-MM-DD HH:MM:SS".
[[nodiscard]] inline std::string local_time_text(const char* format = "%Y-%m-%d %H:%M:%S") {
  const std::time_t now = std::time(nullptr);
  std::tm local{};
  localtime_r(&now, &local);
  char buf[64];
  if (std::strftime(buf, sizeof buf, format, &local) == 0) return {};
  return buf;
}

}  // namespace cellsight::base
