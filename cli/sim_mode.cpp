// `cellsight sim` implementation.
#include "cli/sim_mode.hpp"

#include <sys/stat.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstdio>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "app/catalogue.hpp"
#include "app/sim_setup.hpp"
#include "base/atomic_file.hpp"
#include "drivers/log.hpp"
#include "drivers/sim/random_catalogue.hpp"

namespace cellsight::cli {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;
constexpr int kPngCompression = 3;  // fast; frames are mostly dark and compress well anyway

void emit_vec(YAML::Emitter& out, const Eigen::Vector3d& v) {
  out << YAML::Flow << YAML::BeginSeq << v.x() << v.y() << v.z() << YAML::EndSeq;
}

}  // namespace

Expected<sim::PartPose> parse_pose(const std::string& text) {
  std::vector<double> values;
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    char* end = nullptr;
    const double v = std::strtod(item.c_str(), &end);
    if (item.empty() || end == item.c_str() || *end != '\0' || !std::isfinite(v)) {
      return make_error("--pose '" + text + "': '" + item +
                        "' is not a number; expected x_m,y_m,theta_deg[,swing_deg[,tilt_deg[,z_m]]]");
    }
    values.push_back(v);
  }
  if (values.size() < 3 || values.size() > 6) {
    return make_error("--pose '" + text +
                      "': expected 3 to 6 comma-separated numbers x_m,y_m,theta_deg[,swing_deg[,tilt_deg[,z_m]]]");
  }
  constexpr double kMaxShiftM = 0.3, kMaxAngleDeg = 45.0;
  if (std::abs(values[0]) > kMaxShiftM || std::abs(values[1]) > kMaxShiftM) {
    return make_error("--pose '" + text + "': x and y are metres and must be within +-0.3");
  }
  values.resize(6, 0.0);  // what is not given is 0
  if (std::abs(values[2]) > kMaxAngleDeg || std::abs(values[3]) > kMaxAngleDeg || std::abs(values[4]) > kMaxAngleDeg) {
    return make_error("--pose '" + text + "': angles are degrees and must be within +-45");
  }
  if (std::abs(values[5]) > kMaxShiftM)
    return make_error("--pose '" + text + "': z is metres and must be within +-0.3");
  sim::PartPose pose;
  pose.x_m = values[0];
  pose.y_m = values[1];
  pose.theta_rad = values[2] / kRadToDeg;
  pose.swing_rad = values[3] / kRadToDeg;
  pose.tilt_rad = values[4] / kRadToDeg;
  pose.z_m = values[5];
  return pose;
}

Status write_random_catalogue(const app::Config& config, int count, std::uint64_t seed, const std::string& out_path) {
  const sim::RandomCatalogue catalogue = sim::generate_random_catalogue(count, seed);
  if (auto ok = app::check_catalogue_fits_grid(config, catalogue.parts); !ok) {
    return make_error("the generated catalogue does not fit this configuration's grid: " + ok.error().message);
  }
  std::ostringstream header;
  header
      << "Random part catalogue of the simulated cell (nobody tuned recognition for these parts).\n"
      << "generator: cellsight sim --random-catalogue " << count << " --seed " << seed
      << " (drivers/sim/random_catalogue.cpp); the same N and seed give this file byte for byte.\n"
      << "N: " << count << ", seed: " << seed << "\n"
      << "Keys as in config/parts.yaml; family is shared by near twins, role says whether an evaluation teaches the\n"
      << "part (taught) or keeps it back as one that must come out unknown (untaught).\n"
      << "near-twin pairs:" << (catalogue.twins.empty() ? " none" : "") << "\n";
  for (const auto& t : catalogue.twins) {
    header << "  " << catalogue.parts[t.base].name << " / " << catalogue.parts[t.twin].name << ": "
           << sim::twin_relation_text(t.relation)
           << (t.relation == sim::TwinRelation::kHeightPlus5mm ? " (deliberately hard)" : "") << "\n";
  }
  header << "untaught:";
  for (const auto& p : catalogue.parts) {
    if (p.role == sim::PartRole::kUntaught) header << ' ' << p.name;
  }
  header << "\n";
  if (auto ok = base::write_file_atomic(out_path, app::catalogue_yaml(catalogue.parts, header.str()),
                                        base::Overwrite::kRefuse);
      !ok) {
    return ok.error();
  }
  CS_LOG_INFO("sim", "random catalogue: %d parts, seed %llu, %zu near-twin pairs -> %s", count,
              static_cast<unsigned long long>(seed), catalogue.twins.size(), out_path.c_str());
  return {};
}

