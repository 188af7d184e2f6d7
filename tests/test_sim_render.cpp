// Simulated-cell renderer against independent truth: OpenCV projection of the analytic laser/plate intersection,
// and ray-rectangle geometry for occlusion and laser shadows.
#include <catch2/catch.hpp>
#include <cmath>
#include <numbers>

#include "sim_test_util.hpp"

using namespace cellsight;

namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

struct RowTruth {
  std::vector<double> u;               // analytic stripe column per row (NaN: the line does not cross the row)
  std::vector<Eigen::Vector3d> point;  // the 3D point on the plate seen in that row
};

// For every image row, where the straight 3D segment a..b projects (OpenCV projection, dense sampling).
RowTruth project_segment_rows(const sim::Rig& rig, const Eigen::Vector3d& a, const Eigen::Vector3d& b, int rows) {
  constexpr int kSamples = 40000;  // ~0.02 px apart in the image: linear interpolation error is negligible
  std::vector<cv::Point3d> world;
  for (int i = 0; i < kSamples; ++i) {
    const Eigen::Vector3d p = a + (b - a) * (static_cast<double>(i) / (kSamples - 1));
    world.emplace_back(p.x(), p.y(), p.z());
  }
  const auto px = test::opencv_project(rig, world);
  RowTruth out;
  out.u.assign(rows, std::numeric_limits<double>::quiet_NaN());
  out.point.assign(rows, Eigen::Vector3d::Zero());
  for (int i = 1; i < kSamples; ++i) {
    const double v0 = px[i - 1].y, v1 = px[i].y;
    for (int r = static_cast<int>(std::ceil(std::min(v0, v1))); r <= std::floor(std::max(v0, v1)) && r < rows; ++r) {
      if (r < 0 || v1 == v0) continue;
      const double w = (r - v0) / (v1 - v0);
      out.u[r] = px[i - 1].x + w * (px[i].x - px[i - 1].x);
      const Eigen::Vector3d pa(world[i - 1].x, world[i - 1].y, world[i - 1].z), pb(world[i].x, world[i].y, world[i].z);
      out.point[r] = pa + w * (pb - pa);
    }
  }
  return out;
}

// The segment where the laser plane (world = carrier at travel == start offset) cuts a rectangular plate.
std::pair<Eigen::Vector3d, Eigen::Vector3d> laser_cut(const sim::Rig& rig, const sim::Facet& plate) {
  const Eigen::Vector3d& n = rig.laser_normal_world;
  // Points of the plate: origin + u*au + v*av; on the plane: n.(o + u au + v av) = d -> a line in (u, v).
  const double alpha = n.dot(plate.axis_u), beta = n.dot(plate.axis_v);
  const double gamma = rig.laser_offset_m - n.dot(plate.origin);
  // Solve for u at the plate's v limits (the plates in these tests are cut across their v extent).
  const double v_lo = plate.outline[0].y(), v_hi = plate.outline[2].y();
  const double u_lo = (gamma - beta * v_lo) / alpha, u_hi = (gamma - beta * v_hi) / alpha;
  return {plate.at({u_lo, v_lo}), plate.at({u_hi, v_hi})};
}

sim::Scene scene_of(std::vector<sim::Facet> facets) {
  sim::Scene scene;
  scene.facets = std::move(facets);
  scene.part_material_a = {0.5, 0.0, 10.0};
  scene.part_material_b = scene.part_material_a;
  scene.carrier_material = scene.part_material_a;
  return scene;
}

}  // namespace

