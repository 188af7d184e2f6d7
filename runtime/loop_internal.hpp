// Helpers shared by the production loop's source files (not part of the runtime's interface).
#pragma once

#include <time.h>

#include <chrono>
#include <cstdint>

#include "algo/decision.hpp"
#include "drivers/device.hpp"
#include "runtime/loop_types.hpp"

namespace cellsight::runtime::loop_detail {

inline constexpr const char* kComponent = "loop";
inline constexpr double kNsPerMs = 1e6;

inline std::int64_t to_ns(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count();
}

inline double ms_between(std::chrono::steady_clock::time_point from, std::chrono::steady_clock::time_point to) {
  return static_cast<double>(std::chrono::duration_cast<std::chrono::nanoseconds>(to - from).count()) / kNsPerMs;
}

// TIMESTAMP of the result block: CLOCK_MONOTONIC in microseconds (DESIGN.md register map).
inline std::uint64_t monotonic_us() {
  constexpr std::int64_t kNsPerUs = 1000;
  constexpr std::uint64_t kUsPerS = 1'000'000;
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<std::uint64_t>(now.tv_sec) * kUsPerS + static_cast<std::uint64_t>(now.tv_nsec / kNsPerUs);
}

inline algo::Decision decision_of(algo::DecisionSource source) {
  algo::Decision d;
  d.source = source;
  return d;
}

inline const char* trigger_name(TriggerSource trigger) {
  return trigger == TriggerSource::kSoftware ? "SW_TRIGGER" : "part-present";
}

}  // namespace cellsight::runtime::loop_detail

namespace cellsight::runtime {

// The loop's source files (the only includers of this header) name these without qualification.
using drivers::DeviceStatus;
using drivers::ErrorCode;
using drivers::WarningCode;
using loop_detail::decision_of;
using loop_detail::kComponent;
using loop_detail::ms_between;
using loop_detail::to_ns;

}  // namespace cellsight::runtime
