// `cellsight scan` implementation.
#include "cli/scan_mode.hpp"

#include <cmath>
#include <ctime>
#include <filesystem>

#include "algo/support.hpp"
#include "base/atomic_file.hpp"
#include "base/local_time.hpp"
#include "drivers/log.hpp"
#include "formats/calibration_file.hpp"
#include "formats/input_file.hpp"
#include "formats/ply.hpp"

namespace cellsight::cli {

Expected<app::ScanSummary> run_scan(const app::Config& config, const app::ScanOptions& options) {
  app::ScanSummary summary;
  auto points = app::acquire_scan(config, options, summary);
  if (!points) return points.error();
  const std::string bytes = options.ascii ? formats::write_ply_ascii(*points) : formats::write_ply_binary(*points);
  if (auto ok = base::write_file_atomic(options.out_path, bytes); !ok) return ok.error();
  CS_LOG_INFO("scan", "%zu points from %d frames (stripe width in band in %d of %d) -> %s", summary.points,
              summary.frames, summary.frames_in_band, summary.frames_with_stripe, options.out_path.c_str());
  return summary;
}

int run_calibrate_support(const std::vector<std::string>& args, const app::Config& config) {
  constexpr int kOk = 0, kBadInput = 2, kFailure = 1;
  app::ScanOptions options;
  options.empty_carrier = true;
  std::string scan_path;
  auto fail = [](const std::string& why) {
    std::fprintf(stderr, "cellsight calibrate support: %s\n", why.c_str());
    return kBadInput;
  };
  for (std::size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const bool has_value = i + 1 < args.size();
    if (a == "--sim") {
      options.sim = true;
    } else if (a == "--scan" && has_value) {
      scan_path = args[++i];
    } else if (a == "--calibration" && has_value) {
      options.calibration_path = args[++i];
    } else if (a == "--seed" && has_value) {
      char* end = nullptr;
      options.seed = std::strtoull(args[++i].c_str(), &end, 10);
      if (*end != '\0') return fail("--seed '" + args[i] + "': expected a whole number");
    } else if (a == "--config" || a == "--log-level") {
      ++i;  // handled by the front end
    } else {
      return fail("unexpected '" + a +
                  "' (usage: calibrate support (--scan EMPTY.ply | --sim [--seed S]) [--calibration FILE])");
    }
  }
  if (options.sim == !scan_path.empty()) return fail("give either --scan EMPTY.ply (an empty-carrier scan) or --sim");
  const std::string calibration_path =
      options.calibration_path.empty() ? app::default_calibration_path(config) : options.calibration_path;
  // The other sections are kept: read them first, and refuse to touch a damaged file.
  formats::CalibrationRecord record;
  std::error_code ec;
  if (std::filesystem::exists(calibration_path, ec)) {
    auto loaded = formats::load_calibration(calibration_path);
    if (!loaded) return fail(loaded.error().message);
    record = *loaded;
  }
  std::vector<algo::ScanPoint> points;
  if (options.sim) {
    app::ScanSummary summary;
    auto scanned = app::acquire_scan(config, options, summary);
    if (!scanned) return fail(scanned.error().message);
    points = std::move(*scanned);
  } else {
    auto parsed = formats::load_ply_file(scan_path);
    if (!parsed) return fail(parsed.error().message);
    points = std::move(*parsed);
  }
  algo::SupportFitParams params;
  auto fit = algo::fit_support_plane(points, params);
  if (!fit) return fail(fit.error().message);
  constexpr double kMaxTiltDeg = 20.0;  // the carrier hangs facing the camera
  const double tilt_deg = std::acos(std::min(1.0, std::abs(fit->plane.normal.z()))) * 180.0 / M_PI;
  if (tilt_deg > kMaxTiltDeg) {
    return fail("the fitted plane is tilted " + std::to_string(tilt_deg) +
                " deg from the carrier plane (x, y): is this an empty-carrier scan?");
  }
  constexpr double kMaxRmsMm = 1.0;
  if (fit->rms_m * 1e3 > kMaxRmsMm) {
    return fail("the carrier is not flat enough for a plane (rms " + std::to_string(fit->rms_m * 1e3) +
                " mm > 1 mm): check the carrier is empty and not bent");
  }
  record.has_support = true;
  record.support = fit->plane;
  record.support_rms_mm = fit->rms_m * 1e3;
  record.support_points = fit->inliers;
  record.support_date = base::local_time_text();
  auto saved = formats::save_calibration(calibration_path, record);
  if (!saved) {
    std::fprintf(stderr, "cellsight calibrate support: %s\n", saved.error().message.c_str());
    return kFailure;
  }
  std::printf("support plane (carrier frame): normal %.6f %.6f %.6f, offset %.4f mm\n", fit->plane.normal.x(),
              fit->plane.normal.y(), fit->plane.normal.z(), fit->plane.offset_m * 1e3);
  std::printf("  rms_mm: %.4f\n  inliers: %zu of %zu points (%.1f %%)\n", fit->rms_m * 1e3, fit->inliers, points.size(),
              fit->inlier_fraction * 100.0);
  std::printf("saved %s%s\n", calibration_path.c_str(),
              saved->empty() ? "" : (" (previous kept as " + *saved + ")").c_str());
  return kOk;
}

}  // namespace cellsight::cli
