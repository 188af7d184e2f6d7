// `cellsight calibrate`: views.yaml + pictures -> algo/calibration -> calibration.yaml (or the simulated cell first).
#include "cli/calibrate_mode.hpp"

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <set>

#include "algo/calibration.hpp"
#include "base/atomic_file.hpp"
#include "base/local_time.hpp"
#include "cli/cli.hpp"
#include "drivers/sim/board.hpp"
#include "drivers/sim/random.hpp"
#include "formats/calibration_file.hpp"
#include "formats/yaml_reader.hpp"

namespace cellsight::cli {

const char* const kCalibrateUsage =
    "  calibrate camera   (--images DIR | --sim --out DIR [--seed S]) [--calibration FILE]\n"
    "        camera intrinsics from >= 6 tilted board views, camera pose from the board in the reference fixture\n"
    "  calibrate laser    (--images DIR | --sim --out DIR [--seed S]) [--calibration FILE]\n"
    "        laser plane from >= 2 board poses across the laser (a lamp picture and a laser picture of each)\n"
    "  calibrate conveyor (--images DIR | --sim --out DIR [--seed S]) [--calibration FILE]\n"
    "        encoder scale from the board on the carrier at >= 2 encoder counts about 200 mm apart\n"
    "        DIR holds views.yaml and the PNG pictures; --sim renders them on the simulated cell into DIR first.\n"
    "        Results go to FILE (default: calibration.yaml beside the config); the previous file is kept as\n"
    "        FILE.YYYYMMDD-HHMMSS.bak and stays in force if the step is refused. Run the steps in this order.\n";

namespace {

namespace fs = std::filesystem;

constexpr double kRadToDeg = 180.0 / std::numbers::pi;
constexpr const char* kViewsFile = "views.yaml";
constexpr int kViewsFormatVersion = 1;
constexpr int kPngCompression = 3;
constexpr double kSimStripePeakDn = 180.0;  // the technician sets the laser exposure so the stripe is not saturated

struct Options {
  std::string step;
  std::string images;
  std::string out;
  std::string calibration;
  bool sim = false;
  std::uint64_t seed = 1;
};

std::string first_line(const std::string& text) {
  const std::size_t nl = text.find('\n');
  if (nl == std::string::npos) return text;
  const auto more = std::count(text.begin() + static_cast<std::ptrdiff_t>(nl), text.end(), '\n');
  return text.substr(0, nl) + " (and " + std::to_string(more) + " more problem" + (more == 1 ? "" : "s") + ")";
}

std::string fmt(const char* format, double a, double b = 0.0, double c = 0.0, double d = 0.0, double e = 0.0) {
  char buf[256];
  std::snprintf(buf, sizeof buf, format, a, b, c, d, e);
  return buf;
}

Expected<Options> parse_options(const std::vector<std::string>& args) {
  Options o;
  if (args.empty()) return make_error("calibrate needs a step: camera, laser or conveyor (in that order)");
  o.step = args[0];
  if (o.step != "camera" && o.step != "laser" && o.step != "conveyor") {
    return make_error("unknown calibration step '" + o.step + "': expected camera, laser or conveyor");
  }
  const std::set<std::string> with_value = {"--images", "--out", "--calibration", "--seed", "--config", "--log-level"};
  std::string seed_text;
  for (std::size_t i = 1; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a == "--sim") {
      o.sim = true;
    } else if (with_value.count(a) != 0) {
      if (i + 1 >= args.size()) return make_error(a + " needs a value");
      const std::string& v = args[++i];
      if (a == "--images") o.images = v;
      if (a == "--out") o.out = v;
      if (a == "--calibration") o.calibration = v;
      if (a == "--seed") seed_text = v;
    } else {
      return make_error("unexpected argument '" + a + "' for 'calibrate " + o.step + "'");
    }
  }
  if (o.sim && !o.images.empty()) return make_error("--images and --sim exclude each other: use one");
  if (o.sim && o.out.empty()) return make_error("--sim needs --out DIR (a new folder for the rendered pictures)");
  if (!o.sim && !o.out.empty()) return make_error("--out only applies with --sim");
  if (!o.sim && o.images.empty()) {
    return make_error("calibrate " + o.step + " needs --images DIR (views.yaml and the pictures) or --sim --out DIR");
  }
  if (!seed_text.empty()) {
    if (!o.sim) return make_error("--seed only applies with --sim");
    char* end = nullptr;
    errno = 0;
    const unsigned long long v = std::strtoull(seed_text.c_str(), &end, 10);
    if (*end != '\0' || errno != 0 || seed_text[0] == '-') {
      return make_error("--seed '" + seed_text + "': expected a whole number >= 0");
    }
    o.seed = v;
  }
  return o;
}

// --- views.yaml ---------------------------------------------------------------------------------------------

void read_board(formats::YamlSection s, algo::BoardSpec& b) {
  s.integer("rows", b.rows, 3, 99, "dot rows");
  s.integer("cols", b.cols, 2, 99, "dots per row");
  s.number("spacing_mm", b.spacing_mm, 1.0, 1000.0, "mm");
  s.number("dot_diameter_mm", b.dot_diameter_mm, 0.5, 500.0, "mm");
  s.number("width_mm", b.width_mm, 10.0, 5000.0, "mm");
  s.number("height_mm", b.height_mm, 10.0, 5000.0, "mm");
  if (const std::string why = algo::validate_board(b); !why.empty()) s.error("rows", why);
  s.finish();
}

// DIR/views.yaml, parsed; each step reads its keys through a YamlSection and calls finish().
struct ViewsDoc {
  std::string path;
  YAML::Node node;
};

Expected<ViewsDoc> open_views(const fs::path& dir) {
  ViewsDoc doc;
  doc.path = (dir / kViewsFile).string();
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return make_error(dir.string() + ": no such folder of calibration pictures");
  auto node = formats::load_yaml_file(doc.path);
  if (!node) return node.error();
  doc.node = *node;
  return doc;
}

void read_header(formats::YamlSection& root, const std::string& step, algo::BoardSpec& board) {
  root.require("format_version");
  int version = kViewsFormatVersion;
  root.integer("format_version", version, kViewsFormatVersion, kViewsFormatVersion, "");
  std::string file_step = step;
  root.require("step");
  root.choice("step", file_step, {"camera", "laser", "conveyor"});
  if (file_step != step) root.error("step", "these pictures are for 'calibrate " + file_step + "', not '" + step + "'");
  read_board(root.section("board"), board);
}

fs::path picture_path(const fs::path& dir, const std::string& name) {
  return dir / name;
}

Expected<cv::Mat> read_picture(const fs::path& file) {
  std::error_code ec;
  if (!fs::is_regular_file(file, ec)) {
    return make_error(file.string() + ": no such picture: take it again or correct its name in views.yaml");
  }
  cv::Mat image;
  try {
    image = cv::imread(file.string(), cv::IMREAD_GRAYSCALE);
  } catch (const cv::Exception&) {  // some decoders throw on damaged files; treated like an unreadable one
    image.release();
  }
  if (image.empty())
    return make_error(file.string() + ": cannot read it as an image (PNG expected): take the picture again");
  return image;
}

Status check_size(const fs::path& file, const cv::Mat& image, int width_px, int height_px) {
  if (image.cols == width_px && image.rows == height_px) return {};
  char buf[160];
  std::snprintf(buf, sizeof buf, ": %d x %d pixels, the camera gives %d x %d: use full-size pictures from this camera",
                image.cols, image.rows, width_px, height_px);
  return make_error(file.string() + buf);
}

Expected<std::vector<Eigen::Vector2d>> find_board(const fs::path& file, const cv::Mat& image,
                                                  const algo::BoardSpec& board) {
  auto dots = algo::detect_board(image, board);
  if (!dots) return make_error(file.string() + ": " + dots.error().message);
  return dots;
}

// --- Steps --------------------------------------------------------------------------------------------------

Expected<std::string> camera_step(const fs::path& dir, formats::CalibrationRecord& record) {
  auto doc = open_views(dir);
  if (!doc) return doc.error();
  formats::YamlErrors errors(doc->path);
  formats::YamlSection root(doc->node, "", &errors);
  algo::BoardSpec board;
  read_header(root, "camera", board);
  std::vector<std::string> files;
  for (formats::YamlSection v : root.list("views")) {
    std::string file;
    v.require("file");
    v.text("file", file);
    v.finish();
    files.push_back(file);
  }
  root.require("reference");
  formats::YamlSection ref = root.section("reference");
  std::string ref_file;
  Eigen::Vector3d dot0 = Eigen::Vector3d::Zero();
  ref.require("file");
  ref.require("dot0_cell_m");
  ref.text("file", ref_file);
  ref.vec3("dot0_cell_m", dot0, -10.0, 10.0, "m");
  ref.finish();
  root.finish();
  if (!errors.empty()) return make_error(first_line(errors.joined()));
  const algo::CameraCalibrationOptions options;
  if (static_cast<int>(files.size()) < options.min_views) {
    return make_error(doc->path + " lists " + std::to_string(files.size()) + " tilted views; at least " +
                      std::to_string(options.min_views) +
                      " are needed: take more pictures with the board tilted 20-40 degrees in different directions");
  }

  std::vector<std::vector<Eigen::Vector2d>> views;
  int width = 0, height = 0;
  files.push_back(ref_file);  // read and detected like the others; used for the pose only
  for (const std::string& name : files) {
    const fs::path file = picture_path(dir, name);
    auto image = read_picture(file);
    if (!image) return image.error();
    if (width == 0) {
      width = image->cols;
      height = image->rows;
    }
    if (auto ok = check_size(file, *image, width, height); !ok) return ok.error();
    auto dots = find_board(file, *image, board);
    if (!dots) return dots.error();
    views.push_back(std::move(*dots));
  }
  const std::vector<Eigen::Vector2d> reference = views.back();
  views.pop_back();

  auto intrinsics = algo::calibrate_intrinsics(views, board, width, height, options);
  if (!intrinsics) return intrinsics.error();
  auto pose = algo::camera_pose_from_reference(intrinsics->intrinsics, board, reference,
                                               algo::fixture_board_to_cell(dot0), options.max_rms_px);
  if (!pose) return make_error(ref_file + ": " + pose.error().message);

  record.has_camera = true;
  record.camera_date = base::local_time_text();
  record.camera_views = static_cast<int>(views.size());
  record.sensor.intrinsics = intrinsics->intrinsics;
  record.sensor.camera_pose = pose->camera_pose;
  record.sensor.reprojection_rms_px = intrinsics->rms_px;
  record.reference_rms_px = pose->rms_px;

  const auto& k = intrinsics->intrinsics;
  const Eigen::Vector3d centre = pose->camera_pose.centre_world();
  std::string s = "camera calibrated from " + std::to_string(views.size()) + " views and " + ref_file + " (board " +
                  std::to_string(board.rows) + " x " + std::to_string(board.cols) + " dots)\n";
  s += fmt("  reprojection_rms_px: %.4f (limit %.2f)\n", intrinsics->rms_px, options.max_rms_px);
  s += fmt("  reference_rms_px: %.4f\n", pose->rms_px);
  s += fmt("  fx_px: %.3f\n  fy_px: %.3f\n  cx_px: %.3f\n  cy_px: %.3f\n", k.fx_px, k.fy_px, k.cx_px, k.cy_px);
  s += fmt("  distortion_k1_k2_p1_p2_k3: %.5f %.5f %.6f %.6f %.5f\n", k.k1, k.k2, k.p1, k.p2, k.k3);
  s += fmt("  tilt_spread_deg: %.1f\n  coverage: %.2f\n", intrinsics->tilt_spread_deg, intrinsics->coverage);
  s += fmt("  camera_centre_m: %.4f %.4f %.4f\n", centre.x(), centre.y(), centre.z());
  for (const auto& w : intrinsics->warnings) s += "warning: " + w + "\n";
  if (record.has_laser || record.has_conveyor) {
    s += "note: the laser and conveyor sections were measured with the previous camera calibration: run "
         "'calibrate laser' and 'calibrate conveyor' again\n";
  }
  return s;
}

Expected<std::string> laser_step(const fs::path& dir, formats::CalibrationRecord& record) {
  auto doc = open_views(dir);
  if (!doc) return doc.error();
  formats::YamlErrors errors(doc->path);
  formats::YamlSection root(doc->node, "", &errors);
  algo::BoardSpec board;
  read_header(root, "laser", board);
  double exposure_us = 0.0;  // of the laser pictures: a note for the record, not used in the computation
  root.number("exposure_us", exposure_us, 1.0, 1e6, "us");
  std::vector<std::pair<std::string, std::string>> files;
  for (formats::YamlSection v : root.list("views")) {
    std::pair<std::string, std::string> f;
    v.require("board");
    v.require("laser");
    v.text("board", f.first);
    v.text("laser", f.second);
    v.finish();
    files.push_back(f);
  }
  root.finish();
  if (!errors.empty()) return make_error(first_line(errors.joined()));
  if (files.size() < 2) {
    return make_error(doc->path + " lists " + std::to_string(files.size()) +
                      " board poses; the laser plane needs at least 2 (3 recommended) at different depths and tilts");
  }
  const auto& k = record.sensor.intrinsics;
  std::vector<algo::LaserView> views;
  for (const auto& [board_name, laser_name] : files) {
    algo::LaserView view;
    const fs::path board_file = picture_path(dir, board_name), laser_file = picture_path(dir, laser_name);
    auto lamp = read_picture(board_file);
    if (!lamp) return lamp.error();
    if (auto ok = check_size(board_file, *lamp, k.width_px, k.height_px); !ok) return ok.error();
    auto dots = find_board(board_file, *lamp, board);
    if (!dots) return dots.error();
    view.dots = std::move(*dots);
    auto line = read_picture(laser_file);
    if (!line) return line.error();
    if (auto ok = check_size(laser_file, *line, k.width_px, k.height_px); !ok) return ok.error();
    view.stripe_px = algo::laser_line_centres(*line);
    views.push_back(std::move(view));
  }
  auto plane = algo::calibrate_laser_plane(k, record.sensor.camera_pose, board, views);
  if (!plane) return plane.error();

  record.has_laser = true;
  record.laser_date = base::local_time_text();
  record.sensor.laser_normal = plane->normal;
  record.sensor.laser_offset_m = plane->offset_m;
  record.sensor.laser_residual_mm = plane->residual_rms_mm;
  record.laser_points = plane->points_used;

  const algo::LaserCalibrationOptions options;
  const Eigen::Vector3d& n = plane->normal;
  std::string s = "laser plane calibrated from " + std::to_string(views.size()) + " board poses (" +
                  std::to_string(plane->points_used) + " stripe points, " + std::to_string(plane->points_rejected) +
                  " rejected)\n";
  s += fmt("  laser_residual_mm: %.4f (limit %.2f)\n", plane->residual_rms_mm, options.max_residual_mm);
  s += fmt("  laser_normal: %.6f %.6f %.6f\n", n.x(), n.y(), n.z());
  s += fmt("  laser_offset_mm: %.4f\n", plane->offset_m * 1e3);
  s += fmt("  laser_tilt_from_x_deg: %.4f\n", std::acos(std::clamp(n.x(), -1.0, 1.0)) * kRadToDeg);
  s += fmt("  point_spread_mm: %.1f\n", plane->spread_mm);
  std::string per_view = "  points_per_view:";
  for (int c : plane->points_per_view) per_view += " " + std::to_string(c);
  return s + per_view + "\n";
}

Expected<std::string> conveyor_step(const fs::path& dir, formats::CalibrationRecord& record) {
  auto doc = open_views(dir);
  if (!doc) return doc.error();
  formats::YamlErrors errors(doc->path);
  formats::YamlSection root(doc->node, "", &errors);
  algo::BoardSpec board;
  read_header(root, "conveyor", board);
  std::vector<std::pair<std::string, std::int64_t>> files;
  for (formats::YamlSection v : root.list("views")) {
    std::pair<std::string, std::int64_t> f{"", 0};
    v.require("file");
    v.require("encoder_counts");
    v.text("file", f.first);
    constexpr std::int64_t kMaxCounts = std::int64_t{1} << 62;
    v.integer("encoder_counts", f.second, -kMaxCounts, kMaxCounts, "counts");
    v.finish();
    files.push_back(f);
  }
  root.finish();
  if (!errors.empty()) return make_error(first_line(errors.joined()));
  if (files.size() < 2) {
    return make_error(doc->path + " lists " + std::to_string(files.size()) +
                      " carrier positions; the conveyor scale needs at least 2 (3 recommended) about 100 mm apart");
  }
  const auto& k = record.sensor.intrinsics;
  std::vector<algo::ConveyorView> views;
  for (const auto& [name, counts] : files) {
    const fs::path file = picture_path(dir, name);
    auto image = read_picture(file);
    if (!image) return image.error();
    if (auto ok = check_size(file, *image, k.width_px, k.height_px); !ok) return ok.error();
    auto dots = find_board(file, *image, board);
    if (!dots) return dots.error();
    views.push_back({std::move(*dots), counts});
  }
  auto scale = algo::calibrate_conveyor(k, record.sensor.camera_pose, board, views);
  if (!scale) return scale.error();

  record.has_conveyor = true;
  record.conveyor_date = base::local_time_text();
  record.sensor.mm_per_count = scale->mm_per_count;
  record.conveyor_angle_deg = scale->angle_to_x_deg;

  std::string s = "conveyor scale from " + std::to_string(views.size()) + " carrier positions over " +
                  fmt("%.1f mm\n", scale->travel_mm);
  s += fmt("  mm_per_count: %.7f\n  counts_per_mm: %.5f\n", scale->mm_per_count, 1.0 / scale->mm_per_count);
  s += fmt("  travel_angle_to_x_deg: %.3f\n", scale->angle_to_x_deg);
  s += fmt("  line_residual_mm: %.4f\n  board_rotation_deg: %.3f\n", scale->residual_rms_mm, scale->max_rotation_deg);
  for (const auto& w : scale->warnings) s += "warning: " + w + "\n";
  return s;
}

// --- Simulated pictures -------------------------------------------------------------------------------------

Status write_png(const fs::path& file, const cv::Mat& image) {
  const std::vector<int> params = {cv::IMWRITE_PNG_COMPRESSION, kPngCompression};
  bool written = false;
  try {
    written = cv::imwrite(file.string(), image, params);
  } catch (const cv::Exception& e) {  // OpenCV reports some failures by exception
    return make_error(file.string() + ": " + e.what());
  }
  if (!written) return make_error(file.string() + ": cannot write the PNG");
  return {};
}

std::string board_yaml(const algo::BoardSpec& b) {
  return fmt("board: {rows: %.0f, cols: %.0f, spacing_mm: %g, dot_diameter_mm: %g, ", b.rows, b.cols, b.spacing_mm,
             b.dot_diameter_mm) +
         fmt("width_mm: %g, height_mm: %g}\n", b.width_mm, b.height_mm);
}

}  // namespace

