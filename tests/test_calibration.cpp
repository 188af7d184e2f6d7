// Technician calibration against independent truth: the simulated cell's rig (never read by the calibration
// code), OpenCV projections of exact board poses, analytic stripes; and every kind of bad input refused with the
// previous calibration.yaml left byte for byte as it was.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "algo/calibration.hpp"
#include "cli/calibrate_mode.hpp"
#include "cli/cli.hpp"
#include "drivers/sim/board.hpp"
#include "formats/calibration_file.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

// A cell that differs from every built-in default, so that a calibration that returned defaults would fail.
app::Config truth_config() {
  app::Config cfg = app::default_config();
  auto& k = cfg.rig.camera.intrinsics;
  k.fx_px = 1093.4;
  k.fy_px = 1096.1;
  k.cx_px = 509.8;
  k.cy_px = 386.2;
  k.k1 = -0.07;
  k.k2 = 0.03;
  k.p1 = 6e-4;
  k.p2 = -2e-4;
  k.k3 = 0.0;
  cfg.rig.camera.roll_deg = 0.7;
  cfg.rig.camera.triangulation_angle_deg = 28.0;
  cfg.rig.laser.normal_world = Eigen::Vector3d(1.0, 0.012, -0.021).normalized();
  cfg.rig.laser.offset_m = 0.0023;
  const Eigen::Vector3d& n = cfg.rig.laser.normal_world;
  const Eigen::Vector3d emitter(0.0, 0.55, 1.5);
  cfg.rig.laser.emitter_world_m =
      emitter + (cfg.rig.laser.offset_m - n.dot(emitter)) * n;  // the emitter lies in its plane
  cfg.rig.conveyor.counts_per_mm = 9.87;
  cfg.sim.camera_noise_seed = 5;
  return cfg;
}

using test::TempDir;

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

void write_file(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
}

struct Run {
  int code;
  std::string out, err;
};

std::string drain(std::FILE* f) {
  std::rewind(f);
  std::string s;
  char buf[4096];
  std::size_t n = 0;
  while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) s.append(buf, n);
  std::fclose(f);
  return s;
}

Run calibrate(const std::vector<std::string>& args, const app::Config& config) {
  std::FILE* out = std::tmpfile();
  std::FILE* err = std::tmpfile();
  REQUIRE(out != nullptr);
  REQUIRE(err != nullptr);
  const int code = cli::run_calibrate(args, config, out, err);
  return {code, drain(out), drain(err)};
}

// Exact projections of a board pose by OpenCV (independent of algo::project).
std::vector<Eigen::Vector2d> opencv_project(const algo::Intrinsics& k, const Eigen::Isometry3d& to_camera,
                                            const std::vector<Eigen::Vector3d>& points) {
  cv::Mat camera = (cv::Mat_<double>(3, 3) << k.fx_px, 0, k.cx_px, 0, k.fy_px, k.cy_px, 0, 0, 1);
  cv::Mat dist = (cv::Mat_<double>(1, 5) << k.k1, k.k2, k.p1, k.p2, k.k3);
  cv::Mat r(3, 3, CV_64F), rvec, tvec(3, 1, CV_64F);
  for (int i = 0; i < 3; ++i) {
    tvec.at<double>(i) = to_camera.translation()[i];
    for (int j = 0; j < 3; ++j) r.at<double>(i, j) = to_camera.linear()(i, j);
  }
  cv::Rodrigues(r, rvec);
  std::vector<cv::Point3d> world;
  for (const auto& p : points) world.emplace_back(p.x(), p.y(), p.z());
  std::vector<cv::Point2d> px;
  cv::projectPoints(world, rvec, tvec, camera, dist, px);
  std::vector<Eigen::Vector2d> out;
  for (const auto& p : px) out.emplace_back(p.x, p.y);
  return out;
}

