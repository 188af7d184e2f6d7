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

#include "algo/ply.hpp"
#include "app/model_db.hpp"
#include "app/calibration_file.hpp"
#include "app/config.hpp"
#include "app/recognition.hpp"

namespace {

using namespace cellsight;
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
  for (const fs::path& f : files) {
    auto bytes = app::read_whole_file(f.string());
    if (!bytes) continue;
    auto points = algo::parse_ply(*bytes);
    if (!points) continue;
    const algo::Decision d = (*recogniser)->recognise(*points, std::chrono::steady_clock::now() + std::chrono::hours(1));
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
  for (const auto& [part, c] : per_part) std::printf("  %-20s %d / %d\n", part.c_str(), c.first, c.second);
  for (const auto& [what, n] : confusions) std::printf("  confused: %s x%d\n", what.c_str(), n);
  for (int b = 0; b < kBins; ++b) {
    const auto i = static_cast<std::size_t>(b);
    if (bin_n[i] > 0) {
      std::printf("  p1 in [%.1f, %.1f): %3.0f scans, mean p1 %.3f, accuracy %.3f\n", b / 10.0, (b + 1) / 10.0,
                  bin_n[i], bin_conf[i] / bin_n[i], bin_hit[i] / bin_n[i]);
    }
  }
  return 0;
}
