// Simulated calibration board: what the camera sees of a circle-grid plate, and where a technician would hold it.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstddef>
#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

#include "algo/calibration.hpp"
#include "drivers/sim/renderer.hpp"
#include "drivers/sim/rig.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::sim {

// Surface and lighting of the board pictures.
struct BoardLook {
  double plate_reflectance = 0.80;  // light matt plate
  double dot_reflectance = 0.04;    // dark printed dots
  double lamp_dn = 200.0;           // a white matt surface facing the lamp at lamp_reference_m gives this
  Eigen::Vector3d lamp_offset_m{0.25, 0.35, 0.0};  // calibration lamp beside the camera (cell axes, from the camera)
  double lamp_reference_m = 1.8;
  double lamp_diffuse_share = 0.3;  // light that reaches the board from every direction (cabin walls)
  double backdrop_dn = 12.0;        // the dark cabin around the board, lamp on
};

// Renders the board at a pose in the cell frame (board frame of algo::BoardSpec) with the rig's camera:
// distortion, lens blur, anti-aliased edges (4 x 4 samples on every pixel an edge crosses), sensor noise.
class BoardRenderer {
 public:
  BoardRenderer(const Rig& rig, std::uint64_t noise_seed, BoardLook look = {});

  // The calibration lamp on, laser off.
  void render(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, std::uint64_t seed, cv::Mat& image);
  // Lamp off and the cabin light as in production; the laser on at exposure_us draws its stripe on the board.
  void render_laser(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, double exposure_us,
                    std::uint64_t seed, cv::Mat& image);

  // Ideal image of each dot centre (ground truth for tests).
  [[nodiscard]] std::vector<Eigen::Vector2d> project_dots(const algo::BoardSpec& board,
                                                          const Eigen::Isometry3d& board_to_cell) const;
  // True when the whole plate is inside the image (with margin_px) and its printed face is toward the camera.
  [[nodiscard]] bool fully_visible(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell,
                                   double margin_px) const;
  [[nodiscard]] const Rig& rig() const { return rig_; }

 private:
  // Light reflected by the board (and backdrop) per pixel in DN, before blur and noise.
  void shade(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, bool lamp, double exposure_us);
  // shade()'s steps (board.cpp): one view's pixel corners on the board, and a pixel's shares of backdrop, plate and
  // dot (exact away from edges, else 4 x 4 samples).
  struct View;
  void map_corners_to_board(const View& view);
  [[nodiscard]] std::array<double, 3> pixel_shares(const algo::BoardSpec& board, const View& view, std::size_t c00,
                                                   const Eigen::Vector2d& centre) const;
  void add_noise_and_quantise(const cv::Mat& background, std::uint64_t seed, cv::Mat& image);

  Rig rig_;
  BoardLook look_;
  Renderer renderer_;  // the same sensor (fixed pattern, noise) as the production frames; draws the stripe
  int width_ = 0, height_ = 0;
  std::vector<Eigen::Vector2d> corner_rays_;  // normalised undistorted coordinates at pixel corners, (W+1) x (H+1)
  std::vector<Eigen::Vector2d> corner_uv_;    // per view: board-plane coordinates at the pixel corners
  std::vector<std::uint8_t> corner_valid_;
  cv::Mat light_, blurred_, background_;
};

// The board as one sheet the laser can light: the dark dots return almost no laser light, so they are holes.
[[nodiscard]] Facet board_facet(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell,
                                double margin_m = 0.0);

// --- The simulated technician: where the board is held for each calibration step on this rig ----------------
// Ten tilted views spread over the image for the intrinsics (a view that cannot be fitted into the picture,
// even moved toward its centre, is left out).
[[nodiscard]] std::vector<Eigen::Isometry3d> plan_camera_views(const BoardRenderer& renderer,
                                                               const algo::BoardSpec& board);
// Where this cell's reference fixture puts dot 0 (cell frame): the board on the laser plane at the aim point.
[[nodiscard]] Eigen::Vector3d plan_reference_origin(const Rig& rig, const algo::BoardSpec& board);
// Board poses that cut the laser plane at different depths and tilts, facing both the camera and the laser.
[[nodiscard]] std::vector<Eigen::Isometry3d> plan_laser_views(const Rig& rig, const algo::BoardSpec& board);

struct CarrierView {
  Eigen::Isometry3d board_to_cell = Eigen::Isometry3d::Identity();
  std::int64_t encoder_counts = 0;
};
// The board clamped to the carrier, seen at encoder counts about `step_mm` apart (`count` views).
[[nodiscard]] std::vector<CarrierView> plan_conveyor_views(const Rig& rig, const algo::BoardSpec& board, int count = 3,
                                                           double step_mm = 100.0);

}  // namespace cellsight::sim
