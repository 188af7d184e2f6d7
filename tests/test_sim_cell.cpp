// The simulated cell as a whole: passes from seeds, ground truth that matches the rendered frames.
#include <catch2/catch.hpp>

#include "app/config.hpp"
#include "app/sim_setup.hpp"

using namespace cellsight;

namespace {

sim::SimCell shipped_cell() {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  auto cell = app::make_sim_cell(*cfg);
  REQUIRE(cell.ok());
  return std::move(*cell);
}

}  // namespace

TEST_CASE(
    "Given seeds, when passes are drawn, then poses stay inside the configured ranges, repeat for a seed and "
    "differ between seeds") {
  sim::SimCell cell = shipped_cell();
  const auto& p = cell.params();
  for (std::uint64_t seed = 0; seed < 200; ++seed) {
    auto pass = cell.random_pass("tray", seed);
    REQUIRE(pass.ok());
    CHECK(std::abs(pass->pose.x_m) <= p.pose_xy_range_m);
    CHECK(std::abs(pass->pose.y_m) <= p.pose_xy_range_m);
    CHECK(std::abs(pass->pose.theta_rad) <= p.pose_theta_range_deg * M_PI / 180.0);
    CHECK(std::abs(pass->pose.swing_rad) <= p.swing_range_deg * M_PI / 180.0);
    auto again = cell.random_pass("tray", seed);
    CHECK(again->pose.x_m == pass->pose.x_m);
    CHECK(again->coating_a.name == pass->coating_a.name);
    auto other = cell.random_pass("tray", seed + 1000);
    CHECK(other->pose.x_m != pass->pose.x_m);
  }
  CHECK_FALSE(cell.random_pass("teapot", 1).ok());
}

TEST_CASE(
    "Given a simulated pass, when frames are rendered with ground truth, then the image is bright where the "
    "truth says the stripe is, and truth points lie on the part or the carrier") {
  sim::SimCell cell = shipped_cell();
  auto pass = cell.random_pass("louvred_panel", 5);
  REQUIRE(pass.ok());
  pass->coating_a = pass->coating_b = sim::Coating{"primer", {0.55, 0.15, 20.0}, 1.0};
  REQUIRE(cell.begin_pass(*pass).ok());
  cv::Mat image;
  std::size_t points = 0, bright = 0, on_part = 0;
  for (int frame = 40; frame < cell.frame_count(); frame += 50) {
    std::vector<sim::TruthPoint> truth;
    cell.render_frame(frame, 1500.0, image, &truth);
    for (const auto& t : truth) {
      const int u = static_cast<int>(std::lround(t.pixel.x())), v = static_cast<int>(std::lround(t.pixel.y()));
      REQUIRE(u >= 0);
      REQUIRE(v >= 0);
      REQUIRE(u < image.cols);
      REQUIRE(v < image.rows);
      ++points;
      bright += image.at<std::uint8_t>(v, u) > 60 ? 1 : 0;
      on_part += t.is_part ? 1 : 0;
      // Every truth point is on a facet of its kind: distance to the nearest such facet plane inside the outline.
      bool on_facet = false;
      for (const auto& f : cell.scene().facets) {
        if (f.is_part != t.is_part) continue;
        const double d = std::abs(f.normal.dot(t.p_carrier_m - f.origin));
        if (d > 1e-9) continue;
        // Stripe ends lie exactly on hole or outline edges: accept a point within 0.1 um of the facet's area.
        const Eigen::Vector2d uv = f.to_uv(t.p_carrier_m);
        for (const Eigen::Vector2d& nudge : {Eigen::Vector2d(0, 0), Eigen::Vector2d(1e-7, 0), Eigen::Vector2d(-1e-7, 0),
                                             Eigen::Vector2d(0, 1e-7), Eigen::Vector2d(0, -1e-7)}) {
          on_facet = on_facet || f.contains(uv + nudge);
        }
      }
      CHECK(on_facet);
    }
  }
  INFO("points " << points << ", bright " << bright);
  CHECK(points > 1000);
  CHECK(on_part > points / 2);
  CHECK(bright >= points * 95 / 100);  // the rest: stripe ends, speckle dips
}
