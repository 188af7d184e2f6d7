// Recogniser training: simulated annealing over the feature mask, k-fold CV on threads, final SVM; kNN and MLP.
#include "algo/training.hpp"

#include <libsvm/svm.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <numeric>
#include <random>
#include <tuple>
#include <unordered_map>

#include "algo/splitmix.hpp"
#include "base/parallel_for.hpp"

namespace cellsight::algo {

namespace {

using Clock = std::chrono::steady_clock;

constexpr int kMaxDegree = 10;
constexpr double kPercent = 100.0;

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

bool stop_requested(const std::atomic<bool>* stop) {
  return stop != nullptr && stop->load(std::memory_order_relaxed);
}

// Largest count; 0 for an empty list (written out: GCC 12 flags *max_element as a possible null dereference).
int largest(const std::vector<int>& v) {
  int top = 0;
  for (int x : v) top = std::max(top, x);
  return top;
}

// What every candidate evaluation shares: the scaled training split and its folds.
struct Context {
  const Dataset* train = nullptr;
  int n = 0, classes = 0, folds = 0, threads = 1;
  std::vector<int> fold;  // per sample
  // Per sample: 1 when its prediction counts toward the CV accuracy. Only taught scans count: a synthetic variant
  // helps train the other folds' models but does not score, so CV accuracy measures real scans.
  std::vector<std::uint8_t> scored;
  int scored_n = 0;
  std::vector<double> scaled;  // n x kFeatureCount, Scaler applied
  const std::atomic<bool>* stop = nullptr;
};

// The active columns of a scaled n x 74 matrix, row-major n x mask.count().
std::vector<double> gather(std::span<const double> scaled, std::size_t n, const FeatureMask& mask) {
  const std::size_t d = mask.count();
  std::vector<double> rows(n * d);
  for (std::size_t i = 0; i < n; ++i) {
    std::size_t k = 0;
    for (std::size_t f = 0; f < kFeatureCount; ++f) {
      if (mask.test(f)) rows[i * d + k++] = scaled[i * kFeatureCount + f];
    }
  }
  return rows;
}

std::vector<double> scale_all(const Scaler& scaler, std::span<const FeatureVector> features) {
  std::vector<double> out(features.size() * kFeatureCount);
  for (std::size_t i = 0; i < features.size(); ++i) {
    for (int f = 0; f < kFeatureCount; ++f) {
      out[i * kFeatureCount + static_cast<std::size_t>(f)] = scaler.scale(f, features[i][static_cast<std::size_t>(f)]);
    }
  }
  return out;
}

// correct[param] = the sum of task_correct over param's folds; task t is fold t % folds of param t / folds.
void sum_over_folds(const std::vector<int>& task_correct, int folds, std::vector<int>& correct) {
  std::fill(correct.begin(), correct.end(), 0);
  for (std::size_t t = 0; t < task_correct.size(); ++t) correct[t / static_cast<std::size_t>(folds)] += task_correct[t];
}

// A classifier family as the annealing sees it: a parameter grid and "how many samples does each grid point
// classify correctly over all k folds" for a mask.
class Evaluator {
 public:
  virtual ~Evaluator() = default;
  [[nodiscard]] virtual int grid_size() const = 0;
  [[nodiscard]] virtual std::string describe(int param, int active) const = 0;
  // Fills correct[param]; false when stopped (the result is then incomplete and discarded).
  virtual bool evaluate(const Context& ctx, const FeatureMask& mask, std::vector<int>& correct) = 0;
  // Score only the grid's neighbourhood of `param` from now on (TrainParams::search_grid_radius); no-op by default.
  virtual void focus(int /*param*/) {}
};

class SvmEvaluator final : public Evaluator {
 public:
  explicit SvmEvaluator(const TrainParams& p, int radius = -1)
      : radius_(radius),
        c_count_(static_cast<int>(p.c_grid.size())),
        gamma_count_(static_cast<int>(p.gamma_factors.size())) {
    // Grid order is the tie-break order: lower degree, then smaller gamma, then smaller C (the simpler model).
    const std::vector<int> degrees = p.kernel == KernelType::kPoly ? p.poly_degrees : std::vector<int>{3};
    for (int degree : degrees) {
      for (double gamma_factor : p.gamma_factors) {
        for (double c : p.c_grid) {
          SvmHyper h;
          h.kernel = p.kernel;
          h.c = c;
          h.gamma_factor = gamma_factor;
          h.degree = degree;
          h.coef0 = p.poly_coef0;
          grid_.push_back(h);
        }
      }
    }
    for (int i = 0; i < grid_size(); ++i) active_.push_back(i);
  }
  void focus(int param) override {
    if (radius_ < 0) return;
    // Grid index = (degree x gamma_count + gamma) x c_count + c; the degree stays that of `param`.
    const int c0 = param % c_count_, g0 = (param / c_count_) % gamma_count_, plane = param / (c_count_ * gamma_count_);
    active_.clear();
    for (int g = std::max(0, g0 - radius_); g <= std::min(gamma_count_ - 1, g0 + radius_); ++g) {
      for (int c = std::max(0, c0 - radius_); c <= std::min(c_count_ - 1, c0 + radius_); ++c)
        active_.push_back((plane * gamma_count_ + g) * c_count_ + c);
    }
  }
  [[nodiscard]] int grid_size() const override { return static_cast<int>(grid_.size()); }
  [[nodiscard]] std::string describe(int param, int active) const override {
    return grid_[static_cast<std::size_t>(param)].describe(active);
  }
  [[nodiscard]] const SvmHyper& hyper(int param) const { return grid_[static_cast<std::size_t>(param)]; }

  bool evaluate(const Context& ctx, const FeatureMask& mask, std::vector<int>& correct) override {
    const auto n = static_cast<std::size_t>(ctx.n);
    const int dims = static_cast<int>(mask.count());
    const std::vector<double> rows = gather(ctx.scaled, n, mask);
    const std::size_t stride = static_cast<std::size_t>(dims) + 1;
    std::vector<svm_node> nodes(n * stride);
    for (std::size_t i = 0; i < n; ++i) {
      for (int j = 0; j < dims; ++j)
        nodes[i * stride + static_cast<std::size_t>(j)] = {
            j + 1, rows[i * static_cast<std::size_t>(dims) + static_cast<std::size_t>(j)]};
      nodes[i * stride + static_cast<std::size_t>(dims)] = {-1, 0.0};
    }
    const int tasks = static_cast<int>(active_.size()) * ctx.folds;
    std::vector<int> task_correct(static_cast<std::size_t>(tasks), 0);
    const bool done = base::parallel_for(
        tasks, ctx.threads,
        [&](int t, int /*worker*/) {
          const int fold = t % ctx.folds;
          const SvmHyper& h = grid_[static_cast<std::size_t>(active_[static_cast<std::size_t>(t / ctx.folds)])];
          std::vector<svm_node*> x;
          std::vector<double> y;
          for (std::size_t i = 0; i < n; ++i) {
            if (ctx.fold[i] == fold) continue;
            x.push_back(&nodes[i * stride]);
            y.push_back(ctx.train->labels[i]);
          }
          svm_problem problem{static_cast<int>(x.size()), y.data(), x.data()};
          // CV needs only the decision; libsvm's Platt fit would also call rand() (make_svm_parameter).
          const svm_parameter param = make_svm_parameter(h, dims, PlattFit::kNo);
          svm_model* model = svm_train(&problem, &param);
          int ok = 0;
          for (std::size_t i = 0; i < n; ++i) {
            if (ctx.fold[i] != fold || ctx.scored[i] == 0) continue;
            ok += static_cast<int>(svm_predict(model, &nodes[i * stride])) == ctx.train->labels[i] ? 1 : 0;
          }
          svm_free_and_destroy_model(&model);
          task_correct[static_cast<std::size_t>(t)] = ok;
          return true;
        },
        ctx.stop);
    if (!done) return false;
    std::vector<int> active_correct(active_.size(), 0);
    sum_over_folds(task_correct, ctx.folds, active_correct);
    std::fill(correct.begin(), correct.end(), -1);  // outside the focus: never the best
    for (std::size_t a = 0; a < active_.size(); ++a) correct[static_cast<std::size_t>(active_[a])] = active_correct[a];
    return true;
  }

