// Benchmark of the decision tail on one core: scan (carrier removed) -> grid -> depth image -> 74 features -> SVM ->
// cascade (Perfect Match + two-way check) with 15 taught classes on the full 296 x 500 x 182 grid (budget: 30 ms
// median). Also prints what the thresholds are learnt from: Perfect Match error and two-way blob areas of each class's
// own scans against its template, and of the one-hole / one-rib siblings against each other. Figures only.
//
//   bench_cascade [--truth] [--train N] [--test N] [--runs N]
//   --truth: scans are the renderer's ground-truth points (exact geometry, real visibility) instead of
//            reconstructed ones (simulated camera -> stripe -> triangulation with the true calibration).
#include <sched.h>
#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <map>
#include <memory>
#include <numbers>
#include <string>
#include <vector>

#include "algo/cascade.hpp"
#include "algo/distance_map.hpp"
#include "algo/features.hpp"
#include "algo/grid.hpp"
#include "algo/perfect_match.hpp"
#include "algo/scan.hpp"
#include "algo/scan_builder.hpp"
#include "algo/support.hpp"
#include "algo/svm.hpp"
#include "app/acquire.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "tests/sim_test_util.hpp"

namespace {

using namespace cellsight;
using Clock = std::chrono::steady_clock;

constexpr std::size_t kMaxPoints = 1'000'000;

// CPU time of this thread (the machine may be shared: wall time then includes other processes' turns).
double thread_cpu_ms() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

double ms_between(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}
double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}
double max_of(const std::vector<double>& v) {
  return v.empty() ? 0.0 : *std::max_element(v.begin(), v.end());
}

// One pass of the simulated cell, carrier included, into `out`.
class Scanner {
 public:
  Scanner(const app::Config& cfg, sim::SimCell& cell, bool truth)
      : cfg_(cfg),
        cell_(cell),
        truth_(truth),
        builder_(app::scan_builder_params(cfg), test::true_calibration(cell.rig())) {}

  bool scan(const sim::PassSpec& pass, algo::ScanBuffer& out) {
    out.clear();
    if (truth_) {
      if (!cell_.begin_pass(pass).ok()) return false;
      for (int f = 0; f < cell_.frame_count(); ++f) {
        points_.clear();
        cell_.render_frame(f, 1500.0, image_, &points_);
        for (const sim::TruthPoint& t : points_) {
          out.push({static_cast<float>(t.p_carrier_m.x()), static_cast<float>(t.p_carrier_m.y()),
                    static_cast<float>(t.p_carrier_m.z()), static_cast<std::uint16_t>(f), 0});
        }
      }
      return true;
    }
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
    for (const algo::ScanPoint& p : builder_.scan().points()) out.push(p);
    return true;
  }

 private:
  const app::Config& cfg_;
  sim::SimCell& cell_;
  bool truth_;
  algo::ScanBuilder builder_;
  cv::Mat image_;
  std::vector<sim::TruthPoint> points_;
};

struct Taught {
  std::string name;
  int id = 0;
  algo::DistanceMap map;
  std::vector<algo::SurfaceCell> surface;
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();
  std::vector<std::vector<algo::ScanPoint>> train, test;  // carrier removed
  std::vector<algo::FeatureVector> train_features;
  std::vector<algo::MatchReport> own;
};

}  // namespace

