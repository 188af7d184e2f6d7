// What recognising one scan decided (DESIGN.md "Data flow": algo/cascade), shared by the cascade, the production
// loop, classify/eval and the PLC mapping. Plain value type: no strings, no allocation.
#pragma once

#include <array>
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
    case DecisionSource::kSvm: return "svm";
    case DecisionSource::kPm: return "pm";
    case DecisionSource::kUnknown: return "unknown";
    case DecisionSource::kTimeout: return "timeout";
    case DecisionSource::kBadScan: return "bad_scan";
    case DecisionSource::kNoPart: return "no_part";
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

// The axes of the full pose (DESIGN.md "Pose"), in the order of Decision::pose_sigma and of the PLC's sigma registers:
// p_scan = c + R_z(theta) R_y(ry) R_x(rx) (p_template - c) + (x, y, z), c = the template's centroid (x, y and depth),
// rx the tilt about x, ry the swing about the hook's vertical axis y, theta = rz about the camera axis z. The rotation
// is applied to the template point x first (rx), then y (ry), then z (theta): yaw-pitch-roll Z-Y-X.
enum class PoseAxis : std::uint8_t { kX, kY, kZ, kRx, kRy, kRz };
inline constexpr int kPoseAxes = 6;

// Why a candidate was not accepted (classify --json "rejected_by", eval's reasons, the run loop's log line).
enum class RejectReason : std::uint8_t {
  kNone,         // accepted, or not looked at
  kNoTemplate,   // the class has no usable template (missing or refused file)
  kPmError,      // Perfect Match error per point over its threshold: an unrelated shape
  kMissingArea,  // the scan lacks a compact piece of the template (a hole the template does not have)
  kExtraArea,    // the scan has material where the template has none (a template hole covered)
  kUncovered,    // too much of the template unseen, all places together
  kOutliers,     // too much of the scan off the template, all places together
  kHolePattern,  // holes of one surface where the other is solid (a perforation field shifted or mirrored)
  kSize,         // outer size (width or height) off the template's by more than its own scans vary (5 mm taller)
  kEdge,         // one edge off the template's by more than its own scans vary (5 mm taller at a flanged part's end)
  kAmbiguous,    // passed, but another candidate passed as well without a clear margin
  kNotVerified,  // ranked too low: the verification budget or the candidate limit ended first
  kTwinFeature,  // passed, tied with a near twin, but where the two differ the scan shows the twin (value: cells seen
                 // in its hole, or in the twin's; limit: the expected count)
};

[[nodiscard]] constexpr std::string_view to_string(RejectReason reason) {
  switch (reason) {
    case RejectReason::kNone: return "none";
    case RejectReason::kNoTemplate: return "no_template";
    case RejectReason::kPmError: return "pm_error";
    case RejectReason::kMissingArea: return "missing_area";
    case RejectReason::kExtraArea: return "extra_area";
    case RejectReason::kUncovered: return "uncovered";
    case RejectReason::kOutliers: return "outliers";
    case RejectReason::kHolePattern: return "hole_pattern";
    case RejectReason::kSize: return "size";
    case RejectReason::kEdge: return "edge";
    case RejectReason::kAmbiguous: return "ambiguous";
    case RejectReason::kNotVerified: return "not_verified";
    case RejectReason::kTwinFeature: return "twin_feature";
  }
  return "invalid";
}

