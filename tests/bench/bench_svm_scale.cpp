// How the SVM's training and prediction grow with the number of part types (issue 11): synthetic feature vectors
// (K classes, each a random centre in the 74-feature space with per-sample noise, plus synthetic variants as
// train's augmentation makes them), timed through the code train uses. Figures only.
//
//   bench_svm_scale [--classes 15,50,100,300] [--scans 12] [--variants 1] [--iterations 2] [--threads 2]
//                   [--search-classes 40] [--noise 0.08]
// --noise: per-feature sample spread around the class centre (larger: classes overlap, accuracy below 100 %).
// --search-classes: TrainParams::search_classes (0 = the annealing scores on every class); the "search" column
// says how many classes it used.
// --iterations: annealing steps to time (each scores one mask by k-fold CV over the C x gamma grid); the report
// extrapolates to the configured 200. The final model is trained with Platt's fit, as train ships it.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "algo/training.hpp"

namespace {

using namespace cellsight;
using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

std::vector<int> int_list(const char* text) {
  std::vector<int> out;
  std::stringstream s(text);
  for (std::string item; std::getline(s, item, ',');) out.push_back(std::atoi(item.c_str()));
  return out;
}

// K classes: centres uniform in [0, 1]^74, samples centre + N(0, 0.08) per feature (classes overlap a little, as
// near twins do); `variants` extra samples per scan in its group, as train's augmentation adds them.
algo::Dataset synthetic(int classes, int scans, int variants, float noise_sd, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> centre(0.0F, 1.0F);
  std::normal_distribution<float> noise(0.0F, noise_sd);
  algo::Dataset d;
  int group = 0;
  for (int c = 0; c < classes; ++c) {
    d.classes.push_back({"c" + std::to_string(c), c + 1});
    algo::FeatureVector mean{};
    for (float& v : mean) v = centre(rng);
    for (int s = 0; s < scans; ++s, ++group) {
      for (int v = 0; v <= variants; ++v) {
        algo::FeatureVector f = mean;
        for (float& x : f) x += noise(rng);
        d.push(f, c, group, v);
      }
    }
  }
  return d;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<int> class_counts = {15, 50, 100, 300};
  int scans = 12, variants = 1, iterations = 2, threads = 2;
  int search_classes = algo::TrainParams{}.search_classes;
  float noise_sd = 0.08F;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::strcmp(argv[i], "--classes") == 0) class_counts = int_list(argv[i + 1]);
    if (std::strcmp(argv[i], "--scans") == 0) scans = std::atoi(argv[i + 1]);
    if (std::strcmp(argv[i], "--variants") == 0) variants = std::atoi(argv[i + 1]);
    if (std::strcmp(argv[i], "--iterations") == 0) iterations = std::atoi(argv[i + 1]);
    if (std::strcmp(argv[i], "--threads") == 0) threads = std::atoi(argv[i + 1]);
    if (std::strcmp(argv[i], "--search-classes") == 0) search_classes = std::atoi(argv[i + 1]);
    if (std::strcmp(argv[i], "--noise") == 0) noise_sd = static_cast<float>(std::atof(argv[i + 1]));
  }
  algo::silence_libsvm();
  std::printf("bench_svm_scale: %d scans per class (+%d variants each), %d annealing steps timed, %d threads\n", scans,
              variants, iterations, threads);
  std::printf("%8s %8s %8s %12s %12s %12s %14s %12s %12s %10s\n", "classes", "samples", "search", "train s",
              "per step s", "200 steps s", "final model s", "predict med", "predict max", "test acc");
  for (const int k : class_counts) {
    const algo::Dataset all = synthetic(k, scans, variants, noise_sd, 17);
    auto split = algo::split_per_class(all, std::max(2, scans * 2 / 3), 5);
    if (!split) {
      std::fprintf(stderr, "%s\n", split.error().message.c_str());
      return 1;
    }
    algo::TrainParams params;
    params.annealing.iterations = iterations;
    params.threads = threads;
    params.folds = std::min(5, std::max(2, scans * 2 / 3));
    params.search_variants = 1;
    params.search_classes = search_classes;
    const Clock::time_point t0 = Clock::now();
    auto result = algo::train_recogniser(*split, params);
    const double total_s = seconds_since(t0);
    if (!result) {
      std::fprintf(stderr, "%s\n", result.error().message.c_str());
      return 1;
    }
    // The final model alone, to split the total into search and final fit.
    const algo::Dataset& train = split->train;
    const Clock::time_point t1 = Clock::now();
    auto final_model = algo::SvmModel::train(train.features, train.labels, train.classes, result->model.mask(),
                                             result->model.scaler(), result->model.hyper(), 1);
    const double final_s = seconds_since(t1);
    if (!final_model) return 1;
    std::vector<double> predict_ms;
    int correct = 0;
    for (std::size_t i = 0; i < split->test.size(); ++i) {
      const Clock::time_point t = Clock::now();
      const auto p = final_model->predict(split->test.features[i]);
      predict_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t).count());
      correct += !p.empty() && p[0].class_index == split->test.labels[i] ? 1 : 0;
    }
    std::sort(predict_ms.begin(), predict_ms.end());
    // The annealing alone (the initial mask is scored too): total - final also holds the test scoring, which
    // at 300 classes (1200 test scans x 2 predictions of ~16 ms) is larger than a few steps.
    const double per_step = result->report.svm.seconds / (iterations + 1);
    const std::size_t searched =
        result->report.search_class_names.empty() ? train.classes.size() : result->report.search_class_names.size();
    std::printf("%8d %8zu %8zu %12.1f %12.2f %12.0f %14.2f %9.2f ms %9.2f ms %9.1f %%\n", k, train.size(), searched,
                total_s, per_step, per_step * 201 + final_s, final_s, predict_ms[predict_ms.size() / 2],
                predict_ms.back(), 100.0 * correct / static_cast<double>(split->test.size()));
    std::fflush(stdout);
  }
  return 0;
}