// What an ideal detector measures for each dot: the centre (area centroid) of the dot's image, from OpenCV's
// projection of its outline. Perspective moves it off the image of the dot's centre by a few hundredths of a
// pixel, which the calibration must account for.
std::vector<Eigen::Vector2d> project_dots(const algo::Intrinsics& k, const Eigen::Isometry3d& board_to_camera,
                                          const algo::BoardSpec& board) {
  constexpr int kOutline = 720;
  const double radius = 0.5e-3 * board.dot_diameter_mm;
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < board.dot_count(); ++i) {
    for (int j = 0; j < kOutline; ++j) {
      const double t = 2.0 * std::numbers::pi * j / kOutline;
      points.emplace_back(board.dot_m(i).x() + radius * std::cos(t), board.dot_m(i).y() + radius * std::sin(t), 0.0);
    }
  }
  const std::vector<Eigen::Vector2d> outline = opencv_project(k, board_to_camera, points);
  std::vector<Eigen::Vector2d> centres;
  for (int i = 0; i < board.dot_count(); ++i) {
    const Eigen::Vector2d* p = outline.data() + static_cast<std::ptrdiff_t>(i) * kOutline;
    double area = 0.0;
    Eigen::Vector2d sum = Eigen::Vector2d::Zero();
    for (int j = 0; j < kOutline; ++j) {  // shoelace centroid, relative to the first vertex
      const Eigen::Vector2d a = p[j] - p[0], b = p[(j + 1) % kOutline] - p[0];
      const double cross = a.x() * b.y() - b.x() * a.y();
      area += cross;
      sum += (a + b) * cross;
    }
    centres.push_back(p[0] + sum / (3.0 * area));
  }
  return centres;
}

Eigen::Isometry3d cell_to_camera(const algo::CameraPose& pose) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = pose.r_cam_world;
  t.translation() = pose.t_cam_world;
  return t;
}

// A board pose in the camera frame: field centre at `centre`, turned by the given angles about its own axes.
Eigen::Isometry3d board_in_camera(const algo::BoardSpec& board, const Eigen::Vector3d& centre, double tilt_x_deg,
                                  double tilt_y_deg, double roll_deg) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = (Eigen::AngleAxisd(tilt_x_deg * kDeg, Eigen::Vector3d::UnitX()) *
                Eigen::AngleAxisd(tilt_y_deg * kDeg, Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(roll_deg * kDeg, Eigen::Vector3d::UnitZ()))
                   .toRotationMatrix();
  const Eigen::Vector2d half = 0.5 * board.field_size_m();
  t.translation() = centre - t.linear() * Eigen::Vector3d(half.x(), half.y(), 0.0);
  return t;
}

double angle_deg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) / kDeg;
}

// A complete, plausible calibration file to start the bad-input cases from.
formats::CalibrationRecord sample_record() {
  const sim::Rig rig = sim::make_rig(truth_config().rig);
  formats::CalibrationRecord r;
  r.has_camera = r.has_laser = r.has_conveyor = true;
  r.sensor.intrinsics = rig.params.camera.intrinsics;
  r.sensor.camera_pose = rig.camera_pose;
  r.sensor.laser_normal = rig.laser_normal_world;
  r.sensor.laser_offset_m = rig.laser_offset_m;
  r.sensor.mm_per_count = 0.1013;
  r.sensor.reprojection_rms_px = 0.05;
  r.sensor.laser_residual_mm = 0.09;
  r.camera_date = r.laser_date = r.conveyor_date = "2024-01-02 03:04:05";
  r.camera_views = 8;
  r.reference_rms_px = 0.04;
  r.laser_points = 500;
  r.conveyor_angle_deg = 0.1;
  return r;
}

}  // namespace

// --- End to end on the simulated cell ------------------------------------------------------------------------