 private:
  std::vector<SvmHyper> grid_;
  int radius_ = -1;
  int c_count_ = 0, gamma_count_ = 0;
  std::vector<int> active_;  // the grid points evaluate() scores, ascending (the tie-break order)
};

class KnnEvaluator final : public Evaluator {
 public:
  explicit KnnEvaluator(std::vector<int> k_values) : k_(std::move(k_values)) {}
  [[nodiscard]] int grid_size() const override { return static_cast<int>(k_.size()); }
  [[nodiscard]] std::string describe(int param, int /*active*/) const override {
    return "k=" + std::to_string(k_[static_cast<std::size_t>(param)]) + " (Euclidean, majority vote)";
  }
  [[nodiscard]] int k(int param) const { return k_[static_cast<std::size_t>(param)]; }

  bool evaluate(const Context& ctx, const FeatureMask& mask, std::vector<int>& correct) override {
    const auto n = static_cast<std::size_t>(ctx.n);
    const std::size_t d = mask.count();
    const std::vector<double> rows = gather(ctx.scaled, n, mask);
    const int k_max = largest(k_);
    std::vector<std::uint8_t> hit(n * k_.size(), 0);
    const bool done = base::parallel_for(
        ctx.n, ctx.threads,
        [&](int ii, int /*worker*/) {
          const auto i = static_cast<std::size_t>(ii);
          if (ctx.scored[i] == 0) return true;  // hit[] stays 0: a variant does not score
          std::vector<std::pair<double, int>> near;
          for (std::size_t j = 0; j < n; ++j) {
            if (ctx.fold[j] == ctx.fold[i]) continue;  // only the other folds are "training" for sample i
            double s = 0;
            for (std::size_t f = 0; f < d; ++f) {
              const double t = rows[i * d + f] - rows[j * d + f];
              s += t * t;
            }
            near.emplace_back(s, static_cast<int>(j));
          }
          const auto take = std::min(near.size(), static_cast<std::size_t>(k_max));
          std::partial_sort(near.begin(), near.begin() + static_cast<std::ptrdiff_t>(take), near.end());
          std::vector<int> votes(static_cast<std::size_t>(ctx.classes));
          for (std::size_t q = 0; q < k_.size(); ++q) {
            std::fill(votes.begin(), votes.end(), 0);
            const auto kk = std::min(take, static_cast<std::size_t>(k_[q]));
            for (std::size_t m = 0; m < kk; ++m)
              ++votes[static_cast<std::size_t>(ctx.train->labels[static_cast<std::size_t>(near[m].second)])];
            const int top = largest(votes);
            int winner = -1;
            for (std::size_t m = 0; m < kk && winner < 0; ++m) {
              const int c = ctx.train->labels[static_cast<std::size_t>(near[m].second)];
              if (votes[static_cast<std::size_t>(c)] == top) winner = c;
            }
            hit[i * k_.size() + q] = winner == ctx.train->labels[i] ? 1 : 0;
          }
          return true;
        },
        ctx.stop);
    if (!done) return false;
    std::fill(correct.begin(), correct.end(), 0);
    for (std::size_t i = 0; i < n; ++i) {
      for (std::size_t q = 0; q < k_.size(); ++q) correct[q] += hit[i * k_.size() + q];
    }
    return true;
  }

 private:
  std::vector<int> k_;
};

std::string layout_text(const std::vector<int>& hidden) {
  std::string s;
  for (int h : hidden) {
    if (!s.empty()) s += '-';
    s += std::to_string(h);
  }
  return s;
}

class MlpEvaluator final : public Evaluator {
 public:
  MlpEvaluator(std::vector<std::vector<int>> layouts, MlpParams base, std::uint64_t seed)
      : layouts_(std::move(layouts)), base_(std::move(base)), seed_(seed) {}
  [[nodiscard]] int grid_size() const override { return static_cast<int>(layouts_.size()); }
  [[nodiscard]] std::string describe(int param, int /*active*/) const override {
    std::string text = "hidden ";
    text += layout_text(layouts_[static_cast<std::size_t>(param)]);
    text += " tanh, softmax output, ";
    text += std::to_string(base_.epochs);
    text += " epochs";
    return text;
  }
  [[nodiscard]] MlpParams params(int param, std::uint64_t seed) const {
    MlpParams p = base_;
    p.hidden = layouts_[static_cast<std::size_t>(param)];
    p.seed = seed;
    return p;
  }

  bool evaluate(const Context& ctx, const FeatureMask& mask, std::vector<int>& correct) override {
    const auto n = static_cast<std::size_t>(ctx.n);
    const std::size_t d = mask.count();
    const std::vector<double> rows = gather(ctx.scaled, n, mask);
    const int tasks = grid_size() * ctx.folds;
    std::vector<int> task_correct(static_cast<std::size_t>(tasks), 0);
    const bool done = base::parallel_for(
        tasks, ctx.threads,
        [&](int t, int /*worker*/) {
          const int fold = t % ctx.folds, layout = t / ctx.folds;
          std::vector<double> x;
          std::vector<int> y;
          for (std::size_t i = 0; i < n; ++i) {
            if (ctx.fold[i] == fold) continue;
            x.insert(x.end(), rows.begin() + static_cast<std::ptrdiff_t>(i * d),
                     rows.begin() + static_cast<std::ptrdiff_t>((i + 1) * d));
            y.push_back(ctx.train->labels[i]);
          }
          Mlp net;
          net.train(x, y, static_cast<int>(d), ctx.classes,
                    params(layout, stream_seed(seed_, static_cast<std::uint64_t>(t))));
          int ok = 0;
          for (std::size_t i = 0; i < n; ++i) {
            if (ctx.fold[i] != fold || ctx.scored[i] == 0) continue;
            ok += net.predict(std::span<const double>(rows).subspan(i * d, d)) == ctx.train->labels[i] ? 1 : 0;
          }
          task_correct[static_cast<std::size_t>(t)] = ok;
          return true;
        },
        ctx.stop);
    if (!done) return false;
    sum_over_folds(task_correct, ctx.folds, correct);
    return true;
  }

