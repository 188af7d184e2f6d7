// What recognising one scan decided (DESIGN.md "Data flow": algo/cascade), shared by the cascade, the production
// loop, classify/eval and the PLC mapping. Plain value type: no strings, no allocation.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <string_view>

namespace cellsight::algo {

// Where a decision came from (DESIGN.md classify --json "status").
enum class DecisionSource : std::uint8_t {
  kSvm,      // the SVM was sure (thesis 6.4.4: p1 >= 0.70 and p2 <= 0.06); Perfect Match measured the pose only
  kPm,       // Perfect Match chose among the SVM's best k classes (lowest error)
  kUnknown,  // no taught part fits well enough: never a guess
  kTimeout,  // the hard deadline passed before a decision: never a guess
  kBadScan,  // too few points, empty after support removal, or outside the grid
  kNoPart,   // the pass saw nothing in front of the carrier
};

[[nodiscard]] constexpr std::string_view to_string(DecisionSource source) {
  switch (source) {
    case DecisionSource::kSvm:
      return "svm";
    case DecisionSource::kPm:
      return "pm";
    case DecisionSource::kUnknown:
      return "unknown";
    case DecisionSource::kTimeout:
      return "timeout";
    case DecisionSource::kBadScan:
      return "bad_scan";
    case DecisionSource::kNoPart:
      return "no_part";
  }
  return "invalid";
}

// Displacement of the scanned part relative to its taught template (DESIGN.md "Pose"):
// p_scan = c + R_z(theta) (p_template - c) + (x, y, 0), c = the template's x-y centroid, theta counter-clockwise
// seen from the camera (+z).
struct PlanarPose {
  double x_m = 0.0;
  double y_m = 0.0;
  double theta_rad = 0.0;
};

struct Decision {
  DecisionSource source = DecisionSource::kNoPart;
  int class_index = -1;      // into the model's classes; -1 when there is no class (unknown, timeout, ...)
  int part_id = 0;           // the class's PLC id; 0 when none
  double probability = 0.0;  // SVM probability of the chosen class (of the best class when unknown)
  double pm_error = std::numeric_limits<double>::quiet_NaN();  // per-point Perfect Match cost of the choice
  bool pose_valid = false;
  PlanarPose pose{};
  double template_coverage = std::numeric_limits<double>::quiet_NaN();  // two-way check: template seen in scan
  double scan_outliers = std::numeric_limits<double>::quiet_NaN();      // two-way check: scan off the template
  double missing_area_m2 = std::numeric_limits<double>::quiet_NaN();    // two-way check: largest blob the scan lacks
  double extra_area_m2 = std::numeric_limits<double>::quiet_NaN();      // ... and largest the template lacks
  int second_class_index = -1;  // runner-up (for logs and the eval report)
  double features_ms = 0.0, svm_ms = 0.0, pm_ms = 0.0, total_ms = 0.0;
  [[nodiscard]] bool accepted() const { return source == DecisionSource::kSvm || source == DecisionSource::kPm; }
};

}  // namespace cellsight::algo
