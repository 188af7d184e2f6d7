// Camera model and triangulation against OpenCV and the simulator's ground truth.
#include <catch2/catch.hpp>
#include <opencv2/calib3d.hpp>

#include "algo/triangulation.hpp"
#include "app/config.hpp"
#include "app/sim_setup.hpp"
#include "sim_test_util.hpp"

using namespace cellsight;

namespace {

// Worst distance of the exact ray/plane intersection from each world point, and of the table at the point's integer
// row from the exact intersection there (the table works per row), over world points projected by OpenCV.
struct TriangulationErrors {
  double exact_m = 0.0;
  double table_m = 0.0;
};
TriangulationErrors triangulation_errors(const sim::Rig& rig, const algo::SensorCalibration& calibration,
                                         const std::vector<cv::Point3d>& world) {
  const algo::Triangulator table(calibration);
  const auto pixels = test::opencv_project(rig, world);
  TriangulationErrors worst;
  for (std::size_t i = 0; i < world.size(); ++i) {
    const Eigen::Vector3d truth(world[i].x, world[i].y, world[i].z);
    worst.exact_m =
        std::max(worst.exact_m, (algo::intersect_laser(calibration, {pixels[i].x, pixels[i].y}) - truth).norm());
    const int row = static_cast<int>(std::lround(pixels[i].y));
    const Eigen::Vector3d on_row = algo::intersect_laser(calibration, {pixels[i].x, static_cast<double>(row)});
    const Eigen::Vector3f from_table = table.cell_point(static_cast<float>(pixels[i].x), row);
    worst.table_m = std::max(worst.table_m, (from_table.cast<double>() - on_row).norm());
  }
  return worst;
}

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

TEST_CASE(
    "Given a lens with strong barrel or pincushion distortion, when a pixel is undistorted, then it inverts "
    "the distortion over the whole image") {
  algo::Intrinsics k;
  k.fx_px = 1500;
  k.fy_px = 1480;
  k.cx_px = 512;
  k.cy_px = 384;
  // Stronger than any lens of the cell (short C-mount lenses: |k1| up to ~0.3), with tangential terms.
  for (const double k1 : {-0.3, 0.25}) {
    k.k1 = k1;
    k.k2 = -0.4 * k1;
    k.k3 = 0.05 * k1;
    k.p1 = 0.002;
    k.p2 = -0.0015;
    for (double x = -0.4; x <= 0.4; x += 0.05) {
      for (double y = -0.3; y <= 0.3; y += 0.05) {
        const Eigen::Vector2d px = algo::project(k, Eigen::Vector3d(x, y, 1.0));
        const Eigen::Vector2d n = algo::undistort(k, px);
        INFO("k1 " << k1 << " at (" << x << ", " << y << ")");
        CHECK(n.x() == Approx(x).margin(1e-12));
        CHECK(n.y() == Approx(y).margin(1e-12));
      }
    }
  }
}

TEST_CASE(
    "Given a point on the laser plane projected by OpenCV, when its pixel is triangulated, then the point is "
    "recovered") {
  const sim::Rig rig = sim::make_rig(sim::default_rig_params());
  const algo::SensorCalibration calibration = test::true_calibration(rig);
  std::vector<cv::Point3d> world;
  for (double y = 0.05; y <= 1.05; y += 0.05) {
    for (double z = -0.05; z <= 0.45; z += 0.05) world.emplace_back(0.0, y, z);  // laser plane x = 0
  }
  const TriangulationErrors worst = triangulation_errors(rig, calibration, world);
  INFO("exact " << worst.exact_m * 1e3 << " mm, table " << worst.table_m * 1e3 << " mm");
  CHECK(worst.exact_m < 1e-9);
  CHECK(worst.table_m < 2e-6);  // 0.002 mm: linear interpolation between pixel columns
}

TEST_CASE(
    "Given a laser plane stated with a normal that is not unit length, when pixels are triangulated, then the "
    "points of that plane are recovered as with a unit normal") {
  // The plane n . p = d is the same for (s n, s d): a tilted plane 20 mm off the origin, stated with s = 2.5. Its
  // offset is not 0, so a table that normalised the normal without rescaling the offset would move the plane.
  const sim::Rig rig = sim::make_rig(sim::default_rig_params());
  const Eigen::Vector3d unit_normal = Eigen::Vector3d(1.0, 0.05, 0.1).normalized();
  constexpr double kOffsetM = 0.02, kScale = 2.5;
  algo::SensorCalibration calibration = test::true_calibration(rig);
  calibration.laser_normal = kScale * unit_normal;
  calibration.laser_offset_m = kScale * kOffsetM;
  std::vector<cv::Point3d> world;
  for (double y = 0.05; y <= 1.05; y += 0.05) {
    for (double z = -0.05; z <= 0.45; z += 0.05) {
      const double x = (kOffsetM - unit_normal.y() * y - unit_normal.z() * z) / unit_normal.x();  // on the plane
      world.emplace_back(x, y, z);
    }
  }
  const TriangulationErrors worst = triangulation_errors(rig, calibration, world);
  INFO("exact " << worst.exact_m * 1e3 << " mm, table " << worst.table_m * 1e3 << " mm");
  CHECK(worst.exact_m < 1e-9);
  CHECK(worst.table_m < 2e-6);
}

TEST_CASE(
    "Given a laser plane behind the camera, when pixels are triangulated, then no point is returned, the same "
    "plane in front gives points at its distance") {
  const sim::Rig rig = sim::make_rig(sim::default_rig_params());
  algo::SensorCalibration calibration = test::true_calibration(rig);
  // The optical axis in the cell frame (the camera's z row) and a plane across it 0.5 m behind / before the centre:
  // every ray leaves the camera forward (k > 0), so the plane behind meets the rays' backward extensions only.
  const Eigen::Vector3d axis = calibration.camera_pose.r_cam_world.row(2).transpose();
  const Eigen::Vector3d centre = calibration.camera_pose.centre_world();
  constexpr double kDistanceM = 0.5;
  const auto width = calibration.intrinsics.width_px, height = calibration.intrinsics.height_px;
  auto for_each_sample_pixel = [&](auto check) {
    for (int v = 0; v < height; v += 97) {
      for (int u = 0; u < width; u += 89) check(u, v);
    }
  };
  calibration.laser_normal = axis;
  calibration.laser_offset_m = axis.dot(centre) - kDistanceM;
  const algo::Triangulator behind(calibration);
  for_each_sample_pixel([&](int u, int v) {
    INFO("pixel " << u << ", " << v);
    CHECK(algo::intersect_laser(calibration, Eigen::Vector2d(u, v)).array().isNaN().all());
    CHECK(behind.cell_point(static_cast<float>(u), v).array().isNaN().all());
  });
  calibration.laser_offset_m = axis.dot(centre) + kDistanceM;
  const algo::Triangulator in_front(calibration);
  for_each_sample_pixel([&](int u, int v) {
    INFO("pixel " << u << ", " << v);
    const Eigen::Vector3d exact = algo::intersect_laser(calibration, Eigen::Vector2d(u, v));
    CHECK(axis.dot(exact - centre) == Approx(kDistanceM).margin(1e-9));
    const Eigen::Vector3f from_table = in_front.cell_point(static_cast<float>(u), v);
    CHECK(axis.dot(from_table.cast<double>() - centre) == Approx(kDistanceM).margin(1e-6));
  });
}

TEST_CASE(
    "Given a simulated pass, when the ground-truth stripe pixels are triangulated with the encoder travel, then "
    "the carrier-frame points match the simulator's points") {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  auto cell = app::make_sim_cell(*cfg);
  REQUIRE(cell.ok());
  const algo::SensorCalibration calibration = test::true_calibration(cell->rig());
  const algo::Triangulator table(calibration);
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
      // The table works per integer row and the truth pixel's row is not one: move the truth along the laser plane
      // to the row (the exact intersection, checked against OpenCV above), then compare the production carrier point.
      const int row = static_cast<int>(std::lround(t.pixel.y()));
      const Eigen::Vector3d along_plane = algo::intersect_laser(calibration, {t.pixel.x(), static_cast<double>(row)}) -
                                          algo::intersect_laser(calibration, t.pixel);
      const Eigen::Vector3f p =
          table.carrier_point(static_cast<float>(t.pixel.x()), row, travel, cfg->rig.carrier.start_offset_m);
      worst = std::max(worst, (p.cast<double>() - (t.p_carrier_m + along_plane)).norm());
      ++n;
    }
  }
  INFO(n << " points, worst " << worst * 1e3 << " mm");
  CHECK(n > 1000);
  CHECK(worst < 1e-5);  // the table (2e-6) and float coordinates about 1 m from the origin
}
