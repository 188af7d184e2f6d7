// Technician calibration from circle-grid board views: camera intrinsics, camera pose, laser plane, conveyor scale.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "algo/camera_model.hpp"
#include "algo/result.hpp"

namespace cellsight::algo {

// A flat plate with an asymmetric grid of dark dots (OpenCV's CALIB_CB_ASYMMETRIC_GRID layout).
// Board frame: origin at the centre of dot 0 (top-left seen from the printed face), x along a row, y down the
// rows, z = x cross y pointing into the plate (the dots are printed on the face toward -z).
// Dot (row i, column j) has index i * cols + j and sits at ((2 j + i mod 2) * spacing, i * spacing).
struct BoardSpec {
  int rows = 13;             // dot rows; odd, so that no rotation maps the pattern onto itself
  int cols = 6;              // dots per row
  double spacing_mm = 40.0;  // row pitch; neighbours within a row are 2 * spacing apart
  double dot_diameter_mm = 28.0;
  double width_mm = 520.0;  // the plate, centred on the dot field
  double height_mm = 560.0;

  [[nodiscard]] int dot_count() const { return rows * cols; }
  [[nodiscard]] Eigen::Vector2d dot_m(int index) const;
  [[nodiscard]] Eigen::Vector2d field_size_m() const;  // extent of the dot centres
  [[nodiscard]] Eigen::Vector2d plate_min_m() const;   // plate corners in the board frame
  [[nodiscard]] Eigen::Vector2d plate_max_m() const;
  // Distance in the board plane from (u, v) to the nearest dot centre (O(1)).
  [[nodiscard]] double distance_to_nearest_dot_m(const Eigen::Vector2d& uv) const;
};

// Empty when the board can be used, else what is wrong with it.
[[nodiscard]] std::string validate_board(const BoardSpec& board);

// --- Detection ----------------------------------------------------------------------------------------------
// Finds the board in a mono8 image (cv::findCirclesGrid) and returns the centre of each dot's image (pixels) in
// board index order, refined to sub-pixel by the centroid of its relative darkness. These are image centres, not
// images of the dots' centres: the calibration functions below correct the perspective difference. Fails with a
// message saying what was seen and what to check.
[[nodiscard]] Expected<std::vector<Eigen::Vector2d>> detect_board(const cv::Mat& image, const BoardSpec& board);

// --- Camera intrinsics (Zhang's method, as cv::calibrateCamera) ----------------------------------------------
struct CameraCalibrationOptions {
  int min_views = 6;
  double max_rms_px = 0.5;            // refuse above this reprojection error
  double min_tilt_spread_deg = 20.0;  // the board normals must differ by at least this (else focal length is weak)
  double min_coverage = 0.5;          // share of an 8 x 6 image grid that dots reached; below: a warning
};

struct CameraCalibrationResult {
  Intrinsics intrinsics{};
  double rms_px = 0.0;
  std::vector<double> view_rms_px;
  std::vector<Eigen::Isometry3d> board_to_camera;
  double tilt_spread_deg = 0.0;
  double coverage = 0.0;
  std::vector<std::string> warnings;
};

// `views`: detected dot centres per view (from detect_board), all of one board and one image size.
[[nodiscard]] Expected<CameraCalibrationResult> calibrate_intrinsics(
    const std::vector<std::vector<Eigen::Vector2d>>& views, const BoardSpec& board, int width_px, int height_px,
    const CameraCalibrationOptions& options = {});

// --- Board pose ---------------------------------------------------------------------------------------------
struct BoardPose {
  Eigen::Isometry3d board_to_camera = Eigen::Isometry3d::Identity();
  double rms_px = 0.0;
};

// The board's pose from its dots with calibrated intrinsics (IPPE for planar targets, then Levenberg-Marquardt).
[[nodiscard]] Expected<BoardPose> solve_board_pose(const Intrinsics& intrinsics, const BoardSpec& board,
                                                   const std::vector<Eigen::Vector2d>& dots);

// Camera pose in the cell frame from a reference view of the board held in a fixture at a known pose
// (board_to_cell). thesis 3.3.2.2: the world origin is the centre of one dot of the board.
struct ReferencePose {
  CameraPose camera_pose{};
  double rms_px = 0.0;
};
[[nodiscard]] Expected<ReferencePose> camera_pose_from_reference(const Intrinsics& intrinsics, const BoardSpec& board,
                                                                 const std::vector<Eigen::Vector2d>& dots,
                                                                 const Eigen::Isometry3d& board_to_cell,
                                                                 double max_rms_px = 0.5);

// The board pose of DESIGN's reference fixture: dot 0 at origin_cell_m, board x = cell +x, board y = cell -y
// (rows run downward), printed face toward the camera side (+z).
[[nodiscard]] Eigen::Isometry3d fixture_board_to_cell(const Eigen::Vector3d& origin_cell_m);

// --- Laser plane --------------------------------------------------------------------------------------------
struct LaserLineOptions {
  double min_contrast_dn = 25.0;  // peak above the local background
  int half_window_px = 5;         // centre-of-gravity window around the peak
  double min_sigma_px = 0.45;     // narrower: a hot pixel, not a stripe
  double max_sigma_px = 4.0;      // wider: a glint or stray light
};

// Sub-pixel stripe centre per image row (centre of gravity above the local background); rows without a stripe
// are left out. Each result is (column, row).
[[nodiscard]] std::vector<Eigen::Vector2d> laser_line_centres(const cv::Mat& image,
                                                              const LaserLineOptions& options = {});

// One board pose with the laser on: dots seen with the lamp on, the stripe seen with the lamp off.
struct LaserView {
  std::vector<Eigen::Vector2d> dots;
  std::vector<Eigen::Vector2d> stripe_px;
};

struct LaserCalibrationOptions {
  double dot_margin_mm = 8.0;  // stripe samples this close to a dark dot (or the plate edge) are not used
  int min_points_per_view = 30;
  double min_spread_mm = 20.0;   // second principal spread of the points: below, they lie on one line
  double max_residual_mm = 0.5;  // refuse above this RMS distance to the fitted plane
  double reject_sigmas = 4.0;    // outlier rejection threshold in robust standard deviations
};

struct LaserPlaneResult {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitX();  // cell frame, n.x >= 0
  double offset_m = 0.0;                              // n . p = offset_m
  double residual_rms_mm = 0.0;
  double spread_mm = 0.0;  // second principal spread of the points used
  int points_used = 0;
  int points_rejected = 0;
  std::vector<int> points_per_view;
};

[[nodiscard]] Expected<LaserPlaneResult> calibrate_laser_plane(const Intrinsics& intrinsics,
                                                               const CameraPose& camera_pose, const BoardSpec& board,
                                                               const std::vector<LaserView>& views,
                                                               const LaserCalibrationOptions& options = {});

// Least-squares plane through points (centroid + SVD); the normal is unit length with n.x >= 0.
struct PlaneFit {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitX();
  double offset = 0.0;
  Eigen::Vector3d spread = Eigen::Vector3d::Zero();  // standard deviations along the principal axes, largest first
};
[[nodiscard]] PlaneFit fit_plane(const std::vector<Eigen::Vector3d>& points);

// --- Conveyor scale -----------------------------------------------------------------------------------------
struct ConveyorView {
  std::vector<Eigen::Vector2d> dots;
  std::int64_t encoder_counts = 0;
};

struct ConveyorCalibrationOptions {
  double min_travel_mm = 50.0;
  double warn_angle_deg = 1.0;     // motion further than this from the cell x axis: a warning
  double warn_rotation_deg = 0.5;  // the board turning between views: a warning (it must ride rigidly)
};

struct ConveyorResult {
  double mm_per_count = 0.0;
  Eigen::Vector3d direction = Eigen::Vector3d::UnitX();  // unit travel direction, cell frame
  double angle_to_x_deg = 0.0;
  double travel_mm = 0.0;        // between the first and last view
  double residual_rms_mm = 0.0;  // of the straight-line fit (0 with two views)
  double max_rotation_deg = 0.0;
  std::vector<std::string> warnings;
};

[[nodiscard]] Expected<ConveyorResult> calibrate_conveyor(const Intrinsics& intrinsics, const CameraPose& camera_pose,
                                                          const BoardSpec& board,
                                                          const std::vector<ConveyorView>& views,
                                                          const ConveyorCalibrationOptions& options = {});

}  // namespace cellsight::algo