namespace {

int run(int argc, char** argv) {
  bool truth = false, hull_only = false;
  int n_train = 10, n_test = 3, runs = 3;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--truth") == 0) {
      truth = true;
    } else if (std::strcmp(argv[i], "--hull-only") == 0) {
      hull_only = true;  // the two-way check without its per-cell depth test (cascade.per_cell_depth: false)
    } else if (std::strcmp(argv[i], "--train") == 0 && i + 1 < argc) {
      n_train = std::max(2, std::atoi(argv[++i]));
    } else if (std::strcmp(argv[i], "--test") == 0 && i + 1 < argc) {
      n_test = std::max(1, std::atoi(argv[++i]));
    } else if (std::strcmp(argv[i], "--runs") == 0 && i + 1 < argc) {
      runs = std::max(1, std::atoi(argv[++i]));
    } else {
      std::fprintf(stderr, "usage: bench_cascade [--truth] [--hull-only] [--train N] [--test N] [--runs N]\n");
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
  auto cell = app::make_sim_cell(*cfg);
  if (!cell) {
    std::fprintf(stderr, "%s\n", cell.error().message.c_str());
    return 1;
  }
  algo::GridSpec spec;
  spec.origin_m = cfg->grid.origin_m;
  spec.nx = cfg->grid.nx;
  spec.ny = cfg->grid.ny;
  spec.nz = cfg->grid.nz;
  spec.resolution_m = cfg->grid.resolution_m;
  const algo::GridDims dims{spec.nx, spec.ny, spec.nz, spec.resolution_m};
  Scanner scanner(*cfg, *cell, truth);

  // Support plane from an empty-carrier pass (calibration).
  algo::ScanBuffer raw(kMaxPoints);
  sim::PassSpec no_part;
  no_part.with_part = false;
  if (!scanner.scan(no_part, raw)) return 1;
  auto support = algo::fit_support_plane(raw.points(), {});
  if (!support) {
    std::fprintf(stderr, "%s\n", support.error().message.c_str());
    return 1;
  }
  const double support_threshold_m = cfg->support.distance_threshold_mm / 1000.0;
  auto scan_part = [&](const std::string& part, std::uint64_t seed, std::vector<algo::ScanPoint>& out) {
    auto pass = cell->random_pass(part, seed);
    if (!pass || !scanner.scan(*pass, raw)) return false;
    algo::remove_support(raw, support->plane, support_threshold_m);
    out.assign(raw.points().begin(), raw.points().end());
    return true;
  };

  // The whole shipped catalogue: the decision budget is stated for 15 classes (issue 10).
  const std::vector<std::string> names = {
      "plate_4h",     "plate_5h",        "slotted_plate",     "ribbed_v4",       "ribbed_v3",
      "ribbed_h5",    "louvred_panel",   "bracket_l",         "channel_u",       "tray",
      "frame_window", "chamfered_plate", "frame_two_windows", "perforated_fine", "perforated_coarse"};
  std::printf(
      "bench_cascade: %zu classes, grid %d x %d x %d at %.1f mm, scans from %s; %d training and %d test "
      "scans per class\n",
      names.size(), spec.nx, spec.ny, spec.nz, spec.resolution_m * 1e3,
      truth ? "the renderer's truth points" : "reconstruction (stripe + triangulation, true calibration)", n_train,
      n_test);

  // --- teach: template (first scan) -> distance map; training and test scans ----------------------------------------
  const Clock::time_point t_teach = Clock::now();
  std::vector<std::unique_ptr<Taught>> taught;
  algo::EdtScratch scratch(dims);
  std::vector<float> work(dims.cell_count());
  algo::OccupancyGrid grid(spec, kMaxPoints);
  algo::FeatureExtractor extractor(spec.ny, spec.nx, algo::feature_params_for(spec));
  cv::Mat depth;
  for (std::size_t c = 0; c < names.size(); ++c) {
    auto t = std::make_unique<Taught>();
    t->name = names[c];
    t->id = static_cast<int>(c) + 1;
    std::vector<algo::ScanPoint> first;
    if (!scan_part(t->name, 1, first)) return 1;
    grid.clear();
    (void)grid.accumulate(first);
    if (!algo::build_distance_map(grid.data(), dims, spec.origin_m, algo::kDefaultBandM, scratch, work.data(), t->map)
             .ok()) {
      return 1;
    }
    algo::surface_cells_from_map(t->map.view(), t->surface);
    t->centroid_m = algo::centroid_xy_m(first);
    for (int i = 0; i < n_train + n_test; ++i) {
      std::vector<algo::ScanPoint> s;
      if (!scan_part(t->name, 100 + static_cast<std::uint64_t>(i), s)) return 1;
      (i < n_train ? t->train : t->test).push_back(std::move(s));
    }
    for (const auto& s : t->train) {
      grid.clear();
      (void)grid.accumulate(s);
      grid.depth_image(depth);
      algo::FeatureVector f{};
      if (extractor.compute(depth, f) == algo::FeatureStatus::kOk) t->train_features.push_back(f);
    }
    std::fprintf(stderr, "  taught %-16s (%zu template points, %zu surface cells)\n", t->name.c_str(), first.size(),
                 t->surface.size());
    taught.push_back(std::move(t));
  }
  std::printf("teaching (scans + %zu maps): %.1f s\n", names.size(), ms_between(t_teach, Clock::now()) / 1000.0);

  // --- thresholds from the own-class training scans ------------------------------------------------------------------
  const algo::CascadeParams cascade_params = [&] {
    algo::CascadeParams p;
    p.per_cell_depth = !hull_only;
    return p;
  }();
  algo::PerfectMatchParams pm_params;
  pm_params.lc_m = cfg->pm.lc_m;
  pm_params.eta_plus = cfg->pm.eta_plus;
  pm_params.eta_minus = cfg->pm.eta_minus;
  pm_params.step_min_m = cfg->pm.step_min_m;
  pm_params.step_max_m = cfg->pm.step_max_m;
  pm_params.step_initial_m = cfg->pm.step_initial_m;
  pm_params.max_iterations = cfg->pm.max_iterations;
  algo::Cascade cascade(cascade_params, pm_params, spec);
  std::vector<algo::TemplateModel> models(taught.size());
  for (std::size_t c = 0; c < taught.size(); ++c) {
    Taught& t = *taught[c];
    algo::TemplateModel& m = models[c];
    m.class_index = static_cast<int>(c);
    m.part_id = t.id;
    m.map = t.map.view();
    m.centroid_m = t.centroid_m;
    m.surface_cells = t.surface;
    for (const auto& s : t.train) t.own.push_back(cascade.evaluate(m, s));
    m.thresholds = algo::learn_thresholds(t.own, cascade_params);
  }
  std::printf("\nown-class training scans against their template (max over %d scans) and the learnt thresholds\n",
              n_train);
  std::printf("%-16s %10s %10s %10s %10s | %10s %12s %12s\n", "class", "PM error", "miss mm2", "extra mm2", "cover",
              "max error", "max miss", "max extra");
  for (std::size_t c = 0; c < taught.size(); ++c) {
    const Taught& t = *taught[c];
    double e = 0, mi = 0, ex = 0, cov = 1.0;
    for (const auto& r : t.own) {
      e = std::max(e, r.pm.error);
      mi = std::max(mi, r.missing_area_m2);
      ex = std::max(ex, r.extra_area_m2);
      cov = std::min(cov, r.coverage);
    }
    const algo::TemplateThresholds& th = models[c].thresholds;
    std::printf("%-16s %10.2e %10.0f %10.0f %10.4f | %10.2e %12.0f %12.0f\n", t.name.c_str(), e, mi * 1e6, ex * 1e6,
                cov, th.max_error, th.max_missing_area_m2 * 1e6, th.max_extra_area_m2 * 1e6);
  }

  // --- siblings: scans of one class against the other's template
  // ------------------------------------------------------
  std::printf("\nsibling scans against the other template (min over the test scans; fails when above its max)\n");
  std::printf("%-28s %10s %10s %10s %8s\n", "scan -> template", "PM error", "miss mm2", "extra mm2", "passes");
  const std::pair<int, int> pairs[] = {{0, 1}, {1, 0}, {3, 4}, {4, 3}};
  for (const auto& [from, to] : pairs) {
    double e = 1e9, mi = 1e9, ex = 1e9;
    int passes = 0;
    for (const auto& s : taught[static_cast<std::size_t>(from)]->test) {
      const algo::MatchReport r = cascade.evaluate(models[static_cast<std::size_t>(to)], s);
      e = std::min(e, r.pm.error);
      mi = std::min(mi, r.missing_area_m2);
      ex = std::min(ex, r.extra_area_m2);
      passes += r.passes(models[static_cast<std::size_t>(to)].thresholds) ? 1 : 0;
    }
    const std::string label =
        taught[static_cast<std::size_t>(from)]->name + " -> " + taught[static_cast<std::size_t>(to)]->name;
    std::printf("%-28s %10.2e %10.0f %10.0f %5d/%zu\n", label.c_str(), e, mi * 1e6, ex * 1e6, passes,
                taught[static_cast<std::size_t>(from)]->test.size());
  }

  // --- SVM on the training features
  // ------------------------------------------------------------------------------------
  std::vector<algo::FeatureVector> x;
  std::vector<int> y;
  std::vector<algo::ClassInfo> classes;
  for (std::size_t c = 0; c < taught.size(); ++c) {
    classes.push_back({taught[c]->name, taught[c]->id});
    for (const auto& f : taught[c]->train_features) {
      x.push_back(f);
      y.push_back(static_cast<int>(c));
    }
  }
  algo::silence_libsvm();
  const algo::Scaler scaler = algo::Scaler::fit(x);
  algo::FeatureMask mask;
  mask.set();
  auto svm =
      algo::SvmModel::train(x, y, classes, mask, scaler, algo::SvmHyper{algo::KernelType::kRbf, 4.0, 1.0, 3, 0.0}, 1);
  if (!svm) {
    std::fprintf(stderr, "%s\n", svm.error().message.c_str());
    return 1;
  }

  // --- the timed tail: scan without carrier -> decision -------------------------------------------------------------
  std::vector<double> t_front, t_svm, t_cascade, t_total, cpu_total;
  struct Slow {
    double ms;
    std::string what;
  };
  std::vector<Slow> slowest;  // each test scan's slowest run, for the list of the slowest decisions
  int correct = 0, unknown = 0, wrong = 0, timeouts = 0, by_svm = 0, by_pm = 0;
  std::map<std::string, int> wrong_detail;
  std::vector<std::string> unknown_detail;
  for (std::size_t c = 0; c < taught.size(); ++c) {
    for (const auto& s : taught[c]->test) {
      for (int run = 0; run < runs; ++run) {
        const double cpu0 = thread_cpu_ms();
        const Clock::time_point t0 = Clock::now();
        grid.clear();
        (void)grid.accumulate(s);
        grid.depth_image(depth);
        algo::FeatureVector f{};
        (void)extractor.compute(depth, f);
        const Clock::time_point t1 = Clock::now();
        const std::span<const algo::ClassProbability> p = svm->predict(f);
        const Clock::time_point t2 = Clock::now();
        const algo::Decision d = cascade.decide(p, models, s, t0 + std::chrono::seconds(3));
        const Clock::time_point t3 = Clock::now();
        cpu_total.push_back(thread_cpu_ms() - cpu0);
        t_front.push_back(ms_between(t0, t1));
        t_svm.push_back(ms_between(t1, t2));
        t_cascade.push_back(ms_between(t2, t3));
        t_total.push_back(ms_between(t0, t3));
        {
          char what[160];
          const int top = p.empty() ? -1 : p[0].class_index;
          std::snprintf(what, sizeof what, "%s test %zu: %d verified, SVM first %s, decided %s",
                        taught[c]->name.c_str(), static_cast<std::size_t>(&s - taught[c]->test.data()),
                        d.verified_count, top >= 0 ? taught[static_cast<std::size_t>(top)]->name.c_str() : "-",
                        d.accepted() ? taught[static_cast<std::size_t>(d.class_index)]->name.c_str() : "unknown");
          if (run == 0 || t_total.back() > slowest.back().ms) {
            if (run != 0) slowest.pop_back();
            slowest.push_back({t_total.back(), what});
          }
        }
        if (run != 0) continue;
        if (d.source == algo::DecisionSource::kTimeout) {
          ++timeouts;
        } else if (!d.accepted()) {
          ++unknown;
          // Why: each of the SVM's best two against the thresholds.
          std::string why = taught[c]->name + ":";
          char buf[200];
          for (std::size_t k = 0; k < std::min<std::size_t>(2, p.size()); ++k) {
            const algo::TemplateModel& m = models[static_cast<std::size_t>(p[k].class_index)];
            const algo::MatchReport r = cascade.evaluate(m, s);
            std::snprintf(buf, sizeof buf, "  [%s p %.2f: error %.2e/%.2e, miss %.0f/%.0f, extra %.0f/%.0f mm2]",
                          taught[static_cast<std::size_t>(p[k].class_index)]->name.c_str(), p[k].probability,
                          r.pm.error, m.thresholds.max_error, r.missing_area_m2 * 1e6,
                          m.thresholds.max_missing_area_m2 * 1e6, r.extra_area_m2 * 1e6,
                          m.thresholds.max_extra_area_m2 * 1e6);
            why += buf;
          }
          unknown_detail.push_back(why);
        } else if (d.class_index == static_cast<int>(c)) {
          ++correct;
        } else {
          ++wrong;
          ++wrong_detail[taught[c]->name + " -> " + taught[static_cast<std::size_t>(d.class_index)]->name];
        }
        by_svm += d.source == algo::DecisionSource::kSvm ? 1 : 0;
        by_pm += d.source == algo::DecisionSource::kPm ? 1 : 0;
      }
    }
  }
  // Stage breakdown of one candidate: Perfect Match alone, the two-way check alone (at Perfect Match's pose).
  std::vector<double> t_pm, t_check;
  {
    algo::PerfectMatcher matcher(pm_params);
    for (std::size_t c = 0; c < taught.size(); ++c) {
      for (const auto& s : taught[c]->test) {
        const algo::TemplateModel& m = models[c];
        const Clock::time_point a = Clock::now();
        matcher.set_scan(s);
        const algo::PerfectMatchResult pm = matcher.match(m.map, m.centroid_m, matcher.centroid_start(m.centroid_m));
        const Clock::time_point b = Clock::now();
        const algo::MatchReport r = cascade.two_way_check(m, s, pm.pose);
        const Clock::time_point e = Clock::now();
        t_pm.push_back(ms_between(a, b));
        t_check.push_back(ms_between(b, e) + 0.0 * r.coverage);
      }
    }
  }
  if (const char* loops = std::getenv("BENCH_CASCADE_CHECK_LOOPS"); loops != nullptr) {  // for a profiler
    const algo::TemplateModel& m = models[0];
    const auto& s = taught[0]->test[0];
    algo::PerfectMatcher matcher(pm_params);
    matcher.set_scan(s);
    const algo::PerfectMatchResult pm = matcher.match(m.map, m.centroid_m, matcher.centroid_start(m.centroid_m));
    double sink = 0.0;
    for (int i = 0; i < std::atoi(loops); ++i) sink += cascade.two_way_check(m, s, pm.pose).coverage;
    std::printf("check loop done (%g)\n", sink);
  }
  const std::size_t decisions = t_total.size() / static_cast<std::size_t>(runs);
  std::printf("\n%zu test scans: %d correct, %d unknown, %d wrong, %d timeout (%d by SVM, %d by PM)\n", decisions,
              correct, unknown, wrong, timeouts, by_svm, by_pm);
  for (const auto& [what, n] : wrong_detail) std::printf("  wrong: %s x%d\n", what.c_str(), n);
  for (const auto& why : unknown_detail) std::printf("  unknown: %s\n", why.c_str());
  std::printf("\ntiming, one core, %zu decisions (%d runs each)      median      max   [ms]\n", t_total.size(), runs);
  std::printf("  grid + depth image + 74 features               %8.2f %8.2f\n", median(t_front), max_of(t_front));
  std::printf("  SVM probabilities                              %8.2f %8.2f\n", median(t_svm), max_of(t_svm));
  std::printf("  cascade (Perfect Match + two-way check)        %8.2f %8.2f\n", median(t_cascade), max_of(t_cascade));
  std::printf("  total (budget 30 ms median)                    %8.2f %8.2f\n", median(t_total), max_of(t_total));
  std::printf("  total, CPU time of the thread                  %8.2f %8.2f\n", median(cpu_total), max_of(cpu_total));
  std::printf("  one candidate: Perfect Match (set_scan + match) %7.2f %8.2f\n", median(t_pm), max_of(t_pm));
  std::printf("  one candidate: two-way check (both poses)       %7.2f %8.2f\n", median(t_check), max_of(t_check));
  std::sort(slowest.begin(), slowest.end(), [](const Slow& a, const Slow& b) { return a.ms > b.ms; });
  std::printf("slowest decisions (the slowest of each scan's runs):\n");
  for (std::size_t i = 0; i < std::min<std::size_t>(5, slowest.size()); ++i) {
    std::printf("  %8.2f ms  %s\n", slowest[i].ms, slowest[i].what.c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {  // allocation failure on a small machine (15 maps of 157 MiB)
    std::fprintf(stderr, "bench_cascade: %s\n", e.what());
    return 1;
  }
}
