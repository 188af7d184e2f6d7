// Camera model and triangulation against OpenCV and the simulator's ground truth.
#include <catch2/catch.hpp>

#include <opencv2/calib3d.hpp>

#include "algo/triangulation.hpp"
#include "app/config.hpp"
#include "app/sim_mode.hpp"
#include "sim_test_util.hpp"

using namespace cellsight;

namespace {


}  // namespace

TEST_CASE("Given camera points, when projected, then algo::project equals cv::projectPoints and undistort inverts it") {
  const sim::Rig rig = sim::make_rig(sim::default_rig_params());
  std::vector<cv::Point3d> world;
  for (double x = -0.3; x <= 0.3; x += 0.1) {
    for (double y = -0.1; y <= 1.2; y += 0.1) world.emplace_back(x, y, 0.1 + 0.2 * x);
  }
  const auto expected = test::opencv_project(rig, world);
  for (std::size_t i = 0; i < world.size(); ++i) {
    const Eigen::Vector3d pc = rig.camera_pose.to_camera({world[i].x, world[i].y, world[i].z});
    const Eigen::Vector2d px = algo::project(rig.params.camera.intrinsics, pc);
    CHECK(px.x() == Approx(expected[i].x).margin(1e-9));
    CHECK(px.y() == Approx(expected[i].y).margin(1e-9));
    const Eigen::Vector2d n = algo::undistort(rig.params.camera.intrinsics, px);
    CHECK(n.x() == Approx(pc.x() / pc.z()).margin(1e-12));
    CHECK(n.y() == Approx(pc.y() / pc.z()).margin(1e-12));
  }
}

TEST_CASE("Given a point on the laser plane projected by OpenCV, when its pixel is triangulated, then the point is "
          "recovered") {
  const sim::Rig rig = sim::make_rig(sim::default_rig_params());
  const algo::SensorCalibration calibration = test::true_calibration(rig);
  const algo::Triangulator table(calibration);
  std::vector<cv::Point3d> world;
  for (double y = 0.05; y <= 1.05; y += 0.05) {
    for (double z = -0.05; z <= 0.45; z += 0.05) world.emplace_back(0.0, y, z);  // laser plane x = 0
  }
  const auto pixels = test::opencv_project(rig, world);
  double worst_exact = 0, worst_table = 0;
  for (std::size_t i = 0; i < world.size(); ++i) {
    const Eigen::Vector3d truth(world[i].x, world[i].y, world[i].z);
    worst_exact = std::max(worst_exact, (algo::intersect_laser(calibration, {pixels[i].x, pixels[i].y}) - truth).norm());
    // The table works per integer row: move the truth along the plane to the row centre first.
    const int row = static_cast<int>(std::lround(pixels[i].y));
    const Eigen::Vector3d on_row = algo::intersect_laser(calibration, {pixels[i].x, static_cast<double>(row)});
    const Eigen::Vector3f from_table = table.cell_point(static_cast<float>(pixels[i].x), row);
    worst_table = std::max(worst_table, (from_table.cast<double>() - on_row).norm());
  }
  INFO("exact " << worst_exact * 1e3 << " mm, table " << worst_table * 1e3 << " mm");
  CHECK(worst_exact < 1e-9);
  CHECK(worst_table < 2e-6);  // 0.002 mm: linear interpolation between pixel columns
}

TEST_CASE("Given a simulated pass, when the ground-truth stripe pixels are triangulated with the encoder travel, then "
          "the carrier-frame points match the simulator's points") {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  auto cell = app::make_sim_cell(*cfg);
  REQUIRE(cell.ok());
  const algo::Triangulator table(test::true_calibration(cell->rig()));
  auto pass = cell->random_pass("ribbed_v4", 9);
  REQUIRE(pass.ok());
  REQUIRE(cell->begin_pass(*pass).ok());
  cv::Mat image;
  double worst = 0;
  std::size_t n = 0;
  for (int frame = 30; frame < cell->frame_count(); frame += 60) {
    std::vector<sim::TruthPoint> truth;
    cell->render_frame(frame, 1500.0, image, &truth);
    const double travel = table.travel_m(cell->frame_info(frame).encoder_counts);
    for (const auto& t : truth) {
      // Compare at the exact truth pixel (the row is not an integer here, so use the exact intersection).
      Eigen::Vector3d cell_point = algo::intersect_laser(test::true_calibration(cell->rig()), t.pixel);
      cell_point.x() -= travel - cfg->rig.carrier.start_offset_m;
      worst = std::max(worst, (cell_point - t.p_carrier_m).norm());
      ++n;
    }
  }
  INFO(n << " points, worst " << worst * 1e3 << " mm");
  CHECK(n > 1000);
  CHECK(worst < 1e-7);
}