TEST_CASE("The technician procedure on the simulated cell recovers camera, laser plane and conveyor scale",
          "[calibration][sim]") {
  // GIVEN a simulated cell whose camera, laser and encoder differ from the defaults
  const app::Config config = truth_config();
  const sim::Rig truth = sim::make_rig(config.rig);
  const auto& k_true = truth.params.camera.intrinsics;
  TempDir tmp;
  const std::string file = tmp.file("calibration.yaml");

  // WHEN the three steps run on rendered board pictures only (--sim renders, then calibrates from the folder)
  const Run camera = calibrate({"camera", "--sim", "--out", tmp.file("camera"), "--calibration", file}, config);
  INFO(camera.out << camera.err);
  REQUIRE(camera.code == cli::kExitOk);
  const std::string after_camera = read_file(file);
  auto cam = formats::load_calibration(file);
  REQUIRE(cam.ok());
  CHECK(cam->has_camera);
  CHECK_FALSE(cam->has_laser);

  const Run laser = calibrate({"laser", "--sim", "--out", tmp.file("laser"), "--calibration", file}, config);
  INFO(laser.out << laser.err);
  REQUIRE(laser.code == cli::kExitOk);
  const Run conveyor = calibrate({"conveyor", "--sim", "--out", tmp.file("conveyor"), "--calibration", file}, config);
  INFO(conveyor.out << conveyor.err);
  REQUIRE(conveyor.code == cli::kExitOk);

  auto result = formats::load_sensor_calibration(file);
  REQUIRE(result.ok());
  const algo::SensorCalibration& c = *result;

  // THEN every figure is within the project's acceptance limits of the simulator's truth
  const auto& k = c.intrinsics;
  const double fx_err_pct = 100.0 * (k.fx_px / k_true.fx_px - 1.0);
  const double fy_err_pct = 100.0 * (k.fy_px / k_true.fy_px - 1.0);
  const double cx_err = k.cx_px - k_true.cx_px, cy_err = k.cy_px - k_true.cy_px;
  const Eigen::Vector3d centre_err_mm = 1e3 * (c.camera_pose.centre_world() - truth.camera_centre_world);
  const double rotation_err_deg =
      std::acos(std::clamp(
          0.5 * ((c.camera_pose.r_cam_world * truth.camera_pose.r_cam_world.transpose()).trace() - 1.0), -1.0, 1.0)) /
      kDeg;
  const double normal_err_deg = angle_deg(c.laser_normal, truth.laser_normal_world);
  const double offset_err_mm = 1e3 * (c.laser_offset_m - truth.laser_offset_m);
  const double mm_per_count_true = 1.0 / config.rig.conveyor.counts_per_mm;
  const double scale_err_pct = 100.0 * (c.mm_per_count / mm_per_count_true - 1.0);
  std::printf(
      "calibration accuracy on the simulated cell:\n"
      "  fx %+.4f %%  fy %+.4f %%  cx %+.3f px  cy %+.3f px  (reprojection RMS %.4f px)\n"
      "  camera centre error %.3f mm, rotation error %.4f deg\n"
      "  laser normal %.5f deg, offset %+.4f mm (residual %.4f mm)\n"
      "  mm per count %+.4f %%\n",
      fx_err_pct, fy_err_pct, cx_err, cy_err, c.reprojection_rms_px, centre_err_mm.norm(), rotation_err_deg,
      normal_err_deg, offset_err_mm, c.laser_residual_mm, scale_err_pct);
  CHECK(std::abs(fx_err_pct) < 0.2);
  CHECK(std::abs(fy_err_pct) < 0.2);
  CHECK(std::abs(cx_err) < 1.0);
  CHECK(std::abs(cy_err) < 1.0);
  CHECK(centre_err_mm.norm() < 2.0);
  CHECK(rotation_err_deg < 0.05);
  CHECK(normal_err_deg < 0.1);
  CHECK(std::abs(offset_err_mm) < 0.3);
  CHECK(std::abs(scale_err_pct) < 0.2);

  // AND each later step kept the camera section and left the previous file as a dated backup
  auto final_record = formats::load_calibration(file);
  REQUIRE(final_record.ok());
  auto camera_section = [](const std::string& text) {
    const std::size_t from = text.find("\ncamera:");
    const std::size_t to = std::min(text.find("\nlaser:"), text.find("\nchecksum_fnv1a64:"));
    return text.substr(from, to - from);
  };
  CHECK(final_record->camera_date == cam->camera_date);
  CHECK(camera_section(read_file(file)) == camera_section(after_camera));
  int backups = 0;
  bool camera_file_backed_up = false;
  for (const auto& entry : fs::directory_iterator(fs::path(file).parent_path())) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("calibration.yaml.", 0) == 0 && name.size() > 4 && name.substr(name.size() - 4) == ".bak") {
      ++backups;
      camera_file_backed_up = camera_file_backed_up || read_file(entry.path().string()) == after_camera;
    }
  }
  CHECK(backups == 2);
  CHECK(camera_file_backed_up);
}

// --- Board rendering and detection ---------------------------------------------------------------------------