 private:
  std::vector<std::vector<int>> layouts_;
  MlpParams base_;
  std::uint64_t seed_;
};

struct Score {
  double accuracy = 0.0;
  double cost = 0.0;  // percentage points of CV error + feature penalty (the annealing's energy)
  int param = 0;      // best grid point for this mask
};

struct AnnealingOutcome {
  bool scored = false;  // false: stopped before the initial mask was scored
  FeatureMask mask{};
  Score score{};
  ClassifierReport report;
};

struct StageInfo {
  Classifier classifier = Classifier::kSvm;
  int stage = 0, stages = 0;
  Clock::time_point t0;
};

// Thesis Fig. 2.2 with one candidate per temperature step (L_k = 1), as in 4.2 ("temperature decreasing in each
// iteration"); the neighbour of a mask flips one random feature.
AnnealingOutcome anneal(Evaluator& evaluator, const Context& ctx, const AnnealingParams& ap, int iterations,
                        const FeatureMask& initial, std::uint64_t seed, const StageInfo& stage,
                        const ProgressCallback& progress) {
  AnnealingOutcome out;
  out.report.classifier = stage.classifier;
  const Clock::time_point stage_start = Clock::now();
  std::unordered_map<FeatureMask, Score> memo;
  std::vector<int> correct(static_cast<std::size_t>(evaluator.grid_size()), 0);
  auto score = [&](const FeatureMask& mask, Score& s) {
    if (const auto it = memo.find(mask); it != memo.end()) {
      s = it->second;
      ++out.report.cache_hits;
      return true;
    }
    if (!evaluator.evaluate(ctx, mask, correct)) return false;
    ++out.report.evaluations;
    const auto best = std::max_element(correct.begin(), correct.end());  // first maximum: the simplest model
    s.param = static_cast<int>(best - correct.begin());
    s.accuracy = static_cast<double>(*best) / ctx.scored_n;
    s.cost = kPercent * (1.0 - s.accuracy) + ap.feature_penalty_pct * static_cast<double>(mask.count());
    memo.emplace(mask, s);
    return true;
  };

  Score current;
  if (!score(initial, current)) {
    out.report.stopped = true;
    return out;
  }
  out.scored = true;
  evaluator.focus(current.param);
  FeatureMask current_mask = initial;
  out.mask = initial;
  out.score = current;
  double temperature = ap.start_temperature;
  out.report.curve.push_back(
      {0, temperature, current.accuracy, current.accuracy, current.accuracy, static_cast<int>(initial.count()), true});
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> pick(0, kFeatureCount - 1);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int it = 1; it <= iterations; ++it) {
    if (stop_requested(ctx.stop)) {
      out.report.stopped = true;
      break;
    }
    FeatureMask candidate = current_mask;
    for (;;) {
      const auto f = static_cast<std::size_t>(pick(rng));
      if (candidate.test(f) && static_cast<int>(candidate.count()) <= ap.min_active) continue;
      candidate.flip(f);
      break;
    }
    Score s;
    if (!score(candidate, s)) {
      out.report.stopped = true;
      break;
    }
    const double delta = s.cost - current.cost;
    const double u = unit(rng);  // drawn every step so the random sequence does not depend on the branch
    const bool accept = delta <= 0.0 || u < std::exp(-delta / temperature);
    if (accept) {
      current_mask = candidate;
      current = s;
      if (s.cost < out.score.cost) {
        out.mask = candidate;
        out.score = s;
        evaluator.focus(s.param);
      }
    }
    out.report.curve.push_back({it, temperature, s.accuracy, current.accuracy, out.score.accuracy,
                                static_cast<int>(candidate.count()), accept});
    temperature *= ap.cooling_ratio;
    if (progress) {
      TrainingProgress p;
      p.classifier = stage.classifier;
      p.stage = stage.stage;
      p.stages = stage.stages;
      p.iteration = it;
      p.iterations = iterations;
      p.candidate_accuracy = s.accuracy;
      p.best_accuracy = out.score.accuracy;
      p.best_active = static_cast<int>(out.mask.count());
      p.elapsed_s = seconds_since(stage.t0);
      p.eta_s = seconds_since(stage_start) / it * (iterations - it);
      progress(p);
    }
  }
  out.report.seconds = seconds_since(stage_start);
  return out;
}

// Fisher score per feature on the scaled training data: between-class over within-class scatter. Only the
// starting point of the annealing ("generated using a heuristic", thesis 2.3.1).
FeatureMask fisher_mask(const Context& ctx, int count) {
  std::vector<std::pair<double, int>> ranked;
  const auto n = static_cast<std::size_t>(ctx.n);
  for (int f = 0; f < kFeatureCount; ++f) {
    std::vector<double> sum(static_cast<std::size_t>(ctx.classes), 0.0), sq(static_cast<std::size_t>(ctx.classes), 0.0);
    std::vector<int> cnt(static_cast<std::size_t>(ctx.classes), 0);
    double total = 0.0;
    for (std::size_t i = 0; i < n; ++i) {
      const double v = ctx.scaled[i * kFeatureCount + static_cast<std::size_t>(f)];
      const auto c = static_cast<std::size_t>(ctx.train->labels[i]);
      sum[c] += v;
      sq[c] += v * v;
      ++cnt[c];
      total += v;
    }
    const double mean = total / ctx.n;
    double between = 0.0, within = 0.0;
    for (std::size_t c = 0; c < sum.size(); ++c) {
      if (cnt[c] == 0) continue;
      const double mc = sum[c] / cnt[c];
      between += cnt[c] * (mc - mean) * (mc - mean);
      within += sq[c] - cnt[c] * mc * mc;
    }
    const double score = within > 1e-12 ? between / within : (between > 1e-12 ? 1e12 : 0.0);
    ranked.emplace_back(-score, f);  // ascending sort = best first, ties by index
  }
  std::sort(ranked.begin(), ranked.end());
  FeatureMask mask;
  for (int i = 0; i < count && i < kFeatureCount; ++i)
    mask.set(static_cast<std::size_t>(ranked[static_cast<std::size_t>(i)].second));
  return mask;
}

std::vector<std::string> mask_names(const FeatureMask& mask) {
  std::vector<std::string> names;
  for (int f = 0; f < kFeatureCount; ++f) {
    if (mask.test(static_cast<std::size_t>(f))) names.emplace_back(feature_name(f));
  }
  return names;
}

// Fills test accuracy and confusion from a predictor of test sample i.
template <class Predict>
void score_test(const Dataset& test, int classes, ClassifierReport& report, Predict predict) {
  report.confusion.assign(static_cast<std::size_t>(classes), std::vector<int>(static_cast<std::size_t>(classes), 0));
  int ok = 0;
  for (std::size_t i = 0; i < test.size(); ++i) {
    const int predicted = predict(i);
    const int truth = test.labels[i];
    if (predicted >= 0 && predicted < classes)
      ++report.confusion[static_cast<std::size_t>(truth)][static_cast<std::size_t>(predicted)];
    ok += predicted == truth ? 1 : 0;
  }
  report.test_accuracy = test.size() > 0 ? static_cast<double>(ok) / static_cast<double>(test.size())
                                         : std::numeric_limits<double>::quiet_NaN();
}

// The SVM's probabilities on the held-back scans: top-2 rate and the reliability of the top probability (expected
// calibration error: the scan-weighted gap between mean top probability and accuracy over equal-width bins).
void score_calibration(const Dataset& test, SvmModel& model, ClassifierReport& report) {
  std::vector<CalibrationBin> bins(kCalibrationBins);
  int top2 = 0;
  for (std::size_t i = 0; i < test.size(); ++i) {
    const auto probabilities = model.predict(test.features[i]);
    if (probabilities.empty()) continue;
    const bool hit = probabilities[0].class_index == test.labels[i];
    top2 += hit || (probabilities.size() > 1 && probabilities[1].class_index == test.labels[i]) ? 1 : 0;
    const double p1 = probabilities[0].probability;
    CalibrationBin& b =
        bins[static_cast<std::size_t>(std::clamp(static_cast<int>(p1 * kCalibrationBins), 0, kCalibrationBins - 1))];
    ++b.scans;
    b.mean_probability += p1;
    b.accuracy += hit ? 1.0 : 0.0;
  }
  const double n = static_cast<double>(test.size());
  report.test_top2 = test.size() > 0 ? top2 / n : std::numeric_limits<double>::quiet_NaN();
  report.test_ece = test.size() > 0 ? 0.0 : std::numeric_limits<double>::quiet_NaN();
  report.reliability.clear();
  for (int k = 0; k < kCalibrationBins; ++k) {
    CalibrationBin b = bins[static_cast<std::size_t>(k)];
    if (b.scans == 0) continue;
    b.lo = static_cast<double>(k) / kCalibrationBins;
    b.hi = static_cast<double>(k + 1) / kCalibrationBins;
    b.mean_probability /= b.scans;
    b.accuracy /= b.scans;
    report.test_ece += b.scans / n * std::abs(b.mean_probability - b.accuracy);
    report.reliability.push_back(b);
  }
}

// Scaled samples, group-aware folds and the scored (taught) samples of one training set.
Expected<Context> make_context(const Dataset& set, const Scaler& scaler, const TrainParams& params,
                               const std::atomic<bool>* stop) {
  auto folds = stratified_folds(set, params.folds, stream_seed(params.seed, 1));
  if (!folds) return folds.error();
  Context ctx;
  ctx.train = &set;
  ctx.n = static_cast<int>(set.size());
  ctx.classes = static_cast<int>(set.classes.size());
  ctx.folds = params.folds;
  const int cores = base::hardware_threads();
  ctx.threads = params.threads > 0 ? std::min(params.threads, cores) : cores;
  ctx.fold = std::move(*folds);
  ctx.scaled = scale_all(scaler, set.features);
  ctx.stop = stop;
  ctx.scored.resize(set.size());
  for (std::size_t i = 0; i < set.size(); ++i) {
    ctx.scored[i] = set.variant_of(i) == 0 ? 1 : 0;
    ctx.scored_n += ctx.scored[i];
  }
  return ctx;
}

Status validate_params(const TrainParams& p) {
  const auto& a = p.annealing;
  if (p.folds < 2) return make_error("training: folds must be at least 2");
  if (p.threads < 0) return make_error("training: threads must be >= 0 (0 = all cores)");
  if (p.search_grid_radius < -1) return make_error("training: search_grid_radius must be >= -1 (-1 = whole grid)");
  if (p.search_classes < 0 || p.search_classes == 1) {
    return make_error("training: search_classes must be 0 (all) or at least 2");
  }
  if (!(a.start_temperature > 0.0) || !(a.cooling_ratio > 0.0 && a.cooling_ratio <= 1.0) || a.iterations < 0) {
    return make_error("training: annealing needs start temperature > 0, cooling ratio in (0, 1], iterations >= 0");
  }
  if (a.min_active < 1 || a.min_active >= kFeatureCount || a.initial_active < a.min_active ||
      a.initial_active > kFeatureCount) {
    return make_error("training: need 1 <= min_active <= initial_active <= " + std::to_string(kFeatureCount));
  }
  if (a.initial_mask.any() && static_cast<int>(a.initial_mask.count()) < a.min_active) {
    return make_error("training: the initial mask has fewer features than min_active");
  }
  if (p.c_grid.empty() || p.gamma_factors.empty() || (p.kernel == KernelType::kPoly && p.poly_degrees.empty())) {
    return make_error("training: the C, gamma (and degree) grids must not be empty");
  }
  for (double c : p.c_grid) {
    if (!(c > 0.0) || !std::isfinite(c)) return make_error("training: every C must be > 0");
  }
  for (double g : p.gamma_factors) {
    if (!(g > 0.0) || !std::isfinite(g)) return make_error("training: every gamma factor must be > 0");
  }
  for (int d : p.poly_degrees) {
    if (d < 1 || d > kMaxDegree)
      return make_error("training: polynomial degrees must be in 1.." + std::to_string(kMaxDegree));
  }
  if (p.compare) {
    if (p.knn_k.empty() || p.mlp_layouts.empty())
      return make_error("training: --compare needs k values and MLP layouts");
    for (int k : p.knn_k) {
      if (k < 1) return make_error("training: kNN k must be >= 1");
    }
    for (const auto& layout : p.mlp_layouts) {
      if (layout.empty() || layout.size() > 2)
        return make_error("training: an MLP layout has one or two hidden layers");
      for (int h : layout) {
        if (h < 1) return make_error("training: an MLP layer needs at least one neuron");
      }
    }
    if (p.mlp.epochs < 1 || p.mlp.batch < 1 || !(p.mlp.learning_rate > 0.0) || p.mlp.weight_decay < 0.0) {
      return make_error("training: MLP epochs, batch and learning rate must be positive");
    }
  }
  return {};
}

}  // namespace