TEST_CASE(
    "Given a tilted flat plate and no noise, when a frame is rendered, then every row's stripe centre "
    "matches the analytic ray-plane-camera projection within 0.05 px") {
  const sim::Rig rig = sim::make_rig(test::exact_rig_params());
  const double travel = rig.params.carrier.start_offset_m;  // carrier frame == world frame at this travel
  // A plate leaning back 10 deg, turned 25 deg about y and 3 deg in plane: depth changes along the stripe,
  // the stripe is slanted and crosses the lens distortion.
  const Eigen::Matrix3d r =
      (Eigen::AngleAxisd(25 * kDeg, Eigen::Vector3d::UnitY()) *
       Eigen::AngleAxisd(-10 * kDeg, Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(3 * kDeg, Eigen::Vector3d::UnitZ()))
          .toRotationMatrix();
  const sim::Facet f = test::plate({0.01, 0.55, 0.15}, r.col(0), r.col(1), 0.25, 0.45);
  const sim::Scene scene = scene_of({f});
  sim::Renderer renderer(rig, 1);
  cv::Mat image;
  renderer.render(scene, {travel, 700.0, 1}, image);

  const auto [a, b] = laser_cut(rig, f);
  const RowTruth truth = project_segment_rows(rig, a, b, image.rows);
  int checked = 0;
  double worst = 0.0;
  constexpr int kEdgeRows = 4;  // rows this close to the plate's ends see the stripe's rounded end
  for (int row = kEdgeRows; row + kEdgeRows < image.rows; ++row) {
    if (std::isnan(truth.u[row - kEdgeRows]) || std::isnan(truth.u[row + kEdgeRows])) continue;
    const double measured = test::row_centre_of_gravity(image, row, 20);
    REQUIRE_FALSE(std::isnan(measured));
    worst = std::max(worst, std::abs(measured - truth.u[row]));
    ++checked;
  }
  INFO("rows checked " << checked << ", worst error " << worst << " px");
  CHECK(checked > 500);  // the 0.9 m plate spans most of the 768 rows
  CHECK(worst <= 0.05);
  // Rows outside the plate carry no light at all.
  for (int row = 0; row < image.rows; ++row) {
    bool near_plate = false;
    for (int d = -kEdgeRows; d <= kEdgeRows; ++d) {
      near_plate = near_plate || (row + d >= 0 && row + d < image.rows && !std::isnan(truth.u[row + d]));
    }
    if (!near_plate) {
      double max_value = 0;
      cv::minMaxLoc(image.row(row), nullptr, &max_value);
      CHECK(max_value == 0);
    }
  }
}

TEST_CASE(
    "Given a fin between the camera and the lit plate, when a frame is rendered, then the rows whose view "
    "ray the fin blocks carry no stripe and the others do") {
  const sim::Rig rig = sim::make_rig(test::exact_rig_params());
  const double travel = rig.params.carrier.start_offset_m;
  const sim::Facet back = test::plate({0.0, 0.55, 0.10}, Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), 0.2, 0.4);
  // A fin parallel to the laser plane, 25 mm toward the camera side, standing 120 mm out of the plate,
  // covering heights 0.45..0.65 m. The laser never touches it; it only blocks the camera's view.
  const double fin_x = 0.025, fin_z0 = 0.10, fin_z1 = 0.22, fin_y0 = 0.45, fin_y1 = 0.65;
  const sim::Facet fin =
      test::plate({fin_x, 0.5 * (fin_y0 + fin_y1), 0.5 * (fin_z0 + fin_z1)}, Eigen::Vector3d::UnitZ(),
                  Eigen::Vector3d::UnitY(), 0.5 * (fin_z1 - fin_z0), 0.5 * (fin_y1 - fin_y0));
  sim::Renderer renderer(rig, 1);
  cv::Mat image;
  renderer.render(scene_of({back, fin}), {travel, 700.0, 1}, image);

  const auto [a, b] = laser_cut(rig, back);
  const RowTruth truth = project_segment_rows(rig, a, b, image.rows);
  const Eigen::Vector3d camera = rig.camera_centre_world;
  auto blocked = [&](const Eigen::Vector3d& p) {  // plain ray / axis-aligned rectangle test
    const double t = (fin_x - camera.x()) / (p.x() - camera.x());
    const Eigen::Vector3d hit = camera + t * (p - camera);
    return t > 0 && t < 1 && hit.y() > fin_y0 && hit.y() < fin_y1 && hit.z() > fin_z0 && hit.z() < fin_z1;
  };
  int hidden_rows = 0, seen_rows = 0;
  constexpr int kMargin = 4;  // rows next to a visibility change see the stripe's blurred end
  for (int row = kMargin; row + kMargin < image.rows; ++row) {
    bool all_blocked = true, none_blocked = true, on_plate = true;
    for (int d = -kMargin; d <= kMargin; ++d) {
      if (std::isnan(truth.u[row + d])) {
        on_plate = false;
        break;
      }
      const bool bl = blocked(truth.point[row + d]);
      all_blocked = all_blocked && bl;
      none_blocked = none_blocked && !bl;
    }
    if (!on_plate) continue;
    double max_value = 0;
    cv::minMaxLoc(image.row(row), nullptr, &max_value);
    if (all_blocked) {
      ++hidden_rows;
      CHECK(max_value == 0);
    } else if (none_blocked) {
      ++seen_rows;
      CHECK(max_value > 100);
    }
  }
  INFO("hidden rows " << hidden_rows << ", seen rows " << seen_rows);
  CHECK(hidden_rows > 60);  // the fin hides ~0.2 m of the stripe
  CHECK(seen_rows > 300);
}