TEST_CASE("A rendered board is detected with its dots at their projected centres, in board order",
          "[calibration][board]") {
  // GIVEN a board held tilted in front of the simulated camera
  const app::Config config = truth_config();
  const sim::Rig rig = sim::make_rig(config.rig);
  sim::BoardRenderer renderer(rig, 3);
  const algo::BoardSpec board;
  const auto poses = sim::plan_camera_views(renderer, board);
  REQUIRE(poses.size() >= 6);
  cv::Mat image;
  renderer.render(board, poses[1], 11, image);

  // WHEN it is detected
  auto dots = algo::detect_board(image, board);
  REQUIRE(dots.ok());

  // THEN each dot lies within a few hundredths of a pixel of the centre of its image (OpenCV projection)
  const auto truth = project_dots(rig.params.camera.intrinsics, cell_to_camera(rig.camera_pose) * poses[1], board);
  double sum_sq = 0.0, worst = 0.0;
  for (std::size_t i = 0; i < truth.size(); ++i) {
    const double e = ((*dots)[i] - truth[i]).norm();
    sum_sq += e * e;
    worst = std::max(worst, e);
  }
  const double rms = std::sqrt(sum_sq / static_cast<double>(truth.size()));
  std::printf("dot detection error on a rendered view: RMS %.4f px, worst %.4f px\n", rms, worst);
  CHECK(rms < 0.05);
  CHECK(worst < 0.15);

  // AND a board described with the wrong number of rows is not found, with a message that says what to check
  algo::BoardSpec wrong = board;
  wrong.rows = 11;
  auto missing = algo::detect_board(image, wrong);
  REQUIRE_FALSE(missing.ok());
  CHECK_THAT(missing.error().message, Catch::Contains("no 11 x 6 dot board found") && Catch::Contains("rows/cols"));
}

TEST_CASE("Laser line centres are found to a small fraction of a pixel on an analytic Gaussian stripe",
          "[calibration][stripe]") {
  // GIVEN a stripe whose centre moves sub-pixel from row to row, on a dim background, and a hot pixel elsewhere
  constexpr int kWidth = 200, kHeight = 60;
  constexpr double kSigmaPx = 1.2, kPeakDn = 150.0, kBackgroundDn = 10.0;
  cv::Mat image(kHeight, kWidth, CV_8UC1);
  auto centre_of = [](int row) { return 80.3 + 0.137 * row; };
  for (int y = 0; y < kHeight; ++y) {
    for (int x = 0; x < kWidth; ++x) {
      const double d = x - centre_of(y);
      const double v = y == 30 ? kBackgroundDn : kBackgroundDn + kPeakDn * std::exp(-d * d / (2 * kSigmaPx * kSigmaPx));
      image.at<std::uint8_t>(y, x) = static_cast<std::uint8_t>(std::lround(v));
    }
  }
  image.at<std::uint8_t>(30, 150) = 255;  // a hot pixel in the one row without stripe

  // WHEN the centres are extracted
  const auto centres = algo::laser_line_centres(image);

  // THEN every stripe row is found within 0.03 px (8-bit quantisation only), and the hot pixel is not a stripe
  REQUIRE(centres.size() == kHeight - 1);
  for (const auto& c : centres) {
    CHECK(c.y() != 30.0);
    CHECK(std::abs(c.x() - centre_of(static_cast<int>(c.y()))) < 0.03);
  }
}

// --- Algorithms on exact projections --------------------------------------------------------------------------

