// The labelled scan sets of `cellsight eval` (cli/eval_set.hpp).
#include "cli/eval_set.hpp"

#include <Eigen/Core>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <numbers>
#include <optional>
#include <sstream>

#include "app/recognition.hpp"
#include "app/sim_setup.hpp"
#include "base/atomic_file.hpp"
#include "cli/mode_args.hpp"
#include "drivers/sim/sim_cell.hpp"
#include "formats/ply.hpp"
#include "formats/template_file.hpp"

namespace cellsight::cli {

namespace fs = std::filesystem;

namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

// The simulated pose of a pass -> the pose relative to the part's template (DESIGN.md "Pose"). Both passes place
// the part as p = c0 + R p_part + t with R = R_z(theta) R_y(swing) R_x(tilt) (drivers/sim/sim_cell.cpp), so
// p_scan = c0 + t_s + R_s R_t^T (p_tmpl - c0 - t_t); written as c + R (p_tmpl - c) + d with the template's centroid
// c this gives R = R_s R_t^T and d = (c0 + t_s) - c - R (c0 + t_t - c).
algo::FullPose relative_pose(const sim::PartPose& scan, const sim::PartPose& tmpl, const Eigen::Vector3d& c0,
                             const Eigen::Vector3d& c) {
  const auto rotation = [](const sim::PartPose& p) {
    algo::FullPose f;
    f[algo::PoseAxis::kRz] = p.theta_rad;
    f[algo::PoseAxis::kRy] = p.swing_rad;
    f[algo::PoseAxis::kRx] = p.tilt_rad;
    return algo::rotation_of(f);
  };
  const Eigen::Matrix3d r = rotation(scan) * rotation(tmpl).transpose();
  const Eigen::Vector3d d = (c0 + Eigen::Vector3d(scan.x_m, scan.y_m, scan.z_m)) - c -
                            r * (c0 + Eigen::Vector3d(tmpl.x_m, tmpl.y_m, tmpl.z_m) - c);
  return algo::full_pose_of(r, d);
}

}  // namespace

Status generate_sim_scans(const app::Config& config, const app::ModelDb& db, const std::vector<std::string>& parts,
                          int count, std::uint64_t first_seed, const std::string& calibration_path,
                          const std::string& dir, const app::PassPerturbation* perturb) {
  auto cell = app::make_sim_cell(config);
  if (!cell) return cell.error();
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return make_error(dir + ": cannot create: " + ec.message());
  std::string truth = "file,x_m,y_m,theta_deg,z_m,rx_deg,ry_deg\n";
  for (const std::string& part : parts) {
    const sim::PartSpec* spec = cell->find_part(part);
    if (spec == nullptr) return make_error("eval --sim: no part '" + part + "' in the simulated catalogue");
    std::optional<sim::PartPose> template_pose;
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    if (const formats::PartEntry* taught = db.find(part); taught != nullptr && !taught->scans.empty()) {
      const std::string& source = taught->template_scan_entry()->source;
      std::int64_t seed = 0;
      auto file = formats::TemplateFile::open(db.path_of(taught->template_file), app::grid_spec(config));
      if (source.rfind("sim seed ", 0) == 0 && parse_whole(source.substr(9), 0, INT64_MAX, seed) && file) {
        template_pose = cell->random_pass(part, static_cast<std::uint64_t>(seed))->pose;
        centroid = {file->centroid_m().x(), file->centroid_m().y(), file->centroid_z_m()};
      }
    }
    const Eigen::Vector3d c0 = cell->nominal_centre(*spec);
    fs::create_directories(fs::path(dir) / part, ec);
    // The passes of one part on all cores (each an independent acquisition); truth lines kept in seed order.
    std::vector<std::string> lines(static_cast<std::size_t>(count));
    auto ok = app::acquire_sim_passes(
        config, part, count, first_seed, calibration_path, "generated " + part,
        [&](int index, std::uint64_t seed, std::vector<algo::ScanPoint>&& points) -> Status {
          const std::string rel = part + "/s" + std::to_string(seed) + ".ply";
          if (auto written = base::write_file_atomic(dir + "/" + rel, formats::write_ply_binary(points)); !written)
            return written;
          if (template_pose) {
            using algo::PoseAxis;
            const algo::FullPose p = relative_pose(cell->random_pass(part, seed)->pose, *template_pose, c0, centroid);
            char line[320];
            std::snprintf(line, sizeof line, "%s,%.9f,%.9f,%.9f,%.9f,%.9f,%.9f\n", rel.c_str(), p[PoseAxis::kX],
                          p[PoseAxis::kY], p[PoseAxis::kRz] * kRadToDeg, p[PoseAxis::kZ], p[PoseAxis::kRx] * kRadToDeg,
                          p[PoseAxis::kRy] * kRadToDeg);
            lines[static_cast<std::size_t>(index)] = line;
          }
          return {};
        },
        perturb);
    if (!ok) return ok;
    for (const std::string& line : lines) truth += line;
  }
  return base::write_file_atomic(dir + "/truth.csv", truth);
}

Expected<std::map<std::string, TruthPose>> read_truth(const std::string& dir) {
  std::map<std::string, TruthPose> truth;
  const std::string path = dir + "/truth.csv";
  if (!fs::exists(path)) return truth;
  std::ifstream in(path);
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (line.empty() || line[0] == '#' || line.rfind("file,", 0) == 0) continue;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream fields(line);
    std::string file;
    std::vector<double> v;
    bool numbers = std::getline(fields, file, ',').good();
    for (std::string f; numbers && std::getline(fields, f, ',');) {
      char* end = nullptr;
      v.push_back(std::strtod(f.c_str(), &end));
      numbers = !f.empty() && *end == '\0' && std::isfinite(v.back());
    }
    if (!numbers || (v.size() != 3 && v.size() != 6)) {
      return make_error(path + ":" + std::to_string(number) +
                        ": expected file,x_m,y_m,theta_deg[,z_m,rx_deg,ry_deg] (numbers) in '" + line + "'");
    }
    const double nan = std::numeric_limits<double>::quiet_NaN();
    TruthPose& p = truth[file];
    p[algo::PoseAxis::kX] = v[0];
    p[algo::PoseAxis::kY] = v[1];
    p[algo::PoseAxis::kRz] = v[2] / kRadToDeg;
    p[algo::PoseAxis::kZ] = v.size() == 6 ? v[3] : nan;
    p[algo::PoseAxis::kRx] = v.size() == 6 ? v[4] / kRadToDeg : nan;
    p[algo::PoseAxis::kRy] = v.size() == 6 ? v[5] / kRadToDeg : nan;
  }
  return truth;
}

}  // namespace cellsight::cli
