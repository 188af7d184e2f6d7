// Offline training of the recogniser (thesis 2.6.1, Fig. 2.15): simulated-annealing feature selection, each
// candidate scored by stratified k-fold cross-validation over the classifier's parameter grid, then the final
// probability SVM on the whole training split, measured on the held-back test split. kNN and a small MLP run in
// the same frame for comparison (thesis 4.2).
//
// This is a tool path, not the production loop: it allocates, and it is the one algo stage that runs threads of
// its own (the cross-validation tasks, joined before every return).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "algo/features.hpp"
#include "algo/result.hpp"
#include "algo/svm.hpp"

namespace cellsight::algo {

struct Dataset {
  std::vector<ClassInfo> classes;
  std::vector<FeatureVector> features;
  std::vector<int> labels;  // index into classes, one per feature vector
  // Optional, one per sample when present. group: a taught scan and its synthetic variants (algo/augment) share
  // one id, so they never land on both sides of a split or of a CV fold (empty: every sample its own group).
  // variant: 0 for the taught scan itself, k >= 1 for its k-th variant (empty: all 0).
  std::vector<int> groups;
  std::vector<int> variants;
  [[nodiscard]] std::size_t size() const { return labels.size(); }
  [[nodiscard]] int group_of(std::size_t i) const { return groups.empty() ? static_cast<int>(i) : groups[i]; }
  [[nodiscard]] int variant_of(std::size_t i) const { return variants.empty() ? 0 : variants[i]; }
  void push(const FeatureVector& f, int label, int group, int variant);
};
// Labels in range, one per sample, every feature finite, at least two classes, groups and variants either absent
// or one per sample (a group's samples share its label).
[[nodiscard]] Status validate_dataset(const Dataset& data);

struct DatasetSplit {
  Dataset train, test;
};
// Thesis 6.4.2: per class, train_per_class random taught scans for training (35 of 50 there), the rest held back
// for the generalisation test. A training scan takes its synthetic variants along; a held-back scan goes alone (its
// variants are dropped: the test measures real scans only). A class with no scan left for testing is refused.
[[nodiscard]] Expected<DatasetSplit> split_per_class(const Dataset& all, int train_per_class, std::uint64_t seed);

// Stratified k-fold assignment (thesis 2.5): the fold of every sample, each class's groups spread evenly over the
// folds, every group (a taught scan and its variants) whole in one fold, so a variant never tests its own origin.
// Refuses a class with fewer groups than folds, which would leave a fold without it.
[[nodiscard]] Expected<std::vector<int>> stratified_folds(const Dataset& data, int folds, std::uint64_t seed);

enum class Classifier : std::uint8_t { kSvm, kKnn, kMlp };
[[nodiscard]] std::string_view to_string(Classifier classifier);

struct AnnealingParams {
  // Thesis 4.2 / 6.4.2: T0 = 200, T <- 0.95 T per iteration. The cost is the CV error in percentage points
  // (plus the feature penalty), the unit in which those temperatures make sense: early on a candidate 1 point
  // worse is accepted with p = exp(-1/200) ~ 1, after 100 iterations (T ~ 1.2) with p ~ 0.43, at the end never.
  double start_temperature = 200.0;
  double cooling_ratio = 0.95;
  int iterations = 200;
  int initial_active = 15;     // thesis 6.4.2: the first solution has 15 active features
  FeatureMask initial_mask{};  // used when not empty; otherwise the initial_active best by Fisher score
  int min_active = 1;
  // Ties in accuracy go to the smaller feature set (thesis: "the best minimum number subset of features"):
  // each active feature costs this many percentage points.
  double feature_penalty_pct = 0.01;
};

struct MlpParams {
  std::vector<int> hidden = {32};  // neurons per hidden layer (one or two layers, thesis 4.2.2)
  int epochs = 150;
  int batch = 32;
  double learning_rate = 0.01;  // Adam
  double weight_decay = 1e-4;   // L2, keeps the extra weights small (thesis 2.4.2.3)
  std::uint64_t seed = 1;
};

struct TrainParams {
  AnnealingParams annealing;
  int folds = 5;
  std::uint64_t seed = 1;
  int threads = 0;  // cross-validation threads; 0 = std::thread::hardware_concurrency()
  // The annealing scores its candidates on the taught scans plus at most this many synthetic variants of each
  // (-1: all); the final model always learns from all of them. Each candidate costs k-fold x grid SVM trainings,
  // so the search runs on the smaller set (the selection needs the ranking of masks, not the last percent).
  int search_variants = -1;
  // Issue 11: with more classes than this, the annealing scores its candidates on this many of them only, the
  // hardest distinctions (search_class_subset); the final model learns from all. 0 = always all classes. At or
  // below it the thesis search runs unchanged. Per-step cost grows ~quadratically with the classes (one-vs-one
  // SVMs): measured 0.43 s at 15, 4.8 s at 50, 18.9 s at 100 classes on the 2-core machine.
  int search_classes = 40;
  // With that class subset in use, the annealing scores the whole C x gamma grid only for the initial mask and
  // then the grid points within this many steps (in C and in gamma) of the best mask's best point, re-centred as
  // the best changes (gamma scales with the active features, so the optimum moves little); -1 = the whole grid
  // always. Radius 1 on the 7 x 4 grid: at most 3 x 3 = 9 of 28 trainings per fold.
  int search_grid_radius = 1;
  // SVM grid searched for every candidate mask (thesis 6.4.2): C x gamma factor i (gamma = i / active
  // features) [x degree for the polynomial kernel]. Measured on this 2-core machine, 15 classes x 35 scans,
  // 200 iterations: RBF 2.8 min (5.2 min while the machine was loaded), polynomial with 4 degrees ~3.7 min.
  KernelType kernel = KernelType::kRbf;
  std::vector<double> c_grid = {0.25, 1.0, 4.0, 16.0, 64.0, 256.0, 1024.0};
  std::vector<double> gamma_factors = {1.0, 10.0, 100.0, 1000.0};
  std::vector<int> poly_degrees = {2, 3, 4, 5};
  double poly_coef0 = 0.0;  // thesis eq. 6.4 has none
  // --compare: kNN (k from CV) and an MLP (hidden layout from CV), each with its own annealing run.
  bool compare = false;
  std::vector<int> knn_k = {1, 3, 5, 7, 9};
  int knn_iterations = -1;  // -1: annealing.iterations
  std::vector<std::vector<int>> mlp_layouts = {{16}, {32}, {32, 16}};
  MlpParams mlp;            // hidden is taken from mlp_layouts
  int mlp_iterations = 25;  // an MLP fold costs ~50x an SVM fold
};

struct TrainingProgress {
  Classifier classifier = Classifier::kSvm;
  int stage = 0, stages = 1;          // annealing runs: SVM [, kNN, MLP]
  int iteration = 0, iterations = 0;  // annealing steps done / planned in this stage
  double candidate_accuracy = 0.0;    // CV accuracy of the last candidate
  double best_accuracy = 0.0;
  int best_active = 0;
  double elapsed_s = 0.0;  // since train_recogniser started
  double eta_s = 0.0;      // until this stage ends, from its mean step time
};
using ProgressCallback = std::function<void(const TrainingProgress&)>;

struct AnnealingStep {
  int iteration = 0;
  double temperature = 0.0;
  double candidate_accuracy = 0.0, current_accuracy = 0.0, best_accuracy = 0.0;
  int candidate_active = 0;
  bool accepted = false;
};

inline constexpr int kCalibrationBins = 10;
struct CalibrationBin {
  double lo = 0.0, hi = 0.0;  // top probability range
  int scans = 0;
  double mean_probability = 0.0;  // mean top probability of its scans
  double accuracy = 0.0;          // share of them classified right
};

struct ClassifierReport {
  Classifier classifier = Classifier::kSvm;
  std::string parameters;      // the chosen hyper-parameters, readable
  double cv_accuracy = 0.0;    // k-fold accuracy of the chosen mask and parameters on the training split
  double test_accuracy = 0.0;  // on the held-back test split (NaN when it is empty)
  // SVM only, on the held-back test split: the true class among the two most probable, and the calibration of
  // the top probability (expected calibration error over kCalibrationBins equal-width bins; NaN when empty).
  double test_top2 = 0.0;
  double test_ece = 0.0;
  std::vector<CalibrationBin> reliability;  // the bins with at least one scan
  FeatureMask mask{};
  std::vector<std::string> features;        // names of the active features
  std::vector<std::vector<int>> confusion;  // [true class][predicted class] on the test split
  std::vector<AnnealingStep> curve;         // accuracy per annealing step (step 0 = the initial mask)
  int evaluations = 0;                      // masks scored by cross-validation
  int cache_hits = 0;                       // candidates already scored earlier
  double seconds = 0.0;
  bool stopped = false;  // the stop flag ended its annealing early
};

struct TrainingReport {
  std::vector<std::string> class_names;
  int train_samples = 0, test_samples = 0, folds = 0, threads = 0;  // taught scans, not counting variants
  int synthetic_samples = 0;  // synthetic variants of the training scans the final model also learnt from
  int search_samples = 0;     // samples (scans and variants) the annealing scored its candidates on
  // The classes the SVM annealing scored its candidates on (search_class_subset), in class order; empty: all.
  std::vector<std::string> search_class_names;
  int search_grid_radius = -1;  // the C x gamma neighbourhood scored after the first mask; -1: the whole grid
  ClassifierReport svm;
  SvmHyper svm_hyper{};
  std::optional<ClassifierReport> knn, mlp;
  bool stopped = false;
  double seconds = 0.0;
};

struct TrainingResult {
  SvmModel model;
  TrainingReport report;
};

// The classes the annealing searches on when the catalogue has more than `limit` (issue 11), ascending class
// indices: greedily the classes whose scaled-feature centroid (taught scans) is nearest to another class's, each
// with that nearest neighbour, near twins first, until `limit` are taken. These are the distinctions the feature
// mask must make; well-separated classes are told apart by almost any mask. Deterministic (ties by index). Empty
// when limit <= 0 or every class fits.
[[nodiscard]] std::vector<int> search_class_subset(const Dataset& train, int limit);

// One line for people on how the SVM's feature search was scaled, e.g. "annealing scored masks on 40 of 300
// classes (the nearest centroids); the final SVM learnt from all"; empty when it searched on every class.
[[nodiscard]] std::string search_scope_text(const TrainingReport& report);

// The whole training of Fig. 2.15. Deterministic for params.seed (thread count and timing do not change the
// result). `progress` is called from this thread after every annealing step; `stop` (e.g. set by a SIGINT
// handler) ends the annealing at the next step and the model is trained on the best mask found so far.
[[nodiscard]] Expected<TrainingResult> train_recogniser(const DatasetSplit& split, const TrainParams& params,
                                                        const ProgressCallback& progress = {},
                                                        const std::atomic<bool>* stop = nullptr);

// ---- the comparison classifiers, usable on their own -------------------------------------------------------------

// k nearest neighbours by Euclidean distance (thesis 2.4.1), majority vote; a tie goes to the tied class with the
// nearest member. rows: n x dims, row-major.
[[nodiscard]] int knn_classify(std::span<const double> rows, std::span<const int> labels, int dims, int classes, int k,
                               std::span<const double> x);

// Feed-forward network (thesis 2.4.2, eq. 2.18-2.21): tanh hidden layers (eq. 2.17), softmax output,
// cross-entropy, mini-batch Adam. Deterministic for params.seed.
class Mlp {
 public:
  void train(std::span<const double> rows, std::span<const int> labels, int dims, int classes, const MlpParams& params);
  // Class probabilities (softmax); out.size() must be the class count.
  void probabilities(std::span<const double> x, std::span<double> out) const;
  [[nodiscard]] int predict(std::span<const double> x) const;
  [[nodiscard]] int classes() const { return layers_.empty() ? 0 : layers_.back().out; }

 private:
  struct Layer {
    int in = 0, out = 0;
    std::vector<double> w, b;  // w: out x in
  };
  // train()'s steps on one sample (forward pass and softmax, back-propagation into the batch's gradients) and on
  // one batch (the Adam update).
  struct TrainingBuffers;
  void forward(TrainingBuffers& b) const;
  void backward(TrainingBuffers& b, int label) const;
  void adam_step(TrainingBuffers& b, std::size_t batch_size, int step, const MlpParams& params);

  std::vector<Layer> layers_;
};

}  // namespace cellsight::algo
