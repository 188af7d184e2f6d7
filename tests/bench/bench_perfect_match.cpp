// Benchmark of algo/perfect_match on the full 296 x 500 x 182 grid (budget: 5 ms per template for 100 RPROP
// iterations): time per match, points used, iterations and the pose error reached against known displacements, for
// the default parameters and the variants the defaults were chosen against. Figures only, no pass/fail.
//
//   bench_perfect_match [--poses N] [--parts a,b,...] [--no-surface] [--sim] [--reconstructed] [--swing]
//   default:          catalogue parts sampled as points on their surface (template: one sampling; scans: another
//                     sampling of the same surface, displaced by known poses)
//   --sim:            also passes of the simulated cell: the renderer's truth points (laser-line sampling, frame
//                     pitch, occlusion); with --reconstructed the full camera -> stripe -> triangulation pipeline and
//                     carrier removal; --swing keeps the random swing about y (which 3 DoF cannot model)
#include <sched.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <numbers>
#include <random>
#include <string>
#include <vector>

#include "algo/perfect_match.hpp"
#include "algo/scan.hpp"
#include "algo/scan_builder.hpp"
#include "algo/support.hpp"
#include "app/acquire.hpp"
#include "app/catalogue.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "formats/template_file.hpp"
#include "tests/sim_test_util.hpp"

