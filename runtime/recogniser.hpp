// The recognition stage as the production loop sees it: one pass's points in, one decision out, under a deadline.
#pragma once

#include <chrono>
#include <span>
#include <string_view>

#include "algo/decision.hpp"
#include "algo/scan.hpp"

namespace cellsight::runtime {

class Recogniser {
 public:
  virtual ~Recogniser() = default;
  // The raw points of one pass (carrier included, carrier frame). Decides before `deadline` or returns source
  // kTimeout; never allocates (everything is sized at construction from the config and the model database).
  [[nodiscard]] virtual algo::Decision recognise(std::span<const algo::ScanPoint> points,
                                                 std::chrono::steady_clock::time_point deadline) = 0;
  // Name of a class index of the decisions (for the one log line per part); empty for -1.
  [[nodiscard]] virtual std::string_view class_name(int class_index) const = 0;
};

}  // namespace cellsight::runtime