std::string_view to_string(Classifier classifier) {
  switch (classifier) {
    case Classifier::kSvm: return "svm";
    case Classifier::kKnn: return "knn";
    case Classifier::kMlp: return "mlp";
  }
  return "unknown";
}

void Dataset::push(const FeatureVector& f, int label, int group, int variant) {
  features.push_back(f);
  labels.push_back(label);
  groups.push_back(group);
  variants.push_back(variant);
}

Status validate_dataset(const Dataset& data) {
  if (data.classes.size() < 2) return make_error("dataset: at least two classes are needed");
  if (data.features.size() != data.labels.size()) return make_error("dataset: one label per feature vector is needed");
  if ((!data.groups.empty() && data.groups.size() != data.size()) ||
      (!data.variants.empty() && data.variants.size() != data.size())) {
    return make_error("dataset: groups and variants must be absent or one per sample");
  }
  const int k = static_cast<int>(data.classes.size());
  std::unordered_map<int, int> group_label;
  for (std::size_t i = 0; i < data.size(); ++i) {
    if (data.labels[i] < 0 || data.labels[i] >= k) {
      return make_error("dataset: sample " + std::to_string(i) + " has label " + std::to_string(data.labels[i]) +
                        ", not a class index");
    }
    for (float v : data.features[i]) {
      if (!std::isfinite(v)) return make_error("dataset: sample " + std::to_string(i) + " has a non-finite feature");
    }
    if (data.variant_of(i) < 0) return make_error("dataset: sample " + std::to_string(i) + " has a negative variant");
    const auto [it, fresh] = group_label.emplace(data.group_of(i), data.labels[i]);
    if (!fresh && it->second != data.labels[i]) {
      return make_error("dataset: group " + std::to_string(data.group_of(i)) + " mixes two classes");
    }
  }
  return {};
}