namespace {

using namespace cellsight;
using algo::PerfectMatcher;
using algo::PerfectMatchParams;
using algo::PerfectMatchResult;
using algo::PlanarPose;
using algo::ScanPoint;
using Clock = std::chrono::steady_clock;

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr int kRepeats = 3;  // best of: the machine is shared
constexpr std::size_t kMaxScanPoints = 1'000'000;

double ms_between(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}
double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

std::vector<ScanPoint> surface_points(const sim::PartSpec& spec, const Eigen::Vector3d& centre, double spacing_m,
                                      double phase) {
  return test::lattice_surface_points(spec, centre, spacing_m, phase);
}

std::vector<ScanPoint> displaced(const std::vector<ScanPoint>& points, const Eigen::Vector2d& c,
                                 const PlanarPose& pose) {
  return test::displaced_points(points, c, pose);
}

struct Case {
  std::vector<ScanPoint> scan;
  PlanarPose truth;
};

struct Variant {
  const char* name;
  PerfectMatchParams params;
  bool zero_start;  // from pose 0 instead of the centroid alignment
};

struct Stats {
  std::vector<double> match_ms, set_scan_ms, ms_per_100_iterations, xy_mm, theta_deg;
  double iterations = 0;
  int points = 0;
  int converged = 0;
};

Stats run(const Variant& v, const formats::TemplateModel& model, const std::vector<Case>& cases) {
  PerfectMatcher pm(v.params);
  Stats s;
  const algo::DistanceMapView map = model.map.view();
  for (const Case& c : cases) {
    double best_set = 1e9;
    double best_match = 1e9;
    PerfectMatchResult r;
    for (int k = 0; k < kRepeats; ++k) {
      const Clock::time_point t0 = Clock::now();
      pm.set_scan(c.scan);
      const Clock::time_point t1 = Clock::now();
      r = pm.match(map, model.centroid_m, v.zero_start ? PlanarPose{} : pm.centroid_start(model.centroid_m));
      const Clock::time_point t2 = Clock::now();
      best_set = std::min(best_set, ms_between(t0, t1));
      best_match = std::min(best_match, ms_between(t1, t2));
    }
    s.set_scan_ms.push_back(best_set);
    s.match_ms.push_back(best_match);
    s.ms_per_100_iterations.push_back(best_match * 100.0 / std::max(r.iterations, 1));
    s.xy_mm.push_back(1e3 * std::hypot(r.pose.x_m - c.truth.x_m, r.pose.y_m - c.truth.y_m));
    s.theta_deg.push_back(std::abs(r.pose.theta_rad - c.truth.theta_rad) / kDeg);
    s.iterations += r.iterations;
    s.points = r.points;
    s.converged += r.converged ? 1 : 0;
  }
  s.iterations /= static_cast<double>(cases.size());
  return s;
}

void print(const char* part, const Variant& v, const Stats& s) {
  const auto mean = [](const std::vector<double>& x) {
    double t = 0;
    for (double e : x) t += e;
    return x.empty() ? 0.0 : t / static_cast<double>(x.size());
  };
  const auto mx = [](const std::vector<double>& x) { return x.empty() ? 0.0 : *std::max_element(x.begin(), x.end()); };
  const auto mn = [](const std::vector<double>& x) { return x.empty() ? 0.0 : *std::min_element(x.begin(), x.end()); };
  std::printf(
      "  %-16s %-26s pts %4d  it %5.1f conv %2d/%zu  match median %5.2f min %5.2f max %5.2f ms  per 100 it "
      "median %5.2f min %5.2f ms  set_scan %5.2f ms  xy max %.3f mean %.3f mm  theta max %.4f mean %.4f deg\n",
      part, v.name, s.points, s.iterations, s.converged, s.match_ms.size(), median(s.match_ms), mn(s.match_ms),
      mx(s.match_ms), median(s.ms_per_100_iterations), mn(s.ms_per_100_iterations), median(s.set_scan_ms), mx(s.xy_mm),
      mean(s.xy_mm), mx(s.theta_deg), mean(s.theta_deg));
}

std::vector<Variant> variants() {
  std::vector<Variant> out;
  out.push_back({"default", PerfectMatchParams{}, false});
  out.push_back({"default, start at pose 0", PerfectMatchParams{}, true});
  PerfectMatchParams p;
  p.coarse_points = 0;
  out.push_back({"one level", p, false});
  p = {};
  p.informative_fraction = 0.0;
  out.push_back({"evenly spread", p, false});
  p.coarse_points = 0;
  out.push_back({"evenly, one level", p, false});
  p = {};
  p.max_points = 2000;
  out.push_back({"2000 points", p, false});
  p = {};
  p.max_points = 500;
  p.coarse_points = 0;
  out.push_back({"500 points, one level", p, false});
  p = {};
  p.step_min_m = 1e-6;
  p.step_min_rad = 1e-6;
  out.push_back({"step_min 1e-6", p, false});
  p = {};
  p.fit_lc_m = 0.0;
  out.push_back({"fit Lc = lc_m (0.4 m)", p, false});
  p.fit_lc_m = 0.005;
  out.push_back({"fit Lc 5 mm", p, false});
  p.fit_lc_m = 0.02;
  out.push_back({"fit Lc 20 mm", p, false});
  // The budget figure: exactly max_iterations (100) iterations, no early stop.
  p = {};
  p.step_min_m = 0.0;
  p.step_min_rad = 0.0;
  out.push_back({"100 iterations", p, false});
  p.coarse_points = 0;
  out.push_back({"100 iterations, one level", p, false});
  return out;
}

// Where the used points of a scan lie against the template at the true pose: share beyond 2 / 5 / 20 mm and the
// mean x, y, z of those beyond 5 mm (what a robust Lc has to ignore).
void diagnose(const formats::TemplateModel& model, const Case& c) {
  PerfectMatcher pm;
  pm.set_scan(c.scan);
  const algo::DistanceMapView map = model.map.view();
  const Eigen::Vector2d ctr = model.centroid_m;
  int n2 = 0, n5 = 0, n20 = 0;
  Eigen::Vector3d far = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3f& p : pm.points()) {
    const Eigen::Vector2d v = Eigen::Rotation2Dd(-c.truth.theta_rad) *
                              (p.head<2>().cast<double>() - ctr - Eigen::Vector2d(c.truth.x_m, c.truth.y_m));
    const double d = map.sample(ctr.x() + v.x(), ctr.y() + v.y(), p.z()).distance_m;
    n2 += d > 0.002 ? 1 : 0;
    n20 += d > 0.02 ? 1 : 0;
    if (d > 0.005) {
      ++n5;
      far += p.cast<double>();
    }
  }
  const double n = static_cast<double>(pm.points().size());
  if (n5 > 0) far /= n5;
  std::printf(
      "    truth (%+.1f, %+.1f mm, %+.2f deg): used points beyond 2 / 5 / 20 mm: %.1f / %.1f / %.1f %%, "
      "mean of those beyond 5 mm (%.3f, %.3f, %.3f) m\n",
      c.truth.x_m * 1e3, c.truth.y_m * 1e3, c.truth.theta_rad / kDeg, 100.0 * n2 / n, 100.0 * n5 / n, 100.0 * n20 / n,
      far.x(), far.y(), far.z());
}

// One pass of the simulated cell: the renderer's truth points, or the reconstruction with the true calibration.
class SimScanner {
 public:
  SimScanner(const app::Config& cfg, sim::SimCell& cell, bool reconstructed)
      : cfg_(cfg),
        cell_(cell),
        reconstructed_(reconstructed),
        builder_(app::scan_builder_params(cfg), test::true_calibration(cell.rig())),
        raw_(kMaxScanPoints) {}