TEST_CASE("Intrinsic calibration recovers the camera from exact views and refuses too few or parallel views",
          "[calibration][intrinsics]") {
  const algo::BoardSpec board;
  const algo::Intrinsics truth = truth_config().rig.camera.intrinsics;
  struct View {
    double x, y, z, tx, ty, roll;
  };
  const View specs[] = {{-0.3, -0.2, 1.5, 28, -22, 6},  {0.3, -0.2, 1.5, 25, 30, -5}, {-0.3, 0.2, 1.5, -30, -25, 10},
                        {0.3, 0.2, 1.5, -25, 30, -3},   {0.0, 0.0, 1.3, 5, 40, 0},    {0.0, 0.0, 1.9, 40, -5, 15},
                        {-0.4, 0.0, 1.6, 10, -38, -10}, {0.4, 0.0, 1.6, -12, 36, 4}};
  std::vector<std::vector<Eigen::Vector2d>> views;
  for (const View& s : specs) {
    views.push_back(project_dots(truth, board_in_camera(board, {s.x, s.y, s.z}, s.tx, s.ty, s.roll), board));
  }

  SECTION("exact views give the camera back") {
    auto result = algo::calibrate_intrinsics(views, board, truth.width_px, truth.height_px);
    REQUIRE(result.ok());
    CHECK(result->rms_px < 1e-3);
    CHECK(result->intrinsics.fx_px == Approx(truth.fx_px).epsilon(1e-5));
    CHECK(result->intrinsics.fy_px == Approx(truth.fy_px).epsilon(1e-5));
    CHECK(result->intrinsics.cx_px == Approx(truth.cx_px).margin(0.01));
    CHECK(result->intrinsics.cy_px == Approx(truth.cy_px).margin(0.01));
    CHECK(result->intrinsics.k1 == Approx(truth.k1).margin(1e-4));
  }
  SECTION("four views are refused, saying how many are needed") {
    views.resize(4);
    auto result = algo::calibrate_intrinsics(views, board, truth.width_px, truth.height_px);
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("only 4 board views") && Catch::Contains("at least 6"));
  }
  SECTION("parallel views are refused, saying to tilt the board") {
    views.clear();
    for (const View& s : specs)
      views.push_back(project_dots(truth, board_in_camera(board, {s.x, s.y, s.z}, 0, 0, 0), board));
    auto result = algo::calibrate_intrinsics(views, board, truth.width_px, truth.height_px);
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("tilt the board"));
  }
}

TEST_CASE("The laser plane is recovered from exact stripe points and a degenerate set of boards is refused",
          "[calibration][laser]") {
  const sim::Rig rig = sim::make_rig(truth_config().rig);
  const algo::Intrinsics& k = rig.params.camera.intrinsics;
  const algo::BoardSpec board;
  const Eigen::Isometry3d to_camera = cell_to_camera(rig.camera_pose);
  const Eigen::Vector3d n = rig.laser_normal_world;
  const double d = rig.laser_offset_m;

  // A view: the board's dots, and the pixels of the analytic cut of the laser plane with the board's plane.
  auto make_view = [&](const Eigen::Isometry3d& board_to_cell) {
    algo::LaserView v;
    v.dots = project_dots(k, to_camera * board_to_cell, board);
    const Eigen::Vector3d o = board_to_cell.translation(), u = board_to_cell.linear().col(0),
                          w = board_to_cell.linear().col(1);
    std::vector<Eigen::Vector3d> cut;
    for (double vv = board.plate_min_m().y(); vv <= board.plate_max_m().y(); vv += 0.002) {
      // n . (o + s u + vv w) = d  ->  s
      const double s = (d - n.dot(o) - vv * n.dot(w)) / n.dot(u);
      cut.push_back(o + s * u + vv * w);
    }
    v.stripe_px = opencv_project(k, to_camera, cut);
    return v;
  };
  const auto poses = sim::plan_laser_views(rig, board);
  REQUIRE(poses.size() == 3);

  SECTION("three poses give the plane back") {
    auto result = algo::calibrate_laser_plane(k, rig.camera_pose, board,
                                              {make_view(poses[0]), make_view(poses[1]), make_view(poses[2])});
    REQUIRE(result.ok());
    CHECK(angle_deg(result->normal, n) < 1e-4);
    CHECK(result->offset_m == Approx(d).margin(1e-6));
    CHECK(result->residual_rms_mm < 1e-3);
  }
  SECTION("one pose is refused") {
    auto result = algo::calibrate_laser_plane(k, rig.camera_pose, board, {make_view(poses[0])});
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("at least 2 board poses"));
  }
  SECTION("the same pose twice is refused as one line") {
    auto result = algo::calibrate_laser_plane(k, rig.camera_pose, board, {make_view(poses[1]), make_view(poses[1])});
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("nearly one line"));
  }
  SECTION("parallel boards in one plane, shifted along it, are refused as one line") {
    const Eigen::Isometry3d shifted = Eigen::Translation3d(0.05 * poses[1].linear().col(1)) * poses[1];
    auto result = algo::calibrate_laser_plane(k, rig.camera_pose, board, {make_view(poses[1]), make_view(shifted)});
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("parallel"));
  }
}