TEST_CASE(
    "Given a shelf between the laser and the plate, when a frame is rendered, then the plate's rows in its "
    "shadow carry no stripe and the shelf itself is lit") {
  const sim::Rig rig = sim::make_rig(test::exact_rig_params());
  const double travel = rig.params.carrier.start_offset_m;
  const sim::Facet back = test::plate({0.0, 0.55, 0.10}, Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), 0.2, 0.4);
  // A horizontal shelf above the emitter's height, sticking 400 mm out toward the laser.
  const double shelf_y = 0.70, shelf_z0 = 0.10, shelf_z1 = 0.50;
  const sim::Facet shelf = test::plate({0.0, shelf_y, 0.5 * (shelf_z0 + shelf_z1)}, Eigen::Vector3d::UnitX(),
                                       Eigen::Vector3d::UnitZ(), 0.2, 0.5 * (shelf_z1 - shelf_z0));
  sim::Renderer renderer(rig, 1);
  cv::Mat image;
  std::vector<sim::TruthPoint> points;
  renderer.render(scene_of({back, shelf}), {travel, 700.0, 1}, image, &points);

  const auto [a, b] = laser_cut(rig, back);
  const RowTruth truth = project_segment_rows(rig, a, b, image.rows);
  const Eigen::Vector3d emitter = rig.params.laser.emitter_world_m;
  auto shadowed = [&](const Eigen::Vector3d& p) {  // does the emitter -> p ray cross the shelf?
    const double t = (shelf_y - emitter.y()) / (p.y() - emitter.y());
    const double z = emitter.z() + t * (p.z() - emitter.z());
    return t > 0 && t < 1 && z > shelf_z0 && z < shelf_z1;
  };
  int dark = 0;
  for (int row = 0; row < image.rows; ++row) {
    if (std::isnan(truth.u[row]) || !shadowed(truth.point[row])) continue;
    // Only the plate's stripe is expected to vanish: look at its column, not at the shelf's stripe elsewhere.
    const int u = static_cast<int>(std::lround(truth.u[row]));
    const cv::Mat window = image.row(row).colRange(std::max(0, u - 3), std::min(image.cols, u + 4));
    double max_value = 0;
    cv::minMaxLoc(window, nullptr, &max_value);
    bool near_edge = false;
    for (int d = -4; d <= 4; ++d) {
      near_edge = near_edge || row + d < 0 || row + d >= image.rows || std::isnan(truth.u[row + d]) ||
                  !shadowed(truth.point[row + d]);
    }
    if (near_edge) continue;
    CHECK(max_value == 0);
    ++dark;
  }
  CHECK(dark > 20);
  // The shelf's own cut is lit and visible: ground-truth points lie on it.
  int on_shelf = 0;
  for (const auto& p : points) on_shelf += std::abs(p.p_carrier_m.y() - shelf_y) < 1e-9 ? 1 : 0;
  CHECK(on_shelf > 50);
}

TEST_CASE(
    "Given the same frame request twice, when rendered with noise, then the images are identical, a new "
    "seed changes the noise") {
  sim::RigParams params = sim::default_rig_params();
  const sim::Rig rig = sim::make_rig(params);
  const sim::Facet f = test::plate({0.0, 0.55, 0.10}, Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), 0.2, 0.4);
  sim::Scene scene = scene_of({f});
  scene.part_material_a = {0.3, 1.6, 7.0};  // bare metal: glints and ghosts are drawn too
  sim::Renderer r1(rig, 5), r2(rig, 5);
  r1.prepare(scene);
  r2.prepare(scene);
  cv::Mat a, b, c;
  r1.render(scene, {rig.params.carrier.start_offset_m, 1500.0, 42}, a);
  r2.render(scene, {rig.params.carrier.start_offset_m, 1500.0, 42}, b);
  r1.render(scene, {rig.params.carrier.start_offset_m, 1500.0, 43}, c);
  CHECK(cv::norm(a, b, cv::NORM_INF) == 0);
  CHECK(cv::norm(a, c, cv::NORM_INF) > 0);
}