  bool scan(const sim::PassSpec& pass, std::vector<ScanPoint>& out) {
    out.clear();
    if (!reconstructed_) {
      if (!cell_.begin_pass(pass).ok()) return false;
      for (int f = 0; f < cell_.frame_count(); ++f) {
        truth_.clear();
        cell_.render_frame(f, 1500.0, image_, &truth_);
        for (const sim::TruthPoint& t : truth_) {
          if (!t.is_part) continue;
          out.push_back({static_cast<float>(t.p_carrier_m.x()), static_cast<float>(t.p_carrier_m.y()),
                         static_cast<float>(t.p_carrier_m.z()), static_cast<std::uint16_t>(f), 0});
        }
      }
      return true;
    }
    if (!support_fitted_) {
      sim::PassSpec empty;
      empty.with_part = false;
      if (!acquire(empty)) return false;
      auto support = algo::fit_support_plane(raw_.points(), {});
      if (!support) return false;
      plane_ = support->plane;
      support_fitted_ = true;
    }
    if (!acquire(pass)) return false;
    algo::remove_support(raw_, plane_, cfg_.support.distance_threshold_mm / 1000.0);
    out.assign(raw_.points().begin(), raw_.points().end());
    return true;
  }

 private:
  bool acquire(const sim::PassSpec& pass) {
    raw_.clear();
    sim::SimLine line(cell_);
    sim::SimCamera camera(line, 4, static_cast<std::int32_t>(cfg_.camera.exposure_us));
    sim::SimDigitalIo io(line);
    sim::SimEncoder encoder(line);
    if (!camera.start().ok() || !io.open().ok() || !encoder.open().ok()) return false;
    if (io.set(drivers::Output::kLaserEnable, true) != drivers::DeviceStatus::kOk) return false;
    line.enqueue(pass);
    app::AcquireParams params;
    params.start_exposure_us = static_cast<std::int32_t>(cfg_.camera.exposure_us);
    app::AcquireReport report;
    if (app::acquire_pass(camera, io, encoder, builder_, params, report) != app::AcquireResult::kOk) return false;
    for (const ScanPoint& p : builder_.scan().points()) raw_.push(p);
    return true;
  }

  const app::Config& cfg_;
  sim::SimCell& cell_;
  bool reconstructed_;
  algo::ScanBuilder builder_;
  algo::ScanBuffer raw_;
  algo::Plane plane_{};
  bool support_fitted_ = false;
  cv::Mat image_;
  std::vector<sim::TruthPoint> truth_;
};

// The displacement of pass b relative to pass a in DESIGN.md's convention about the template centroid c, for passes
// without swing: p_b = n + t_b + R(theta_b) p_part and p_a = n + t_a + R(theta_a) p_part.
PlanarPose relative_pose(const sim::PartPose& a, const sim::PartPose& b, const Eigen::Vector3d& n,
                         const Eigen::Vector2d& c) {
  const double th = b.theta_rad - a.theta_rad;
  const Eigen::Vector2d ua = n.head<2>() + Eigen::Vector2d(a.x_m, a.y_m) - c;
  const Eigen::Vector2d ub = n.head<2>() + Eigen::Vector2d(b.x_m, b.y_m) - c;
  const Eigen::Vector2d t = ub - Eigen::Rotation2Dd(th) * ua;
  return {t.x(), t.y(), th};
}

}  // namespace