std::vector<int> search_class_subset(const Dataset& train, int limit) {
  const std::size_t classes = train.classes.size();
  if (limit <= 0 || classes <= static_cast<std::size_t>(limit)) return {};
  const Scaler scaler = Scaler::fit(train.features);
  std::vector<double> centroid(classes * kFeatureCount, 0.0);
  std::vector<int> count(classes, 0);
  for (std::size_t i = 0; i < train.size(); ++i) {
    if (train.variant_of(i) != 0) continue;
    const auto c = static_cast<std::size_t>(train.labels[i]);
    ++count[c];
    for (int f = 0; f < kFeatureCount; ++f)
      centroid[c * kFeatureCount + static_cast<std::size_t>(f)] +=
          scaler.scale(f, train.features[i][static_cast<std::size_t>(f)]);
  }
  for (std::size_t c = 0; c < classes; ++c) {
    for (int f = 0; f < kFeatureCount; ++f)
      centroid[c * kFeatureCount + static_cast<std::size_t>(f)] /= std::max(1, count[c]);
  }
  // (squared distance to the nearest other centroid, class, that neighbour), near twins first, ties by index.
  std::vector<std::tuple<double, std::size_t, std::size_t>> nearest;
  for (std::size_t a = 0; a < classes; ++a) {
    std::tuple<double, std::size_t, std::size_t> best{std::numeric_limits<double>::infinity(), a, a};
    for (std::size_t b = 0; b < classes; ++b) {
      if (b == a) continue;
      double d2 = 0.0;
      for (std::size_t f = 0; f < kFeatureCount; ++f) {
        const double t = centroid[a * kFeatureCount + f] - centroid[b * kFeatureCount + f];
        d2 += t * t;
      }
      if (d2 < std::get<0>(best)) best = {d2, a, b};
    }
    nearest.push_back(best);
  }
  std::sort(nearest.begin(), nearest.end());
  std::vector<std::uint8_t> taken(classes, 0);
  std::vector<int> subset;
  for (const auto& [d2, a, b] : nearest) {
    for (const std::size_t c : {a, b}) {
      if (taken[c] == 0 && subset.size() < static_cast<std::size_t>(limit)) {
        taken[c] = 1;
        subset.push_back(static_cast<int>(c));
      }
    }
  }
  std::sort(subset.begin(), subset.end());
  return subset;
}

std::string search_scope_text(const TrainingReport& report) {
  if (report.search_class_names.empty()) return {};
  return "annealing scored masks on " + std::to_string(report.search_class_names.size()) + " of " +
         std::to_string(report.class_names.size()) + " classes (the nearest centroids, svm.search_classes)" +
         (report.search_grid_radius >= 0 ? ", after the first mask on the C x gamma grid points within " +
                                               std::to_string(report.search_grid_radius) + " step(s) of the best"
                                         : std::string()) +
         "; the final SVM learnt from all";
}

Expected<DatasetSplit> split_per_class(const Dataset& all, int train_per_class, std::uint64_t seed) {
  if (Status s = validate_dataset(all); !s) return s.error();
  if (train_per_class < 1) return make_error("split: train_per_class must be >= 1");
  DatasetSplit split;
  split.train.classes = split.test.classes = all.classes;
  std::mt19937_64 rng(seed);
  std::unordered_map<int, std::vector<std::size_t>> variants_of;  // group -> its synthetic variants, in order
  for (std::size_t i = 0; i < all.size(); ++i) {
    if (all.variant_of(i) > 0) variants_of[all.group_of(i)].push_back(i);
  }
  for (int c = 0; c < static_cast<int>(all.classes.size()); ++c) {
    std::vector<std::size_t> members;  // the taught scans of the class
    for (std::size_t i = 0; i < all.size(); ++i) {
      if (all.labels[i] == c && all.variant_of(i) == 0) members.push_back(i);
    }
    if (static_cast<int>(members.size()) <= train_per_class) {
      return make_error("split: class '" + all.classes[static_cast<std::size_t>(c)].name + "' has " +
                        std::to_string(members.size()) + " scans; " + std::to_string(train_per_class) +
                        " for training plus at least one for testing are needed (svm.train_per_class)");
    }
    std::shuffle(members.begin(), members.end(), rng);
    for (std::size_t m = 0; m < members.size(); ++m) {
      const std::size_t i = members[m];
      const bool train = static_cast<int>(m) < train_per_class;
      Dataset& to = train ? split.train : split.test;
      to.push(all.features[i], c, all.group_of(i), 0);
      if (!train) continue;
      if (const auto v = variants_of.find(all.group_of(i)); v != variants_of.end()) {
        for (std::size_t j : v->second) to.push(all.features[j], c, all.group_of(j), all.variant_of(j));
      }
    }
  }
  return split;
}

Expected<std::vector<int>> stratified_folds(const Dataset& data, int folds, std::uint64_t seed) {
  if (folds < 2) return make_error("k-fold: at least 2 folds are needed");
  std::vector<int> fold(data.size(), -1);
  std::mt19937_64 rng(seed);
  std::unordered_map<int, int> group_fold;
  for (int c = 0; c < static_cast<int>(data.classes.size()); ++c) {
    std::vector<int> groups;  // of the class, in order of first appearance
    for (std::size_t i = 0; i < data.size(); ++i) {
      if (data.labels[i] == c && group_fold.emplace(data.group_of(i), -1).second) groups.push_back(data.group_of(i));
    }
    if (static_cast<int>(groups.size()) < folds) {
      return make_error("k-fold: class '" + data.classes[static_cast<std::size_t>(c)].name + "' has " +
                        std::to_string(groups.size()) + " training sample(s); " + std::to_string(folds) +
                        "-fold cross-validation needs at least " + std::to_string(folds) + " per class");
    }
    std::shuffle(groups.begin(), groups.end(), rng);
    for (std::size_t m = 0; m < groups.size(); ++m)
      group_fold[groups[m]] = static_cast<int>(m % static_cast<std::size_t>(folds));
  }
  for (std::size_t i = 0; i < data.size(); ++i) fold[i] = group_fold[data.group_of(i)];
  return fold;
}