Status write_sim_calibration_views(const app::Config& config, const std::string& step, const std::string& out_dir,
                                   std::uint64_t seed) {
  if (step != "camera" && step != "laser" && step != "conveyor")
    return make_error("unknown calibration step '" + step + "'");
  auto staged = base::StagedDirectory::create(out_dir);
  if (!staged) return staged.error();
  const fs::path dir = staged->path();
  const sim::Rig rig = sim::make_rig(config.rig);
  sim::BoardRenderer renderer(rig, config.sim.camera_noise_seed);
  const algo::BoardSpec board;
  std::string yaml = "# Board pictures of the simulated cell for `cellsight calibrate " + step + " --images DIR`.\n";
  yaml += "format_version: " + std::to_string(kViewsFormatVersion) + "\nstep: " + step + "\n" + board_yaml(board);
  cv::Mat image;
  char name[64];
  std::uint64_t shot = 0;
  if (step == "camera") {
    yaml += "views:\n";
    for (const Eigen::Isometry3d& pose : sim::plan_camera_views(renderer, board)) {
      std::snprintf(name, sizeof name, "view_%02llu.png", static_cast<unsigned long long>(shot));
      renderer.render(board, pose, sim::mix_seed(seed, ++shot), image);
      if (auto ok = write_png(dir / name, image); !ok) return ok;
      yaml += std::string("  - {file: ") + name + "}\n";
    }
    const Eigen::Vector3d dot0 = sim::plan_reference_origin(rig, board);
    renderer.render(board, algo::fixture_board_to_cell(dot0), sim::mix_seed(seed, ++shot), image);
    if (auto ok = write_png(dir / "reference.png", image); !ok) return ok;
    yaml += "reference:\n  file: reference.png\n";
    yaml +=
        fmt("  dot0_cell_m: [%.6f, %.6f, %.6f]   # dot 0 in the fixture (cell frame)\n", dot0.x(), dot0.y(), dot0.z());
  } else if (step == "laser") {
    const double exposure_us =
        kSimStripePeakDn / (config.rig.sensor.gain_dn_per_us * sim::BoardLook{}.plate_reflectance);
    yaml += fmt("exposure_us: %.0f   # laser pictures (information only)\n", exposure_us);
    yaml += "views:\n";
    int index = 0;
    for (const Eigen::Isometry3d& pose : sim::plan_laser_views(rig, board)) {
      char lamp_name[64], laser_name[64];
      std::snprintf(lamp_name, sizeof lamp_name, "laser_%02d_board.png", index);
      std::snprintf(laser_name, sizeof laser_name, "laser_%02d_line.png", index);
      ++index;
      renderer.render(board, pose, sim::mix_seed(seed, ++shot), image);
      if (auto ok = write_png(dir / lamp_name, image); !ok) return ok;
      renderer.render_laser(board, pose, exposure_us, sim::mix_seed(seed, ++shot), image);
      if (auto ok = write_png(dir / laser_name, image); !ok) return ok;
      yaml += std::string("  - {board: ") + lamp_name + ", laser: " + laser_name + "}\n";
    }
  } else {
    yaml += "views:\n";
    int index = 0;
    for (const sim::CarrierView& v : sim::plan_conveyor_views(rig, board)) {
      std::snprintf(name, sizeof name, "carrier_%02d.png", index++);
      renderer.render(board, v.board_to_cell, sim::mix_seed(seed, ++shot), image);
      if (auto ok = write_png(dir / name, image); !ok) return ok;
      yaml += std::string("  - {file: ") + name + ", encoder_counts: " + std::to_string(v.encoder_counts) + "}\n";
    }
  }
  if (auto ok = base::write_file_atomic((dir / kViewsFile).string(), yaml); !ok) return ok;
  return staged->commit();
}

