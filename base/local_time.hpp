// The wall-clock time as text in the local time zone: dates in the model database, calibration and reports.
#pragma once

#include <ctime>
#include <string>

namespace cellsight::base {

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