// One class the cascade considered, in the SVM's rank order.
struct CandidateOutcome {
  int class_index = -1;
  double probability = 0.0;  // the SVM's
  bool verified = false;     // Perfect Match and the two-way check ran
  bool passed = false;       // met every threshold of its template
  RejectReason rejected_by = RejectReason::kNone;
  double value = std::numeric_limits<double>::quiet_NaN();  // the figure that failed (m^2 for areas, shares, error)
  double limit = std::numeric_limits<double>::quiet_NaN();  // ... and its learnt threshold
  double pm_error = std::numeric_limits<double>::quiet_NaN();
  bool pm_stopped_early = false;  // its error was far above the limit early on: pm_error is where it stopped
  double missing_area_m2 = std::numeric_limits<double>::quiet_NaN();
  double extra_area_m2 = std::numeric_limits<double>::quiet_NaN();
  double evidence_m2 = std::numeric_limits<double>::quiet_NaN();  // weighted evidence against it (ties, margins)
  double coverage = std::numeric_limits<double>::quiet_NaN();     // share of its template the scan covers
  double outliers = std::numeric_limits<double>::quiet_NaN();     // share of the scan its template does not explain
  double size_dev_m = std::numeric_limits<double>::quiet_NaN();   // outer size off its template's (TemplateThresholds)
  double edge_dev_m = std::numeric_limits<double>::quiet_NaN();   // its edges' largest deviation (TemplateThresholds)
  // Diagnosis of the two above, signed (the scan's minus its template's learnt centre; > 0 wider, taller, an edge
  // further out): the width and the height, and each edge (left, right, bottom, top: cascade.hpp's Edge order). NaN
  // where not measured (lines ending in lost data; the edges also where no hole places them, MatchReport::edge_m).
  std::array<double, 2> size_off_xy_m = {std::numeric_limits<double>::quiet_NaN(),
                                         std::numeric_limits<double>::quiet_NaN()};
  std::array<double, 4> edge_off_m = {
      std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN(),
      std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()};
  double hole_pattern_m2 = std::numeric_limits<double>::quiet_NaN();  // MatchReport::hole_pattern_m2
  PlanarPose check_pose{};  // the pose its two-way check ran at (diagnosis: a refused candidate's pose)
  double ms = 0.0;
};

// The most candidates a decision reports (fixed capacity: a Decision is a plain value that never allocates).
inline constexpr int kMaxReportedCandidates = 16;

struct Decision {
  static constexpr std::array<double, kPoseAxes> nan_array() {
    std::array<double, kPoseAxes> a{};
    a.fill(std::numeric_limits<double>::quiet_NaN());
    return a;
  }
  DecisionSource source = DecisionSource::kNoPart;
  int class_index = -1;      // into the model's classes; -1 when there is no class (unknown, timeout, ...)
  int part_id = 0;           // the class's PLC id; 0 when none
  double probability = 0.0;  // SVM probability of the chosen class (of the best class when unknown)
  double pm_error = std::numeric_limits<double>::quiet_NaN();  // per-point Perfect Match cost of the choice
  bool pose_valid = false;
  PlanarPose pose{};
  // The out-of-plane part of the full pose (PoseAxis): NaN where the geometry does not fix the axis (a strip a few
  // millimetres high gives no tilt about x) or no pose was estimated; published invalid then, never 0.
  double z_m = std::numeric_limits<double>::quiet_NaN();
  double rx_rad = std::numeric_limits<double>::quiet_NaN();
  double ry_rad = std::numeric_limits<double>::quiet_NaN();
  // 1-sigma uncertainty per PoseAxis (m for x, y, z; rad for rx, ry, theta), calibrated on the simulator's truth;
  // NaN exactly where the axis's value is NaN or not estimated.
  std::array<double, kPoseAxes> pose_sigma{nan_array()};
  double template_coverage = std::numeric_limits<double>::quiet_NaN();  // two-way check: template seen in scan
  double scan_outliers = std::numeric_limits<double>::quiet_NaN();      // two-way check: scan off the template
  double missing_area_m2 = std::numeric_limits<double>::quiet_NaN();    // two-way check: largest blob the scan lacks
  double extra_area_m2 = std::numeric_limits<double>::quiet_NaN();      // ... and largest the template lacks
  int second_class_index = -1;                                          // runner-up (for logs and the eval report)
  // The candidates in the SVM's rank order as far as the cascade went (verified or not), at most
  // kMaxReportedCandidates; verified_count = how many ran Perfect Match.
  std::array<CandidateOutcome, kMaxReportedCandidates> candidates{};
  int candidate_count = 0;
  int verified_count = 0;
  // Unknown: the reason of the most probable verified candidate (ambiguous when two passed), for the log.
  RejectReason unknown_reason = RejectReason::kNone;
  double features_ms = 0.0, svm_ms = 0.0, pm_ms = 0.0, total_ms = 0.0;
  [[nodiscard]] bool accepted() const { return source == DecisionSource::kSvm || source == DecisionSource::kPm; }
};

}  // namespace cellsight::algo
