// The SVM alone on a labelled scan folder (DIR/<part>/*.ply, as `cellsight eval --sim` writes it): accuracy,
// true class among the two most probable (what the cascade's Perfect Match candidates need), calibration of the
// top-1 probability (expected calibration error, 10 bins) and the confusions. Figures only.
//
//   bench_svm_eval --models DIR --scans DIR [--config F] [--calibration F]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "base/file_read.hpp"
#include "formats/calibration_file.hpp"
#include "formats/ply.hpp"

namespace {

using namespace cellsight;
using cellsight::Expected;
using cellsight::make_error;
namespace fs = std::filesystem;

constexpr int kBins = 10;

const char* value_of(int argc, char** argv, const char* flag) {
  for (int i = 1; i + 1 < argc; ++i) {
    if (std::string(argv[i]) == flag) return argv[i + 1];
  }
  return nullptr;
}

}  // namespace

int main(int argc, char** argv) {
  const char* models = value_of(argc, argv, "--models");
  const char* scans = value_of(argc, argv, "--scans");
  if (models == nullptr || scans == nullptr) {
    std::fprintf(stderr, "usage: bench_svm_eval --models DIR --scans DIR [--config F] [--calibration F]\n");
    return 2;
  }
  const char* config_arg = value_of(argc, argv, "--config");
  auto config = app::find_and_load_config(config_arg != nullptr ? config_arg : "");
  if (!config) {
    std::fprintf(stderr, "%s\n", config.error().message.c_str());
    return 2;
  }
  const char* cal = value_of(argc, argv, "--calibration");
  auto recogniser = app::make_recogniser(*config, models, cal != nullptr ? cal : app::default_calibration_path(*config),
                                         app::RecogniserMode::kSvmOnly);
  if (!recogniser) {
    std::fprintf(stderr, "%s\n", recogniser.error().message.c_str());
    return 2;
  }
  std::vector<fs::path> files;
  for (const auto& dir : fs::directory_iterator(scans)) {
    if (!dir.is_directory()) continue;
    for (const auto& f : fs::directory_iterator(dir.path())) {
      if (f.path().extension() == ".ply") files.push_back(f.path());
    }
  }
  std::sort(files.begin(), files.end());
  int total = 0, top1 = 0, top2 = 0;
  std::map<std::string, std::pair<int, int>> per_part;  // correct, scans
  std::map<std::string, int> confusions;
  std::vector<double> bin_conf(kBins, 0.0), bin_hit(kBins, 0.0), bin_n(kBins, 0.0);
  std::vector<double> prepare_ms;  // support removal .. features (the canonical frame included)
  for (const fs::path& f : files) {
    auto bytes = base::read_file(f.string(), app::kMaxTaughtScanBytes);
    if (!bytes) continue;
    auto points = formats::parse_ply(*bytes);
    if (!points) continue;
    const algo::Decision d =
        (*recogniser)->recognise(*points, std::chrono::steady_clock::now() + std::chrono::hours(1));
    prepare_ms.push_back(d.features_ms);
    const std::string truth = f.parent_path().filename().string();
    const std::string first(d.class_index >= 0 ? (*recogniser)->class_name(d.class_index) : "none");
    const std::string second(d.second_class_index >= 0 ? (*recogniser)->class_name(d.second_class_index) : "none");
    ++total;
    ++per_part[truth].second;
    const bool hit = first == truth;
    if (hit) {
      ++top1;
      ++per_part[truth].first;
    } else {
      ++confusions[truth + " -> " + first + (second == truth ? " (2nd)" : "")];
    }
    if (hit || second == truth) ++top2;
    const int bin = std::clamp(static_cast<int>(d.probability * kBins), 0, kBins - 1);
    bin_conf[static_cast<std::size_t>(bin)] += d.probability;
    bin_hit[static_cast<std::size_t>(bin)] += hit ? 1.0 : 0.0;
    bin_n[static_cast<std::size_t>(bin)] += 1.0;
  }
  if (total == 0) {
    std::fprintf(stderr, "no scans under %s\n", scans);
    return 2;
  }
  double ece = 0.0;
  for (int b = 0; b < kBins; ++b) {
    const auto i = static_cast<std::size_t>(b);
    if (bin_n[i] > 0) ece += std::abs(bin_conf[i] - bin_hit[i]) / total;
  }
  std::printf("svm alone: %d scans, top-1 %.2f %%, top-2 %.2f %%, ECE %.3f\n", total, 100.0 * top1 / total,
              100.0 * top2 / total, ece);
  std::sort(prepare_ms.begin(), prepare_ms.end());
  std::printf("  carrier removal .. features: median %.1f ms, max %.1f ms (wall time; the machine may be shared)\n",
              prepare_ms[prepare_ms.size() / 2], prepare_ms.back());
  for (const auto& [part, c] : per_part) std::printf("  %-20s %d / %d\n", part.c_str(), c.first, c.second);
  for (const auto& [what, n] : confusions) std::printf("  confused: %s x%d\n", what.c_str(), n);
  // One scan's preparation, and its canonical mapping alone, on this thread (figures: wall time, median of 20).
  if (auto support = app::load_support_plane(cal != nullptr ? cal : app::default_calibration_path(*config));
      support && !files.empty()) {
    auto bytes = base::read_file(files.front().string(), app::kMaxTaughtScanBytes);
    auto points = bytes ? formats::parse_ply(*bytes) : Expected<std::vector<algo::ScanPoint>>(make_error("unread"));
    if (points) {
      app::ScanPreparer preparer(*config, *support, points->size() + 1);
      const algo::GridSpec spec = app::grid_spec(*config);
      algo::CanonicalScratch scratch(spec);
      std::vector<algo::ScanPoint> out(points->size());
      algo::CanonicalPose pose;
      std::vector<double> prepare_t, canonical_t;
      for (int run = 0; run < 20; ++run) {
        auto t0 = std::chrono::steady_clock::now();
        (void)preparer.prepare(*points);
        auto t1 = std::chrono::steady_clock::now();
        (void)algo::canonicalise(preparer.part_points(), spec, {}, scratch, out, pose);
        auto t2 = std::chrono::steady_clock::now();
        prepare_t.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
        canonical_t.push_back(std::chrono::duration<double, std::milli>(t2 - t1).count());
      }
      std::sort(prepare_t.begin(), prepare_t.end());
      std::sort(canonical_t.begin(), canonical_t.end());
      std::printf("  %s: %zu points, %zu on the part: prepare %.2f ms, of it canonical frame %.2f ms (median of 20)\n",
                  files.front().filename().c_str(), points->size(), preparer.part_points().size(), prepare_t[10],
                  canonical_t[10]);
    }
  }
  for (int b = 0; b < kBins; ++b) {
    const auto i = static_cast<std::size_t>(b);
    if (bin_n[i] > 0) {
      std::printf("  p1 in [%.1f, %.1f): %3.0f scans, mean p1 %.3f, accuracy %.3f\n", b / 10.0, (b + 1) / 10.0,
                  bin_n[i], bin_conf[i] / bin_n[i], bin_hit[i] / bin_n[i]);
    }
  }
  return 0;
}