namespace {

// The two halves of a split are valid and name the same classes.
Status validate_split(const DatasetSplit& split) {
  if (Status s = validate_dataset(split.train); !s) return make_error("training split: " + s.error().message);
  if (!split.test.labels.empty()) {
    if (Status s = validate_dataset(split.test); !s) return make_error("test split: " + s.error().message);
  }
  if (split.test.classes.size() != split.train.classes.size()) {
    return make_error("training: the test split has other classes than the training split");
  }
  for (std::size_t c = 0; c < split.train.classes.size(); ++c) {
    if (split.test.classes[c].name != split.train.classes[c].name) {
      return make_error("training: the test split has other classes than the training split");
    }
  }
  return {};
}

// The annealing's set: the taught scans and their first search_variants variants (all of them when negative).
Dataset annealing_set(const Dataset& train, int search_variants) {
  Dataset search;
  search.classes = train.classes;
  for (std::size_t i = 0; i < train.size(); ++i) {
    const int v = train.variant_of(i);
    if (search_variants < 0 || v <= search_variants)
      search.push(train.features[i], train.labels[i], train.group_of(i), v);
  }
  return search;
}

// The samples of the classes in `keep` (ascending class indices), relabelled 0..keep.size()-1 in that order.
Dataset restrict_classes(const Dataset& set, const std::vector<int>& keep) {
  Dataset out;
  std::vector<int> index_of(set.classes.size(), -1);
  for (std::size_t k = 0; k < keep.size(); ++k) {
    index_of[static_cast<std::size_t>(keep[k])] = static_cast<int>(k);
    out.classes.push_back(set.classes[static_cast<std::size_t>(keep[k])]);
  }
  for (std::size_t i = 0; i < set.size(); ++i) {
    const int label = index_of[static_cast<std::size_t>(set.labels[i])];
    if (label >= 0) out.push(set.features[i], label, set.group_of(i), set.variant_of(i));
  }
  return out;
}

// What the classifier stages of one training share.
struct TrainingRun {
  const DatasetSplit& split;
  const TrainParams& params;
  const Dataset& search;  // the annealing's set (kNN and MLP: all classes)
  const Context& ctx;     // the search set scaled, with its folds
  // The SVM annealing's set: `search` itself, or its search_classes subset (issue 11) in svm_search.
  const std::vector<int>& subset;  // class indices of the subset; empty: all classes
  const Context& svm_ctx;
  const Scaler& scaler;
  const std::vector<double>& test_scaled;
  FeatureMask initial;  // where every annealing starts
  int classes = 0;
  int stages = 1;  // annealing runs in all (progress)
  Clock::time_point t0;
  const ProgressCallback& progress;
  const std::atomic<bool>* stop = nullptr;
};

void report_samples(const TrainingRun& run, TrainingReport& report) {
  const Dataset& train = run.split.train;
  for (const ClassInfo& c : train.classes) report.class_names.push_back(c.name);
  for (std::size_t i = 0; i < train.size(); ++i) {
    if (train.variant_of(i) == 0) ++report.train_samples;
  }
  report.synthetic_samples = static_cast<int>(train.size()) - report.train_samples;
  report.search_samples = run.svm_ctx.n;
  for (const int c : run.subset) report.search_class_names.push_back(train.classes[static_cast<std::size_t>(c)].name);
  report.search_grid_radius = run.subset.empty() ? -1 : run.params.search_grid_radius;
  report.test_samples = static_cast<int>(run.split.test.size());
  report.folds = run.params.folds;
  report.threads = run.ctx.threads;
}

// SVM: annealing, then the probability model on the whole training split (thesis 2.6.1).
Status train_svm(const TrainingRun& run, TrainingResult& result) {
  const DatasetSplit& split = run.split;
  const TrainParams& params = run.params;
  TrainingReport& report = result.report;
  SvmEvaluator svm_eval(params, run.subset.empty() ? -1 : params.search_grid_radius);
  AnnealingOutcome svm = anneal(svm_eval, run.svm_ctx, params.annealing, params.annealing.iterations, run.initial,
                                stream_seed(params.seed, 2), {Classifier::kSvm, 0, run.stages, run.t0}, run.progress);
  if (!svm.scored) return make_error("training stopped before the first feature set was scored: no model");
  // The chosen features' C and gamma again on every training sample (the final model learns from all of them):
  // the grid's best on the search set need not be the best on the larger one. With a class subset, on the
  // search set of every class within the grid's focus: C and gamma picked on near twins alone cost 6.5 points
  // of test accuracy at 100 noisy classes (bench_svm_scale --noise 0.4), and every class with every variant
  // would cost what the subset saved (~3000 s at 300 classes with 8 variants per scan).
  const bool regrid = run.subset.empty() ? split.train.size() > run.search.size() : true;
  if (regrid && !stop_requested(run.stop)) {
    auto full =
        run.subset.empty() ? make_context(split.train, run.scaler, params, run.stop) : Expected<Context>{Context{}};
    if (!full) return full.error();
    const Context& on = run.subset.empty() ? *full : run.ctx;
    std::vector<int> correct(static_cast<std::size_t>(svm_eval.grid_size()), 0);
    if (svm_eval.evaluate(on, svm.mask, correct)) {
      const auto best = std::max_element(correct.begin(), correct.end());
      svm.score.param = static_cast<int>(best - correct.begin());
      svm.score.accuracy = static_cast<double>(*best) / on.scored_n;
    }
  }
  report.svm_hyper = svm_eval.hyper(svm.score.param);
  auto model = SvmModel::train(split.train.features, split.train.labels, split.train.classes, svm.mask, run.scaler,
                               report.svm_hyper, params.seed);
  if (!model) return model.error();
  result.model = std::move(*model);
  report.svm = std::move(svm.report);
  report.svm.parameters = svm_eval.describe(svm.score.param, static_cast<int>(svm.mask.count()));
  report.svm.cv_accuracy = svm.score.accuracy;
  report.svm.mask = svm.mask;
  report.svm.features = mask_names(svm.mask);
  score_test(split.test, run.classes, report.svm, [&](std::size_t i) {
    const auto probabilities = result.model.predict(split.test.features[i]);
    return probabilities.empty() ? -1 : probabilities.front().class_index;
  });
  score_calibration(split.test, result.model, report.svm);
  report.stopped = report.svm.stopped;
  return {};
}

// Comparison classifier (thesis 4.2): kNN with its own annealing run.
void compare_knn(const TrainingRun& run, TrainingReport& report) {
  const DatasetSplit& split = run.split;
  const TrainParams& params = run.params;
  KnnEvaluator knn_eval(params.knn_k);
  const int knn_iterations = params.knn_iterations >= 0 ? params.knn_iterations : params.annealing.iterations;
  AnnealingOutcome knn = anneal(knn_eval, run.ctx, params.annealing, knn_iterations, run.initial,
                                stream_seed(params.seed, 3), {Classifier::kKnn, 1, run.stages, run.t0}, run.progress);
  if (!knn.scored) return;
  const int k = knn_eval.k(knn.score.param);
  const std::size_t d = knn.mask.count();
  const std::vector<double> train_rows = gather(run.ctx.scaled, run.search.size(), knn.mask);
  const std::vector<double> test_rows = gather(run.test_scaled, split.test.size(), knn.mask);
  ClassifierReport r = std::move(knn.report);
  r.parameters = knn_eval.describe(knn.score.param, static_cast<int>(d));
  r.cv_accuracy = knn.score.accuracy;
  r.mask = knn.mask;
  r.features = mask_names(knn.mask);
  score_test(split.test, run.classes, r, [&](std::size_t i) {
    return knn_classify(train_rows, run.search.labels, static_cast<int>(d), run.classes, k,
                        std::span<const double>(test_rows).subspan(i * d, d));
  });
  report.stopped = report.stopped || r.stopped;
  report.knn = std::move(r);
}

// Comparison classifier (thesis 4.2): the multilayer perceptron with its own annealing run.
void compare_mlp(const TrainingRun& run, TrainingReport& report) {
  const DatasetSplit& split = run.split;
  const TrainParams& params = run.params;
  MlpEvaluator mlp_eval(params.mlp_layouts, params.mlp, stream_seed(params.seed, 4));
  AnnealingOutcome mlp = anneal(mlp_eval, run.ctx, params.annealing, params.mlp_iterations, run.initial,
                                stream_seed(params.seed, 5), {Classifier::kMlp, 2, run.stages, run.t0}, run.progress);
  if (!mlp.scored) return;
  const std::size_t d = mlp.mask.count();
  const std::vector<double> train_rows = gather(run.ctx.scaled, run.search.size(), mlp.mask);
  const std::vector<double> test_rows = gather(run.test_scaled, split.test.size(), mlp.mask);
  Mlp net;
  net.train(train_rows, run.search.labels, static_cast<int>(d), run.classes,
            mlp_eval.params(mlp.score.param, stream_seed(params.seed, 6)));
  ClassifierReport r = std::move(mlp.report);
  r.parameters = mlp_eval.describe(mlp.score.param, static_cast<int>(d));
  r.cv_accuracy = mlp.score.accuracy;
  r.mask = mlp.mask;
  r.features = mask_names(mlp.mask);
  score_test(split.test, run.classes, r,
             [&](std::size_t i) { return net.predict(std::span<const double>(test_rows).subspan(i * d, d)); });
  report.stopped = report.stopped || r.stopped;
  report.mlp = std::move(r);
}

}  // namespace

