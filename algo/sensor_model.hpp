// The calibrated sensor: what triangulation needs to turn a stripe pixel into a cell-frame point.
#pragma once

#include <Eigen/Core>

#include "algo/camera_model.hpp"

namespace cellsight::algo {

// Produced by `cellsight calibrate` (config/calibration.yaml); never the simulator's true parameters.
struct SensorCalibration {
  Intrinsics intrinsics{};
  CameraPose camera_pose{};                                 // cell (world) frame -> camera
  Eigen::Vector3d laser_normal = Eigen::Vector3d::UnitX();  // laser plane: normal . p = laser_offset_m (cell frame)
  double laser_offset_m = 0.0;
  double mm_per_count = 0.1;  // conveyor encoder scale
  // Quality figures recorded when calibrating (for reports and refusal thresholds).
  double reprojection_rms_px = 0.0;
  double laser_residual_mm = 0.0;
};

// Plane n . p = offset in the carrier frame (the carrier's support, thesis 6.4.1.1).
struct Plane {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  double offset_m = 0.0;
  [[nodiscard]] double signed_distance(const Eigen::Vector3d& p) const { return normal.dot(p) - offset_m; }
};

}  // namespace cellsight::algo