int main(int argc, char** argv) {
  int n_poses = 20;
  bool with_sim = false;
  bool reconstructed = false;
  bool swing = false;
  bool surface = true;
  std::vector<std::string> names = {"plate_4h",        "ribbed_v3",     "bracket_l",
                                    "chamfered_plate", "louvred_panel", "perforated_fine"};
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--poses") == 0 && i + 1 < argc) {
      n_poses = std::max(1, std::atoi(argv[++i]));
    } else if (std::strcmp(argv[i], "--sim") == 0) {
      with_sim = true;
    } else if (std::strcmp(argv[i], "--reconstructed") == 0) {
      with_sim = reconstructed = true;
    } else if (std::strcmp(argv[i], "--swing") == 0) {
      swing = true;
    } else if (std::strcmp(argv[i], "--no-surface") == 0) {
      surface = false;
    } else if (std::strcmp(argv[i], "--parts") == 0 && i + 1 < argc) {
      names.clear();
      std::string list = argv[++i];
      for (std::size_t start = 0; start <= list.size();) {
        const std::size_t comma = std::min(list.find(',', start), list.size());
        if (comma > start) names.push_back(list.substr(start, comma - start));
        start = comma + 1;
      }
    } else {
      std::fprintf(stderr,
                   "usage: bench_perfect_match [--poses N] [--parts a,b,...] [--no-surface] [--sim] [--reconstructed] "
                   "[--swing]\n");
      return 2;
    }
  }
  cpu_set_t one;
  CPU_ZERO(&one);
  CPU_SET(static_cast<int>(sched_getcpu()), &one);
  sched_setaffinity(0, sizeof one, &one);  // one core, no migrations during the timing

  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  if (!cfg) {
    std::fprintf(stderr, "%s\n", cfg.error().message.c_str());
    return 1;
  }
  auto catalogue = app::load_catalogue(CELLSIGHT_SOURCE_DIR "/config/parts.yaml");
  if (!catalogue) {
    std::fprintf(stderr, "%s\n", catalogue.error().message.c_str());
    return 1;
  }
  algo::GridSpec spec;
  spec.origin_m = cfg->grid.origin_m;
  spec.nx = cfg->grid.nx;
  spec.ny = cfg->grid.ny;
  spec.nz = cfg->grid.nz;
  spec.resolution_m = cfg->grid.resolution_m;
  const std::vector<Variant> vars = variants();
  std::printf(
      "bench_perfect_match: grid %d x %d x %d at %.1f mm, %d poses per part (x, y in +-50 mm, theta in +-5 "
      "deg), start: centroid alignment, best of %d runs per match\n",
      spec.nx, spec.ny, spec.nz, spec.resolution_m * 1e3, n_poses, kRepeats);

  // --- surface samplings: template from one lattice, scans from another, displaced by known poses ------------------
  const Eigen::Vector3d centre(0.325, 0.6, 0.1);
  if (surface) std::printf("\nsurface points (template lattice 1.5 mm, scan lattice 1.2 mm with another phase):\n");
  // The default band with every variant; a narrower and the widest band with the default variant only.
  for (const double band_m : {algo::kDefaultBandM, 0.0088, algo::kMaxFineDistanceM}) {
    if (!surface) break;
    std::printf(" sparse map, band %.1f mm%s\n", band_m * 1e3, band_m == algo::kDefaultBandM ? " (default)" : "");
    for (const std::string& name : names) {
      const sim::PartSpec* part = nullptr;
      for (const auto& p : *catalogue) {
        if (p.name == name) part = &p;
      }
      if (part == nullptr) continue;
      const auto points = surface_points(*part, centre, 0.0015, 0.5);
      const auto other = surface_points(*part, centre, 0.0012, 0.23);
      formats::TemplateBuildParams build;
      build.band_m = band_m;
      auto model = formats::build_template(points, spec, build);
      if (!model) {
        std::fprintf(stderr, "%s: %s\n", name.c_str(), model.error().message.c_str());
        return 1;
      }
      std::mt19937 rng(11);
      std::uniform_real_distribution<double> xy(-0.05, 0.05);
      std::uniform_real_distribution<double> th(-5.0 * kDeg, 5.0 * kDeg);
      std::vector<Case> cases;
      for (int i = 0; i < n_poses; ++i) {
        const PlanarPose truth{xy(rng), xy(rng), th(rng)};
        cases.push_back({displaced(other, model->centroid_m, truth), truth});
      }
      for (const Variant& v : vars) {
        if (band_m != algo::kDefaultBandM && std::strcmp(v.name, "default") != 0) continue;
        print(name.c_str(), v, run(v, *model, cases));
      }
    }
  }

  if (!with_sim) return 0;
  // --- passes of the simulated cell --------------------------------------------------------------------------------
  auto cell = app::make_sim_cell(*cfg);
  if (!cell) {
    std::fprintf(stderr, "%s\n", cell.error().message.c_str());
    return 1;
  }
  SimScanner scanner(*cfg, *cell, reconstructed);
  std::printf("\nsimulated passes (%s%s); template: the pass with seed 1:\n",
              reconstructed ? "reconstructed, carrier removed" : "renderer truth points",
              swing ? ", random swing kept" : ", swing 0");
  for (const std::string& name : names) {
    const sim::PartSpec* part = cell->find_part(name);
    if (part == nullptr) continue;
    const Clock::time_point t0 = Clock::now();
    auto make_pass = [&](std::uint64_t seed) {
      auto pass = cell->random_pass(name, seed);
      if (pass && !swing) pass->pose.swing_rad = 0.0;
      return pass;
    };
    auto first = make_pass(1);
    std::vector<ScanPoint> points;
    if (!first || !scanner.scan(*first, points)) return 1;
    auto model = formats::build_template(points, spec, {});
    if (!model) {
      std::fprintf(stderr, "%s: %s\n", name.c_str(), model.error().message.c_str());
      return 1;
    }
    std::vector<Case> cases;
    for (int i = 0; i < n_poses; ++i) {
      auto pass = make_pass(100 + static_cast<std::uint64_t>(i));
      Case c;
      if (!pass || !scanner.scan(*pass, c.scan)) return 1;
      c.truth = relative_pose(first->pose, pass->pose, cell->nominal_centre(*part), model->centroid_m);
      cases.push_back(std::move(c));
    }
    std::printf("  %s: %zu template points, %.0f points per scan, %.1f s to scan\n", name.c_str(), points.size(),
                static_cast<double>(cases.front().scan.size()), ms_between(t0, Clock::now()) / 1e3);
    for (const Case& c : cases) diagnose(*model, c);
    for (const Variant& v : vars) print(name.c_str(), v, run(v, *model, cases));
  }
  return 0;
}