Expected<TrainingResult> train_recogniser(const DatasetSplit& split, const TrainParams& params,
                                          const ProgressCallback& progress, const std::atomic<bool>* stop) {
  const Clock::time_point t0 = Clock::now();
  if (Status s = validate_params(params); !s) return s.error();
  if (Status s = validate_split(split); !s) return s.error();
  const Dataset search = annealing_set(split.train, params.search_variants);
  silence_libsvm();
  const Scaler scaler = Scaler::fit(split.train.features);
  auto searched = make_context(search, scaler, params, stop);
  if (!searched) return searched.error();
  const Context& ctx = *searched;
  const std::vector<double> test_scaled = scale_all(scaler, split.test.features);
  const FeatureMask initial = params.annealing.initial_mask.any() ? params.annealing.initial_mask
                                                                  : fisher_mask(ctx, params.annealing.initial_active);
  const std::vector<int> subset = search_class_subset(split.train, params.search_classes);
  const Dataset svm_search = subset.empty() ? Dataset{} : restrict_classes(search, subset);
  auto svm_searched = subset.empty() ? Expected<Context>{Context{}} : make_context(svm_search, scaler, params, stop);
  if (!svm_searched) return svm_searched.error();
  const TrainingRun run{split,
                        params,
                        search,
                        ctx,
                        subset,
                        subset.empty() ? ctx : *svm_searched,
                        scaler,
                        test_scaled,
                        initial,
                        static_cast<int>(split.train.classes.size()),
                        params.compare ? 3 : 1,
                        t0,
                        progress,
                        stop};

  TrainingResult result;
  report_samples(run, result.report);
  if (Status s = train_svm(run, result); !s) return s.error();
  if (params.compare && !result.report.stopped) compare_knn(run, result.report);
  if (params.compare && !result.report.stopped) compare_mlp(run, result.report);
  result.report.seconds = seconds_since(t0);
  return result;
}

// ---- kNN ----------------------------------------------------------------------------------------------------------

int knn_classify(std::span<const double> rows, std::span<const int> labels, int dims, int classes, int k,
                 std::span<const double> x) {
  if (classes <= 0 || labels.empty() || dims <= 0) return -1;
  const auto d = static_cast<std::size_t>(dims);
  std::vector<std::pair<double, int>> near;
  near.reserve(labels.size());
  for (std::size_t j = 0; j < labels.size(); ++j) {
    double s = 0;
    for (std::size_t f = 0; f < d; ++f) {
      const double t = x[f] - rows[j * d + f];
      s += t * t;
    }
    near.emplace_back(s, static_cast<int>(j));
  }
  const auto take = std::min(near.size(), static_cast<std::size_t>(std::max(k, 1)));
  std::partial_sort(near.begin(), near.begin() + static_cast<std::ptrdiff_t>(take), near.end());
  std::vector<int> votes(static_cast<std::size_t>(classes), 0);
  for (std::size_t m = 0; m < take; ++m)
    ++votes[static_cast<std::size_t>(labels[static_cast<std::size_t>(near[m].second)])];
  const int top = largest(votes);
  for (std::size_t m = 0; m < take; ++m) {
    const int c = labels[static_cast<std::size_t>(near[m].second)];
    if (votes[static_cast<std::size_t>(c)] == top) return c;
  }
  return -1;
}

// ---- MLP ----------------------------------------------------------------------------------------------------------

// train()'s working set, allocated once per training: activations per layer (index 0 = input), deltas, gradients and
// Adam's moments.
struct Mlp::TrainingBuffers {
  std::vector<std::vector<double>> act, delta, gw, gb, mw, vw, mb, vb;

  TrainingBuffers(const std::vector<Layer>& layers, int dims)
      : act(layers.size() + 1),
        delta(layers.size()),
        gw(layers.size()),
        gb(layers.size()),
        mw(layers.size()),
        vw(layers.size()),
        mb(layers.size()),
        vb(layers.size()) {
    act[0].resize(static_cast<std::size_t>(dims));
    for (std::size_t l = 0; l < layers.size(); ++l) {
      act[l + 1].resize(static_cast<std::size_t>(layers[l].out));
      delta[l].resize(static_cast<std::size_t>(layers[l].out));
      gw[l].resize(layers[l].w.size());
      gb[l].resize(layers[l].b.size());
      mw[l].assign(layers[l].w.size(), 0.0);
      vw[l].assign(layers[l].w.size(), 0.0);
      mb[l].assign(layers[l].b.size(), 0.0);
      vb[l].assign(layers[l].b.size(), 0.0);
    }
  }
};

