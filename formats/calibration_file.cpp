// calibration.yaml: validating reader, writer with checksum, dated backup before every save.
#include "formats/calibration_file.hpp"

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>

#include "base/atomic_file.hpp"
#include "base/file_read.hpp"
#include "base/local_time.hpp"
#include "formats/yaml_reader.hpp"
#include "formats/yaml_text.hpp"

namespace cellsight::formats {
namespace {

namespace fs = std::filesystem;
using formats::number;

constexpr const char* kChecksumKey = "checksum_fnv1a64";
// A calibration file is a few kB; the cap of base::read_file only keeps a wrong path from filling the memory.
constexpr std::size_t kMaxCalibrationBytes = std::size_t{16} << 20;
constexpr double kOrthonormalTolerance = 1e-6;
constexpr double kUnitTolerance = 1e-6;

// FNV-1a, 64 bit: catches truncation and stray edits (not an authentication code).
std::uint64_t fnv1a64(std::string_view bytes) {
  std::uint64_t h = 0xcbf29ce484222325ULL;
  for (const char c : bytes) {
    h ^= static_cast<unsigned char>(c);
    h *= 0x100000001b3ULL;
  }
  return h;
}

std::string vec(const Eigen::Vector3d& v) {
  char buf[128];
  std::snprintf(buf, sizeof buf, "[%.17g, %.17g, %.17g]", v.x(), v.y(), v.z());
  return buf;
}

void read_camera(YamlSection s, CalibrationRecord& r) {
  for (const char* key :
       {"calibrated_at", "views", "width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2",
        "k3", "reprojection_rms_px", "reference_rms_px", "x_axis", "y_axis", "z_axis", "translation_m"}) {
    s.require(key);
  }
  auto& k = r.sensor.intrinsics;
  s.text("calibrated_at", r.camera_date);
  s.integer("views", r.camera_views, 1, 10000, "views");
  s.integer("width_px", k.width_px, 64, 8192, "px");
  s.integer("height_px", k.height_px, 64, 8192, "px");
  s.number("fx_px", k.fx_px, 50.0, 50000.0, "px");
  s.number("fy_px", k.fy_px, 50.0, 50000.0, "px");
  s.number("cx_px", k.cx_px, 0.0, 8192.0, "px");
  s.number("cy_px", k.cy_px, 0.0, 8192.0, "px");
  if (k.cx_px > k.width_px) s.error("cx_px", "lies outside the image (wider than width_px)");
  if (k.cy_px > k.height_px) s.error("cy_px", "lies outside the image (higher than height_px)");
  s.number("k1", k.k1, -2.0, 2.0, "");
  s.number("k2", k.k2, -5.0, 5.0, "");
  s.number("p1", k.p1, -0.1, 0.1, "");
  s.number("p2", k.p2, -0.1, 0.1, "");
  s.number("k3", k.k3, -10.0, 10.0, "");
  s.number("reprojection_rms_px", r.sensor.reprojection_rms_px, 0.0, 10.0, "px");
  s.number("reference_rms_px", r.reference_rms_px, 0.0, 10.0, "px");
  Eigen::Matrix3d rot = Eigen::Matrix3d::Zero();
  Eigen::Vector3d axis = Eigen::Vector3d::Zero();
  const char* axes[3] = {"x_axis", "y_axis", "z_axis"};
  for (int i = 0; i < 3; ++i) {
    axis.setZero();
    s.vec3(axes[i], axis, -1.0, 1.0, "");
    rot.row(i) = axis.transpose();
  }
  if (!(rot * rot.transpose() - Eigen::Matrix3d::Identity()).isZero(kOrthonormalTolerance) ||
      rot.determinant() <= 0.0) {
    s.error("x_axis", "the camera axes are not a right-handed orthonormal set (x_axis, y_axis, z_axis)");
  }
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  s.vec3("translation_m", translation, -20.0, 20.0, "m");
  r.sensor.camera_pose.r_cam_world = rot;
  r.sensor.camera_pose.t_cam_world = translation;
  s.finish();
}

// The plane's unit normal under key "normal" (the laser plane's and the carrier plane's).
Eigen::Vector3d read_unit_normal(YamlSection& s) {
  Eigen::Vector3d n = Eigen::Vector3d::Zero();
  s.vec3("normal", n, -1.0, 1.0, "");
  if (std::abs(n.norm() - 1.0) > kUnitTolerance) s.error("normal", "must be a unit vector");
  return n;
}

void read_laser(YamlSection s, CalibrationRecord& r) {
  for (const char* key : {"calibrated_at", "normal", "offset_m", "residual_mm", "points"}) s.require(key);
  s.text("calibrated_at", r.laser_date);
  r.sensor.laser_normal = read_unit_normal(s);
  s.number("offset_m", r.sensor.laser_offset_m, -5.0, 5.0, "m");
  s.number("residual_mm", r.sensor.laser_residual_mm, 0.0, 100.0, "mm");
  s.integer("points", r.laser_points, 3, 100000000, "points");
  s.finish();
}

void read_conveyor(YamlSection s, CalibrationRecord& r) {
  for (const char* key : {"calibrated_at", "mm_per_count", "angle_to_x_deg"}) s.require(key);
  s.text("calibrated_at", r.conveyor_date);
  s.number("mm_per_count", r.sensor.mm_per_count, 1e-6, 1000.0, "mm/count");
  s.number("angle_to_x_deg", r.conveyor_angle_deg, 0.0, 90.0, "deg");
  s.finish();
}

void read_support(YamlSection s, CalibrationRecord& r) {
  for (const char* key : {"calibrated_at", "normal", "offset_m", "rms_mm", "points"}) s.require(key);
  s.text("calibrated_at", r.support_date);
  r.support.normal = read_unit_normal(s);
  s.number("offset_m", r.support.offset_m, -5.0, 5.0, "m");
  s.number("rms_mm", r.support_rms_mm, 0.0, 100.0, "mm");
  std::int64_t points = 0;
  s.integer("points", points, 3, 1000000000, "points");
  r.support_points = static_cast<std::size_t>(points);
  s.finish();
}

}  // namespace

std::string calibration_yaml(const CalibrationRecord& r) {
  std::string t;
  t += "# cellsight sensor calibration, written by `cellsight calibrate` (scripts/calibrate.sh). Do not edit: the\n";
  t += "# checksum on the last line refuses a changed or damaged file. To go back, copy a backup\n";
  t += "# (this file's name + .YYYYMMDD-HHMMSS.bak) over it. Cell frame (DESIGN.md): x along conveyor travel, y up,\n";
  t += "# z toward the camera, metres; origin at dot 0 of the board in the reference fixture.\n";
  t += "format_version: " + std::to_string(kCalibrationFormatVersion) + "\n";
  if (r.has_camera) {
    const auto& k = r.sensor.intrinsics;
    const auto& pose = r.sensor.camera_pose;
    t += "camera:\n";
    t += "  calibrated_at: " + formats::yaml_quoted(r.camera_date) + "\n";
    t += "  views: " + std::to_string(r.camera_views) + "\n";
    t += "  width_px: " + std::to_string(k.width_px) + "\n";
    t += "  height_px: " + std::to_string(k.height_px) + "\n";
    t += "  fx_px: " + number(k.fx_px) + "\n";
    t += "  fy_px: " + number(k.fy_px) + "\n";
    t += "  cx_px: " + number(k.cx_px) + "\n";
    t += "  cy_px: " + number(k.cy_px) + "\n";
    t += "  k1: " + number(k.k1) + "            # distortion, OpenCV's k1 k2 p1 p2 k3 model\n";
    t += "  k2: " + number(k.k2) + "\n";
    t += "  p1: " + number(k.p1) + "\n";
    t += "  p2: " + number(k.p2) + "\n";
    t += "  k3: " + number(k.k3) + "\n";
    t += "  reprojection_rms_px: " + number(r.sensor.reprojection_rms_px) + "\n";
    t += "  reference_rms_px: " + number(r.reference_rms_px) + "\n";
    t += "  # camera axes (x right, y down, z forward) in cell coordinates: the rows of the cell -> camera rotation\n";
    t += "  x_axis: " + vec(pose.r_cam_world.row(0).transpose()) + "\n";
    t += "  y_axis: " + vec(pose.r_cam_world.row(1).transpose()) + "\n";
    t += "  z_axis: " + vec(pose.r_cam_world.row(2).transpose()) + "\n";
    t += "  translation_m: " + vec(pose.t_cam_world) + "   # cell -> camera: p_cam = R p_cell + translation\n";
    const Eigen::Vector3d centre = pose.centre_world();
    char note[128];
    std::snprintf(note, sizeof note, "  # camera centre in the cell frame: [%.4f, %.4f, %.4f] m\n", centre.x(),
                  centre.y(), centre.z());
    t += note;
  }
  if (r.has_laser) {
    t += "laser:                     # plane normal . p = offset_m (cell frame)\n";
    t += "  calibrated_at: " + formats::yaml_quoted(r.laser_date) + "\n";
    t += "  normal: " + vec(r.sensor.laser_normal) + "\n";
    t += "  offset_m: " + number(r.sensor.laser_offset_m) + "\n";
    t += "  residual_mm: " + number(r.sensor.laser_residual_mm) + "\n";
    t += "  points: " + std::to_string(r.laser_points) + "\n";
  }
  if (r.has_conveyor) {
    t += "conveyor:\n";
    t += "  calibrated_at: " + formats::yaml_quoted(r.conveyor_date) + "\n";
    t += "  mm_per_count: " + number(r.sensor.mm_per_count) + "\n";
    t += "  angle_to_x_deg: " + number(r.conveyor_angle_deg) + "\n";
  }
  if (r.has_support) {
    t += "support:                   # carrier plane: normal . p = offset_m (carrier frame)\n";
    t += "  calibrated_at: " + formats::yaml_quoted(r.support_date) + "\n";
    t += "  normal: " + vec(r.support.normal) + "\n";
    t += "  offset_m: " + number(r.support.offset_m) + "\n";
    t += "  rms_mm: " + number(r.support_rms_mm) + "\n";
    t += "  points: " + std::to_string(r.support_points) + "\n";
  }
  char line[64];
  std::snprintf(line, sizeof line, "%s: \"%016" PRIx64 "\"\n", kChecksumKey, fnv1a64(t));
  return t + line;
}

Expected<CalibrationRecord> load_calibration(const std::string& path) {
  auto bytes = base::read_file(path, kMaxCalibrationBytes);
  if (!bytes) return bytes.error();
  // A file cut short loses its last line first: say so before any syntax error it causes.
  const std::size_t at = formats::checksum_line_start(*bytes, kChecksumKey);
  if (at == std::string::npos) {
    const auto lines = std::count(bytes->begin(), bytes->end(), '\n');
    char buf[96];
    std::snprintf(buf, sizeof buf, ":%ld:1", static_cast<long>(lines) + 1);
    return make_error(path + buf + ": " + kChecksumKey +
                      ": missing: the file is truncated or was not written by cellsight; copy a backup "
                      "(" +
                      fs::path(path).filename().string() + ".*.bak) over it or calibrate again");
  }
  auto doc = load_yaml_file(path);
  if (!doc) return doc.error();

  CalibrationRecord record;
  YamlErrors errors(path);
  YamlSection root(*doc, "", &errors);
  root.require("format_version");
  int version = kCalibrationFormatVersion;
  constexpr int kMaxVersion = 1000;
  root.integer("format_version", version, 1, kMaxVersion, "");
  if (version != kCalibrationFormatVersion) {
    root.error("format_version",
               "version " + std::to_string(version) + " is not supported (this cellsight reads version " +
                   std::to_string(kCalibrationFormatVersion) + "): calibrate again with this version");
  }
  std::string stored_checksum;
  root.text(kChecksumKey, stored_checksum);
  // A section is present once its step has run; an empty or absent one is simply not calibrated yet.
  record.has_camera = root.has("camera");
  record.has_laser = root.has("laser");
  record.has_conveyor = root.has("conveyor");
  record.has_support = root.has("support");
  if (record.has_support) read_support(root.section("support"), record);
  if (record.has_camera) read_camera(root.section("camera"), record);
  if (record.has_laser) read_laser(root.section("laser"), record);
  if (record.has_conveyor) read_conveyor(root.section("conveyor"), record);
  for (const char* key : {"camera", "laser", "conveyor", "support"})
    (void)root.section(key);  // known keys, even when empty
  root.finish();

  char expected[20];
  std::snprintf(expected, sizeof expected, "%016" PRIx64, fnv1a64(std::string_view(*bytes).substr(0, at)));
  if (errors.empty() && stored_checksum != expected) {
    root.error(kChecksumKey,
               "does not match the content: the file was changed or damaged after cellsight wrote it; copy "
               "a backup (" +
                   fs::path(path).filename().string() + ".*.bak) over it or calibrate again");
  }
  if (!errors.empty()) return make_error(errors.joined());
  return record;
}

Expected<algo::SensorCalibration> load_sensor_calibration(const std::string& path) {
  auto record = load_calibration(path);
  if (!record) return record.error();
  if (!record->has_camera) return make_error(path + ": no camera section: run 'cellsight calibrate camera'");
  if (!record->has_laser) return make_error(path + ": no laser section: run 'cellsight calibrate laser'");
  if (!record->has_conveyor) return make_error(path + ": no conveyor section: run 'cellsight calibrate conveyor'");
  return record->sensor;
}

Expected<std::string> save_calibration(const std::string& path, const CalibrationRecord& record) {
  std::error_code ec;
  std::string backup;
  if (fs::exists(path, ec)) {
    auto old = base::read_file(path, kMaxCalibrationBytes);
    if (!old) return make_error(old.error().message + " (needed for the backup; nothing was changed)");
    const std::string stem = path + "." + base::local_time_text("%Y%m%d-%H%M%S");
    backup = stem + ".bak";
    for (int n = 2; fs::exists(backup, ec); ++n) backup = stem + "-" + std::to_string(n) + ".bak";
    if (auto ok = base::write_file_atomic(backup, *old); !ok) {
      return make_error(ok.error().message + " (the backup failed; nothing was changed)");
    }
  }
  if (auto ok = base::write_file_atomic(path, calibration_yaml(record)); !ok) return ok.error();
  return backup;
}

}  // namespace cellsight::formats