TEST_CASE("The conveyor scale is the board's travel per count, and backward counting or a short move is refused",
          "[calibration][conveyor]") {
  const sim::Rig rig = sim::make_rig(truth_config().rig);
  const algo::Intrinsics& k = rig.params.camera.intrinsics;
  const algo::BoardSpec board;
  const Eigen::Isometry3d to_camera = cell_to_camera(rig.camera_pose);
  const Eigen::Isometry3d start = algo::fixture_board_to_cell({-0.32, 0.79, 0.10});
  auto views_along = [&](const Eigen::Vector3d& direction, double mm_per_count, std::vector<std::int64_t> counts) {
    std::vector<algo::ConveyorView> views;
    for (std::int64_t c : counts) {
      const Eigen::Isometry3d pose = Eigen::Translation3d(direction.normalized() * (c * mm_per_count * 1e-3)) * start;
      views.push_back({project_dots(k, to_camera * pose, board), c});
    }
    return views;
  };

  SECTION("exact views along x give the scale back, without warnings") {
    auto result = algo::calibrate_conveyor(k, rig.camera_pose, board,
                                           views_along(Eigen::Vector3d::UnitX(), 0.0987, {0, 1013, 2026}));
    REQUIRE(result.ok());
    CHECK(result->mm_per_count == Approx(0.0987).epsilon(1e-6));
    CHECK(result->angle_to_x_deg < 1e-3);
    CHECK(result->warnings.empty());
  }
  SECTION("motion 3 degrees off the x axis is measured and warned about") {
    const Eigen::Vector3d skew(std::cos(3 * kDeg), 0.0, std::sin(3 * kDeg));
    auto result = algo::calibrate_conveyor(k, rig.camera_pose, board, views_along(skew, 0.1, {0, 2000}));
    REQUIRE(result.ok());
    CHECK(result->angle_to_x_deg == Approx(3.0).margin(0.01));
    REQUIRE(result->warnings.size() == 1);
    CHECK_THAT(result->warnings[0], Catch::Contains("away from the cell x axis"));
  }
  SECTION("counts that fall while the carrier moves downstream are refused") {
    auto result =
        algo::calibrate_conveyor(k, rig.camera_pose, board, views_along(Eigen::Vector3d::UnitX(), -0.1, {0, 2000}));
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("swap the encoder A and B"));
  }
  SECTION("a 10 mm move is refused") {
    auto result =
        algo::calibrate_conveyor(k, rig.camera_pose, board, views_along(Eigen::Vector3d::UnitX(), 0.1, {0, 100}));
    REQUIRE_FALSE(result.ok());
    CHECK_THAT(result.error().message, Catch::Contains("about 200 mm"));
  }
}

// --- calibration.yaml ----------------------------------------------------------------------------------------