void Mlp::train(std::span<const double> rows, std::span<const int> labels, int dims, int classes,
                const MlpParams& params) {
  layers_.clear();
  std::vector<int> sizes{dims};
  sizes.insert(sizes.end(), params.hidden.begin(), params.hidden.end());
  sizes.push_back(classes);
  std::mt19937_64 rng(params.seed);
  for (std::size_t i = 0; i + 1 < sizes.size(); ++i) {
    Layer layer;
    layer.in = sizes[i];
    layer.out = sizes[i + 1];
    // Thesis 2.4.2.3: small random weights (Glorot range), zero biases.
    const double a = std::sqrt(6.0 / (layer.in + layer.out));
    std::uniform_real_distribution<double> init(-a, a);
    layer.w.resize(static_cast<std::size_t>(layer.in) * static_cast<std::size_t>(layer.out));
    for (double& w : layer.w) w = init(rng);
    layer.b.assign(static_cast<std::size_t>(layer.out), 0.0);
    layers_.push_back(std::move(layer));
  }
  const std::size_t depth = layers_.size(), n = labels.size();
  if (n == 0) return;
  TrainingBuffers buffers(layers_, dims);
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  const auto d = static_cast<std::size_t>(dims);
  int step = 0;
  for (int epoch = 0; epoch < params.epochs; ++epoch) {
    std::shuffle(order.begin(), order.end(), rng);
    for (std::size_t start = 0; start < n; start += static_cast<std::size_t>(params.batch)) {
      const std::size_t end = std::min(n, start + static_cast<std::size_t>(params.batch));
      for (std::size_t l = 0; l < depth; ++l) {
        std::fill(buffers.gw[l].begin(), buffers.gw[l].end(), 0.0);
        std::fill(buffers.gb[l].begin(), buffers.gb[l].end(), 0.0);
      }
      for (std::size_t s = start; s < end; ++s) {
        const std::size_t i = order[s];
        std::copy_n(rows.begin() + static_cast<std::ptrdiff_t>(i * d), d, buffers.act[0].begin());
        forward(buffers);
        backward(buffers, labels[i]);
      }
      ++step;
      adam_step(buffers, end - start, step, params);
    }
  }
}

void Mlp::forward(TrainingBuffers& b) const {
  const std::size_t depth = layers_.size();
  // Eq. 2.18-2.21, tanh inside, softmax at the output (thesis 4.2.2).
  for (std::size_t l = 0; l < depth; ++l) {
    const Layer& layer = layers_[l];
    for (int o = 0; o < layer.out; ++o) {
      double z = layer.b[static_cast<std::size_t>(o)];
      const double* w = &layer.w[static_cast<std::size_t>(o) * static_cast<std::size_t>(layer.in)];
      for (int q = 0; q < layer.in; ++q) z += w[q] * b.act[l][static_cast<std::size_t>(q)];
      b.act[l + 1][static_cast<std::size_t>(o)] = l + 1 < depth ? std::tanh(z) : z;
    }
  }
  std::vector<double>& out = b.act[depth];
  const double top = *std::max_element(out.begin(), out.end());
  double sum = 0.0;
  for (double& v : out) sum += (v = std::exp(v - top));
  for (double& v : out) v /= sum;
}

void Mlp::backward(TrainingBuffers& b, int label) const {
  const std::size_t depth = layers_.size();
  // Softmax + cross-entropy gives p - onehot at the output.
  const std::vector<double>& out = b.act[depth];
  for (std::size_t o = 0; o < out.size(); ++o)
    b.delta[depth - 1][o] = out[o] - (static_cast<int>(o) == label ? 1.0 : 0.0);
  for (std::size_t l = depth; l-- > 0;) {
    const Layer& layer = layers_[l];
    for (int o = 0; o < layer.out; ++o) {
      const double g = b.delta[l][static_cast<std::size_t>(o)];
      b.gb[l][static_cast<std::size_t>(o)] += g;
      double* gwo = &b.gw[l][static_cast<std::size_t>(o) * static_cast<std::size_t>(layer.in)];
      for (int q = 0; q < layer.in; ++q) gwo[q] += g * b.act[l][static_cast<std::size_t>(q)];
    }
    if (l == 0) break;
    for (int q = 0; q < layer.in; ++q) {
      double back = 0.0;
      for (int o = 0; o < layer.out; ++o)
        back +=
            layer.w[static_cast<std::size_t>(o) * static_cast<std::size_t>(layer.in) + static_cast<std::size_t>(q)] *
            b.delta[l][static_cast<std::size_t>(o)];
      const double a = b.act[l][static_cast<std::size_t>(q)];
      b.delta[l - 1][static_cast<std::size_t>(q)] = back * (1.0 - a * a);  // tanh' = 1 - tanh^2
    }
  }
}

void Mlp::adam_step(TrainingBuffers& b, std::size_t batch_size, int step, const MlpParams& params) {
  constexpr double kBeta1 = 0.9, kBeta2 = 0.999, kAdamEps = 1e-8;
  const double scale = 1.0 / static_cast<double>(batch_size);
  const double c1 = 1.0 - std::pow(kBeta1, step), c2 = 1.0 - std::pow(kBeta2, step);
  auto adam = [&](std::vector<double>& w, const std::vector<double>& g, std::vector<double>& m, std::vector<double>& v,
                  double decay) {
    for (std::size_t j = 0; j < w.size(); ++j) {
      const double grad = g[j] * scale + decay * w[j];
      m[j] = kBeta1 * m[j] + (1.0 - kBeta1) * grad;
      v[j] = kBeta2 * v[j] + (1.0 - kBeta2) * grad * grad;
      w[j] -= params.learning_rate * (m[j] / c1) / (std::sqrt(v[j] / c2) + kAdamEps);
    }
  };
  for (std::size_t l = 0; l < layers_.size(); ++l) {
    adam(layers_[l].w, b.gw[l], b.mw[l], b.vw[l], params.weight_decay);
    adam(layers_[l].b, b.gb[l], b.mb[l], b.vb[l], 0.0);
  }
}

void Mlp::probabilities(std::span<const double> x, std::span<double> out) const {
  std::vector<double> a(x.begin(), x.end()), next;
  for (std::size_t l = 0; l < layers_.size(); ++l) {
    const Layer& layer = layers_[l];
    next.assign(static_cast<std::size_t>(layer.out), 0.0);
    for (int o = 0; o < layer.out; ++o) {
      double z = layer.b[static_cast<std::size_t>(o)];
      for (int q = 0; q < layer.in; ++q)
        z += layer.w[static_cast<std::size_t>(o) * static_cast<std::size_t>(layer.in) + static_cast<std::size_t>(q)] *
             a[static_cast<std::size_t>(q)];
      next[static_cast<std::size_t>(o)] = l + 1 < layers_.size() ? std::tanh(z) : z;
    }
    a.swap(next);
  }
  const double top = a.empty() ? 0.0 : *std::max_element(a.begin(), a.end());
  double sum = 0.0;
  for (double& v : a) sum += (v = std::exp(v - top));
  for (std::size_t o = 0; o < out.size() && o < a.size(); ++o) out[o] = a[o] / sum;
}

int Mlp::predict(std::span<const double> x) const {
  std::vector<double> p(static_cast<std::size_t>(classes()));
  probabilities(x, p);
  return p.empty() ? -1 : static_cast<int>(std::max_element(p.begin(), p.end()) - p.begin());
}

}  // namespace cellsight::algo