std::string truth_yaml(const app::Config& config, const sim::SimCell& cell, const std::vector<double>& exposures_us) {
  const sim::Rig& rig = cell.rig();
  const sim::PassSpec& pass = cell.pass();
  YAML::Emitter out;
  out.SetDoublePrecision(12);
  out << YAML::Comment(
      "Ground truth of one simulated pass (cellsight sim). Metres, degrees; carrier frame of DESIGN.md.");
  out << YAML::BeginMap;
  out << YAML::Key << "format_version" << YAML::Value << 1;
  out << YAML::Key << "part" << YAML::Value << pass.part;
  out << YAML::Key << "seed" << YAML::Value << pass.seed;
  out << YAML::Key << "pose" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "x_m" << YAML::Value << pass.pose.x_m;
  out << YAML::Key << "y_m" << YAML::Value << pass.pose.y_m;
  out << YAML::Key << "theta_deg" << YAML::Value << pass.pose.theta_rad * kRadToDeg;
  out << YAML::Key << "swing_deg" << YAML::Value << pass.pose.swing_rad * kRadToDeg;
  out << YAML::Key << "tilt_deg" << YAML::Value << pass.pose.tilt_rad * kRadToDeg;
  out << YAML::Key << "z_m" << YAML::Value << pass.pose.z_m;
  out << YAML::EndMap;
  if (const sim::PartSpec* part = cell.find_part(pass.part)) {
    out << YAML::Key << "nominal_centre_m" << YAML::Value;
    emit_vec(out, cell.nominal_centre(*part));
  }
  const Eigen::Matrix4d t = cell.part_to_carrier().matrix();
  out << YAML::Key << "part_to_carrier" << YAML::Value << YAML::Flow << YAML::BeginSeq;
  for (int r = 0; r < 3; ++r) {
    out << YAML::Flow << YAML::BeginSeq << t(r, 0) << t(r, 1) << t(r, 2) << t(r, 3) << YAML::EndSeq;
  }
  out << YAML::EndSeq;
  out << YAML::Key << "coating" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "a" << YAML::Value << pass.coating_a.name;
  out << YAML::Key << "b" << YAML::Value << pass.coating_b.name;
  out << YAML::Key << "split_x_m" << YAML::Value << (std::isfinite(pass.split_x_m) ? pass.split_x_m : 0.0);
  out << YAML::Key << "split" << YAML::Value << std::isfinite(pass.split_x_m);
  out << YAML::EndMap;

  const auto& k = rig.params.camera.intrinsics;
  out << YAML::Key << "rig" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "camera" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "width_px" << YAML::Value << k.width_px << YAML::Key << "height_px" << YAML::Value << k.height_px;
  out << YAML::Key << "fx_px" << YAML::Value << k.fx_px << YAML::Key << "fy_px" << YAML::Value << k.fy_px;
  out << YAML::Key << "cx_px" << YAML::Value << k.cx_px << YAML::Key << "cy_px" << YAML::Value << k.cy_px;
  out << YAML::Key << "distortion_k1_k2_p1_p2_k3" << YAML::Value << YAML::Flow << YAML::BeginSeq << k.k1 << k.k2 << k.p1
      << k.p2 << k.k3 << YAML::EndSeq;
  out << YAML::Key << "rotation_cam_world" << YAML::Value << YAML::Flow << YAML::BeginSeq;
  for (int r = 0; r < 3; ++r) {
    const auto& m = rig.camera_pose.r_cam_world;
    out << YAML::Flow << YAML::BeginSeq << m(r, 0) << m(r, 1) << m(r, 2) << YAML::EndSeq;
  }
  out << YAML::EndSeq;
  out << YAML::Key << "translation_cam_world_m" << YAML::Value;
  emit_vec(out, rig.camera_pose.t_cam_world);
  out << YAML::Key << "centre_world_m" << YAML::Value;
  emit_vec(out, rig.camera_centre_world);
  out << YAML::EndMap;
  out << YAML::Key << "laser" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "normal" << YAML::Value;
  emit_vec(out, rig.laser_normal_world);
  out << YAML::Key << "offset_m" << YAML::Value << rig.laser_offset_m;
  out << YAML::Key << "emitter_m" << YAML::Value;
  emit_vec(out, rig.params.laser.emitter_world_m);
  out << YAML::EndMap;
  out << YAML::Key << "conveyor" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "speed_m_per_s" << YAML::Value << rig.params.conveyor.speed_m_per_s;
  out << YAML::Key << "counts_per_mm" << YAML::Value << rig.params.conveyor.counts_per_mm;
  out << YAML::Key << "trigger_every_counts" << YAML::Value << rig.params.conveyor.trigger_every_counts;
  out << YAML::EndMap;
  out << YAML::Key << "carrier_start_offset_m" << YAML::Value << rig.params.carrier.start_offset_m;
  out << YAML::Key << "world_from_carrier" << YAML::Value
      << "p_world = p_carrier + (travel_m - carrier_start_offset_m) * [1, 0, 0]";
  out << YAML::EndMap;

  out << YAML::Key << "frames" << YAML::Value << YAML::BeginSeq;
  for (int i = 0; i < cell.frame_count(); ++i) {
    const sim::FrameInfo f = cell.frame_info(i);
    char name[32];
    std::snprintf(name, sizeof name, "frames/%06d.png", i);
    out << YAML::Flow << YAML::BeginMap;
    out << YAML::Key << "index" << YAML::Value << i;
    out << YAML::Key << "file" << YAML::Value << name;
    out << YAML::Key << "travel_m" << YAML::Value << f.travel_m;
    out << YAML::Key << "encoder_counts" << YAML::Value << f.encoder_counts;
    out << YAML::Key << "timestamp_ns" << YAML::Value << f.timestamp_ns;
    out << YAML::Key << "exposure_us" << YAML::Value << exposures_us[static_cast<std::size_t>(i)];
    out << YAML::EndMap;
  }
  out << YAML::EndSeq;
  out << YAML::Key << "config_source" << YAML::Value << config.source;
  out << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

Status write_sim_pass(const app::Config& config, sim::SimCell& cell, const SimOptions& options) {
  auto pass = cell.random_pass(options.part, options.seed);
  if (!pass) return pass.error();
  if (options.pose) pass->pose = *options.pose;
  if (auto ok = cell.begin_pass(*pass); !ok) return ok.error();

  auto staged = base::StagedDirectory::create(options.out_dir);
  if (!staged) return staged.error();
  const std::string frames_dir = staged->path() + "/frames";
  if (::mkdir(frames_dir.c_str(), 0755) != 0) return make_error(frames_dir + ": cannot create");

  cv::Mat image;
  std::vector<double> exposures_us;
  const std::vector<int> png_params = {cv::IMWRITE_PNG_COMPRESSION, kPngCompression, cv::IMWRITE_PNG_STRATEGY,
                                       cv::IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY};
  for (int i = 0; i < cell.frame_count(); ++i) {
    const double exposure_us = config.camera.exposure_us;  // fixed here; the exposure loop runs in `scan`
    cell.render_frame(i, exposure_us, image);
    exposures_us.push_back(exposure_us);
    char name[64];
    std::snprintf(name, sizeof name, "/%06d.png", i);
    bool written = false;
    try {
      written = cv::imwrite(frames_dir + name, image, png_params);
    } catch (const cv::Exception& e) {  // OpenCV reports some failures by exception
      return make_error(frames_dir + name + ": " + e.what());
    }
    if (!written) return make_error(frames_dir + name + ": cannot write the PNG");
  }
  if (auto ok = base::write_file_atomic(staged->path() + "/truth.yaml", truth_yaml(config, cell, exposures_us)); !ok) {
    return ok.error();
  }
  if (auto ok = staged->commit(); !ok) return ok.error();
  CS_LOG_INFO("sim", "part %s seed %llu: %d frames -> %s (pose x %.4f m, y %.4f m, theta %.3f deg, swing %.3f deg, %s)",
              pass->part.c_str(), static_cast<unsigned long long>(pass->seed), cell.frame_count(),
              options.out_dir.c_str(), pass->pose.x_m, pass->pose.y_m, pass->pose.theta_rad * kRadToDeg,
              pass->pose.swing_rad * kRadToDeg, pass->coating_a.name.c_str());
  return {};
}

}  // namespace cellsight::cli