TEST_CASE("calibration.yaml round-trips exactly and refuses truncated, corrupt and edited files",
          "[calibration][file]") {
  TempDir tmp;
  const std::string file = tmp.file("calibration.yaml");
  const formats::CalibrationRecord record = sample_record();
  const std::string text = formats::calibration_yaml(record);

  SECTION("a saved file loads back to the same numbers") {
    auto backup = formats::save_calibration(file, record);
    REQUIRE(backup.ok());
    CHECK(backup->empty());  // nothing to back up the first time
    auto loaded = formats::load_calibration(file);
    REQUIRE(loaded.ok());
    CHECK(loaded->sensor.intrinsics.fx_px == record.sensor.intrinsics.fx_px);
    CHECK(loaded->sensor.intrinsics.k2 == record.sensor.intrinsics.k2);
    CHECK((loaded->sensor.camera_pose.r_cam_world - record.sensor.camera_pose.r_cam_world).norm() < 1e-15);
    CHECK((loaded->sensor.camera_pose.t_cam_world - record.sensor.camera_pose.t_cam_world).norm() < 1e-12);
    CHECK(loaded->sensor.laser_normal == record.sensor.laser_normal);
    CHECK(loaded->sensor.mm_per_count == record.sensor.mm_per_count);
  }
  SECTION("a second save keeps the first file as a dated backup") {
    REQUIRE(formats::save_calibration(file, record).ok());
    formats::CalibrationRecord changed = record;
    changed.sensor.mm_per_count = 0.2;
    auto backup = formats::save_calibration(file, changed);
    REQUIRE(backup.ok());
    CHECK_THAT(*backup, Catch::StartsWith(file + ".") && Catch::EndsWith(".bak"));
    CHECK(read_file(*backup) == text);
    CHECK(formats::load_calibration(file)->sensor.mm_per_count == 0.2);
  }
  SECTION("every truncation of the file is refused, never half-used") {
    // Everything short of the final newline loses data (the newline alone carries none).
    for (std::size_t length = 0; length + 1 < text.size(); length += 7) {
      write_file(file, text.substr(0, length));
      auto loaded = formats::load_calibration(file);
      INFO("truncated to " << length << " bytes");
      CHECK_FALSE(loaded.ok());
    }
  }
  SECTION("a value out of range is refused with file, line and key") {
    std::string bad = text;
    const std::size_t at = bad.find("  fx_px: ");
    REQUIRE(at != std::string::npos);
    bad.replace(at, bad.find('\n', at) - at, "  fx_px: -3");
    write_file(file, bad);
    auto loaded = formats::load_calibration(file);
    REQUIRE_FALSE(loaded.ok());
    const auto line = std::count(bad.begin(), bad.begin() + static_cast<std::ptrdiff_t>(at), '\n') + 1;
    CHECK_THAT(loaded.error().message,
               Catch::Contains(file + ":" + std::to_string(line) + ":") && Catch::Contains("camera.fx_px"));
  }
  SECTION("a laser or support normal that is not a unit vector is refused, even in a well-sealed file") {
    // Triangulation and support removal read n . p = offset as metres only when |n| = 1.
    formats::CalibrationRecord long_laser = record;
    long_laser.sensor.laser_normal *= 0.999;  // each component stays within [-1, 1]: only the length is wrong
    formats::CalibrationRecord long_support = record;
    long_support.has_support = true;
    long_support.support = {Eigen::Vector3d(0.0, 0.0, 0.999), 0.05};
    long_support.support_date = record.laser_date;
    long_support.support_points = 5000;
    for (const auto& [bad, key] : {std::pair{long_laser, "laser.normal"}, std::pair{long_support, "support.normal"}}) {
      REQUIRE(formats::save_calibration(file, bad).ok());
      auto loaded = formats::load_calibration(file);
      REQUIRE_FALSE(loaded.ok());
      CHECK_THAT(loaded.error().message,
                 Catch::Contains(file + ":") && Catch::Contains(std::string(key) + ": must be a unit vector"));
    }
  }
  SECTION("an edited number that stays in range fails the checksum") {
    std::string edited = text;
    const std::size_t at = edited.find("  mm_per_count: 0.1013");
    REQUIRE(at != std::string::npos);
    edited.replace(at, std::string("  mm_per_count: 0.1013").size(), "  mm_per_count: 0.1014");
    write_file(file, edited);
    auto loaded = formats::load_calibration(file);
    REQUIRE_FALSE(loaded.ok());
    CHECK_THAT(loaded.error().message, Catch::Contains("checksum_fnv1a64") && Catch::Contains("backup"));
  }
  SECTION("production refuses a file without every section") {
    formats::CalibrationRecord camera_only = record;
    camera_only.has_laser = camera_only.has_conveyor = false;
    REQUIRE(formats::save_calibration(file, camera_only).ok());
    REQUIRE(formats::load_calibration(file).ok());
    auto sensor = formats::load_sensor_calibration(file);
    REQUIRE_FALSE(sensor.ok());
    CHECK_THAT(sensor.error().message, Catch::Contains("calibrate laser"));
  }
}

// --- Bad input through the mode ------------------------------------------------------------------------------