int run_calibrate(const std::vector<std::string>& args, const app::Config& config) {
  return run_calibrate(args, config, stdout, stderr);
}

int run_calibrate(const std::vector<std::string>& args, const app::Config& config, std::FILE* out, std::FILE* err) {
  auto options = parse_options(args);
  if (!options) {
    std::fprintf(err, "cellsight calibrate: %s (see 'cellsight help')\n", options.error().message.c_str());
    return kExitUsage;
  }
  const Options& o = *options;
  const std::string path = o.calibration.empty() ? app::default_calibration_path(config) : o.calibration;
  const std::string prefix = "cellsight calibrate " + o.step + ": ";
  auto refuse = [&](int code, const std::string& message) {
    std::fprintf(err, "%s%s (%s unchanged)\n", prefix.c_str(), message.c_str(), path.c_str());
    return code;
  };

  // The previous calibration must be readable: its other sections are kept, and a damaged file is never
  // silently replaced (the technician decides: restore a backup or move it away).
  formats::CalibrationRecord record;
  std::error_code ec;
  if (fs::exists(path, ec)) {
    auto loaded = formats::load_calibration(path);
    if (!loaded) {
      return refuse(kExitUsage, "the existing calibration is refused: " + first_line(loaded.error().message) +
                                    "; copy a backup over it, or move it away to calibrate from scratch");
    }
    record = std::move(*loaded);
  }
  if (o.step != "camera" && !record.has_camera) {
    return refuse(kExitUsage, "no camera calibration in " + path + ": run 'cellsight calibrate camera' first");
  }

  fs::path dir = o.images;
  if (o.sim) {
    if (fs::exists(o.out, ec) && !(fs::is_directory(o.out, ec) && fs::is_empty(o.out, ec))) {
      return refuse(kExitUsage, "--out " + o.out + " already exists and is not empty: choose a new folder");
    }
    if (auto ok = write_sim_calibration_views(config, o.step, o.out, o.seed); !ok) {
      return refuse(kExitFailure, "rendering the simulated pictures failed: " + ok.error().message);
    }
    std::fprintf(out, "simulated %s pictures written to %s\n", o.step.c_str(), o.out.c_str());
    dir = o.out;
  }

  Expected<std::string> summary = o.step == "camera"  ? camera_step(dir, record)
                                  : o.step == "laser" ? laser_step(dir, record)
                                                      : conveyor_step(dir, record);
  if (!summary) return refuse(kExitUsage, summary.error().message);
  std::fputs(summary->c_str(), out);
  auto backup = formats::save_calibration(path, record);
  if (!backup) return refuse(kExitFailure, "cannot save: " + backup.error().message);
  if (backup->empty()) {
    std::fprintf(out, "saved %s\n", path.c_str());
  } else {
    std::fprintf(out, "saved %s (previous kept as %s)\n", path.c_str(), backup->c_str());
  }
  return kExitOk;
}

}  // namespace cellsight::cli
