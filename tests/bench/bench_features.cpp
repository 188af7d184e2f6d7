// Benchmark of the recognition front end on one core: support removal + grid + depth image + 74 features for a
// simulated scan (budget 15 ms), and SVM probabilities of a 15-class model (budget 1 ms). Prints medians.
#include <sched.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "algo/features.hpp"
#include "algo/grid.hpp"
#include "algo/scan.hpp"
#include "algo/support.hpp"
#include "algo/svm.hpp"
#include "app/config.hpp"
#include "app/sim_setup.hpp"

namespace {

using namespace cellsight;
using Clock = std::chrono::steady_clock;

constexpr std::size_t kMaxPoints = 800000;
constexpr int kScanRuns = 40;
constexpr int kPredictRuns = 2000;

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// Every truth point of a pass (part and carrier): what a perfect stripe extractor and triangulation would deliver.
void render_pass(sim::SimCell& cell, const sim::PassSpec& pass, algo::ScanBuffer& scan) {
  if (!cell.begin_pass(pass).ok()) return;
  cv::Mat image;
  std::vector<sim::TruthPoint> truth;
  scan.clear();
  for (int f = 0; f < cell.frame_count(); ++f) {
    truth.clear();
    cell.render_frame(f, 1500.0, image, &truth);
    for (const sim::TruthPoint& t : truth) {
      scan.push({static_cast<float>(t.p_carrier_m.x()), static_cast<float>(t.p_carrier_m.y()),
                 static_cast<float>(t.p_carrier_m.z()), static_cast<std::uint16_t>(f), 0});
    }
  }
}

}  // namespace

int main() {
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

  // Support plane from an empty-carrier pass (calibration, not timed).
  algo::ScanBuffer empty(kMaxPoints);
  sim::PassSpec no_part;
  no_part.with_part = false;
  render_pass(*cell, no_part, empty);
  auto support = algo::fit_support_plane(empty.points(), {});
  if (!support) {
    std::fprintf(stderr, "%s\n", support.error().message.c_str());
    return 1;
  }
  const double threshold_m = cfg->support.distance_threshold_mm / 1000.0;

  std::printf("recognition front end, one core, median of %d runs per scan\n", kScanRuns);
  std::printf("%-18s %9s %9s %10s %10s %10s %10s %10s\n", "part", "points", "part pts", "support ms", "grid ms",
              "depth ms", "feat ms", "total ms");
  algo::OccupancyGrid grid(spec, kMaxPoints);
  algo::FeatureExtractor extractor(spec.ny, spec.nx, algo::feature_params_for(spec));
  algo::ScanBuffer raw(kMaxPoints), work(kMaxPoints);
  cv::Mat depth;
  algo::FeatureVector features{};
  for (const std::string part : {"louvred_panel", "ribbed_v4", "perforated_fine", "frame_two_windows"}) {
    auto pass = cell->random_pass(part, 7);
    if (!pass) continue;
    render_pass(*cell, *pass, raw);
    std::vector<double> t_support, t_grid, t_depth, t_features, t_total;
    std::size_t kept = 0;
    for (int run = 0; run < kScanRuns; ++run) {
      work.clear();
      for (const algo::ScanPoint& p : raw.points()) work.push(p);  // fresh copy, not timed
      const Clock::time_point t0 = Clock::now();
      algo::remove_support(work, support->plane, threshold_m);
      const Clock::time_point t1 = Clock::now();
      grid.clear();
      (void)grid.accumulate(work.points());
      const Clock::time_point t2 = Clock::now();
      grid.depth_image(depth);
      const Clock::time_point t3 = Clock::now();
      const algo::FeatureStatus status = extractor.compute(depth, features);
      const Clock::time_point t4 = Clock::now();
      if (status != algo::FeatureStatus::kOk) std::fprintf(stderr, "features: %s\n", algo::to_string(status).data());
      kept = work.size();
      auto ms = [](Clock::time_point a, Clock::time_point b) {
        return std::chrono::duration<double, std::milli>(b - a).count();
      };
      t_support.push_back(ms(t0, t1));
      t_grid.push_back(ms(t1, t2));
      t_depth.push_back(ms(t2, t3));
      t_features.push_back(ms(t3, t4));
      t_total.push_back(ms(t0, t4));
    }
    std::printf("%-18s %9zu %9zu %10.3f %10.3f %10.3f %10.3f %10.3f\n", part.c_str(), raw.size(), kept,
                median(t_support), median(t_grid), median(t_depth), median(t_features), median(t_total));
  }

  // SVM: 15 classes x 35 training scans (the thesis's training set size), synthetic clusters in 74-D.
  std::mt19937_64 rng(1);
  std::normal_distribution<double> g(0.0, 1.0);
  constexpr int kClasses = 15, kPerClass = 35;
  std::vector<std::vector<double>> centres(kClasses, std::vector<double>(algo::kFeatureCount));
  for (auto& c : centres) {
    for (double& v : c) v = 0.6 * g(rng);
  }
  std::vector<algo::FeatureVector> x;
  std::vector<int> y;
  std::vector<algo::ClassInfo> classes;
  for (int c = 0; c < kClasses; ++c) classes.push_back({"part_" + std::to_string(c), c + 1});
  for (int i = 0; i < kPerClass; ++i) {
    for (int c = 0; c < kClasses; ++c) {
      algo::FeatureVector f{};
      for (int k = 0; k < algo::kFeatureCount; ++k) {
        f[static_cast<std::size_t>(k)] =
            static_cast<float>(centres[static_cast<std::size_t>(c)][static_cast<std::size_t>(k)] + g(rng));
      }
      x.push_back(f);
      y.push_back(c);
    }
  }
  const algo::Scaler scaler = algo::Scaler::fit(x);
  std::printf("\nSVM probabilities, %d classes x %d training scans, median of %d predictions\n", kClasses, kPerClass,
              kPredictRuns);
  std::printf("%-62s %6s %10s %10s\n", "model", "SVs", "train s", "predict ms");
  for (const int active : {15, 30, 74}) {
    for (const algo::KernelType kernel : {algo::KernelType::kRbf, algo::KernelType::kPoly}) {
      algo::FeatureMask mask;
      for (int k = 0; k < active; ++k) mask.set(static_cast<std::size_t>(k));
      algo::SvmHyper hyper{kernel, 4.0, 1.0, 4, 0.0};
      const Clock::time_point t0 = Clock::now();
      auto model = algo::SvmModel::train(x, y, classes, mask, scaler, hyper, 1);
      const double train_s = ms_since(t0) / 1000.0;
      if (!model) {
        std::fprintf(stderr, "%s\n", model.error().message.c_str());
        return 1;
      }
      std::vector<double> t;
      double sink = 0.0;
      for (int i = 0; i < kPredictRuns; ++i) {
        const algo::FeatureVector& f = x[static_cast<std::size_t>(i) % x.size()];
        const Clock::time_point p0 = Clock::now();
        sink += model->predict(f)[0].probability;
        t.push_back(ms_since(p0));
      }
      std::printf("%-62s %6d %10.2f %10.4f%s\n", hyper.describe(active).c_str(), model->support_vectors(), train_s,
                  median(t), sink > 0 ? "" : " ?");
    }
  }
  return 0;
}