TEST_CASE("Bad calibration input is refused with one line saying what to do, and calibration.yaml is unchanged",
          "[calibration][cli]") {
  // GIVEN a valid calibration in force and a folder of camera pictures
  const app::Config config = truth_config();
  TempDir tmp;
  const std::string file = tmp.file("calibration.yaml");
  REQUIRE(formats::save_calibration(file, sample_record()).ok());
  const std::string before = read_file(file);
  const std::string dir = tmp.file("pictures");
  fs::create_directory(dir);
  const cv::Mat blank(768, 1024, CV_8UC1, cv::Scalar(40));
  for (int i = 0; i < 6; ++i) REQUIRE(cv::imwrite(dir + "/view_0" + std::to_string(i) + ".png", blank));
  REQUIRE(cv::imwrite(dir + "/reference.png", blank));
  auto views_yaml = [&](int count, const std::string& board) {
    std::string y = "format_version: 1\nstep: camera\n" + board + "views:\n";
    for (int i = 0; i < count; ++i) y += "  - {file: view_0" + std::to_string(i) + ".png}\n";
    return y + "reference: {file: reference.png, dot0_cell_m: [-0.22, 0.79, 0.12]}\n";
  };
  write_file(dir + "/views.yaml", views_yaml(6, ""));
  const std::vector<std::string> camera_args = {"camera", "--images", dir, "--calibration", file};

  auto expect_refused = [&](const Run& run, const std::string& what) {
    INFO(run.out << run.err);
    CHECK(run.code == cli::kExitUsage);
    CHECK_THAT(run.err, Catch::Contains(what));
    CHECK(std::count(run.err.begin(), run.err.end(), '\n') == 1);  // one line
    CHECK(read_file(file) == before);
  };

  SECTION("an unreadable picture") {
    write_file(dir + "/view_00.png", "this is not a PNG");
    expect_refused(calibrate(camera_args, config), "view_00.png: cannot read it as an image");
  }
  SECTION("a picture without the board") {
    expect_refused(calibrate(camera_args, config), "view_00.png: no 13 x 6 dot board found (0 dark dots seen");
  }
  SECTION("a board of the wrong size") {
    sim::BoardRenderer renderer(sim::make_rig(config.rig), 3);
    cv::Mat image;
    const auto poses = sim::plan_camera_views(renderer, algo::BoardSpec{});
    REQUIRE_FALSE(poses.empty());
    renderer.render(algo::BoardSpec{}, poses[0], 1, image);
    REQUIRE(cv::imwrite(dir + "/view_00.png", image));
    write_file(dir + "/views.yaml", views_yaml(6, "board: {rows: 11, cols: 6}\n"));
    expect_refused(calibrate(camera_args, config), "no 11 x 6 dot board found");
  }
  SECTION("too few views") {
    write_file(dir + "/views.yaml", views_yaml(3, ""));
    expect_refused(calibrate(camera_args, config), "lists 3 tilted views; at least 6 are needed");
  }
  SECTION("a misspelt key in views.yaml") {
    write_file(dir + "/views.yaml", views_yaml(6, "board: {rowz: 13}\n"));
    expect_refused(calibrate(camera_args, config), "board.rowz: unknown key");
  }
  SECTION("a truncated calibration.yaml") {
    const std::string truncated = before.substr(0, before.size() / 2);
    write_file(file, truncated);
    const Run run = calibrate({"laser", "--images", dir, "--calibration", file}, config);
    INFO(run.err);
    CHECK(run.code == cli::kExitUsage);
    CHECK_THAT(run.err, Catch::Contains("existing calibration is refused") && Catch::Contains("truncated"));
    CHECK(read_file(file) == truncated);
  }
  SECTION("a corrupt calibration.yaml") {
    std::string corrupt = before;
    corrupt.replace(corrupt.find("  cy_px: "), 9, "  cy_px: [");
    write_file(file, corrupt);
    const Run run = calibrate(camera_args, config);
    CHECK(run.code == cli::kExitUsage);
    CHECK_THAT(run.err, Catch::Contains(file + ":") && Catch::Contains("copy a backup over it"));
    CHECK(read_file(file) == corrupt);
  }
  SECTION("the laser step before any camera calibration") {
    fs::remove(file);
    const Run run = calibrate({"laser", "--images", dir, "--calibration", file}, config);
    CHECK(run.code == cli::kExitUsage);
    CHECK_THAT(run.err, Catch::Contains("run 'cellsight calibrate camera' first"));
    CHECK_FALSE(fs::exists(file));
  }
  SECTION("arguments that do not fit") {
    for (const auto& args : std::vector<std::vector<std::string>>{
             {}, {"support"}, {"camera"}, {"camera", "--sim"}, {"camera", "--images", dir, "--sim", "--out", dir}}) {
      const Run run = calibrate(args, config);
      CHECK(run.code == cli::kExitUsage);
      CHECK(std::count(run.err.begin(), run.err.end(), '\n') == 1);
    }
    CHECK(read_file(file) == before);
  }
}
