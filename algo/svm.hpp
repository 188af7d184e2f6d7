// Probability SVM over the selected features (thesis 2.4.3, 5.2, 6.4.2): libsvm C-SVC training, own
// allocation-free prediction, and a self-checking binary form for the model database.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "algo/features.hpp"
#include "algo/result.hpp"

struct svm_parameter;  // libsvm/svm.h: only the files that call libsvm include it

namespace cellsight::algo {

enum class KernelType : std::uint8_t {
  kRbf = 0,   // exp(-gamma |x1 - x2|^2), thesis eq. 6.2
  kPoly = 1,  // (gamma x1.x2 + coef0)^degree, thesis eq. 6.4 (coef0 = 0 there)
};
[[nodiscard]] std::string_view to_string(KernelType kernel);

struct SvmHyper {
  KernelType kernel = KernelType::kRbf;
  double c = 1.0;             // soft-margin cost (eq. 2.37)
  double gamma_factor = 1.0;  // i of thesis eq. 6.3: gamma = i / number of active features
  int degree = 3;             // polynomial kernel only
  double coef0 = 0.0;         // polynomial kernel only
  [[nodiscard]] double gamma(int active_features) const { return gamma_factor / active_features; }
  [[nodiscard]] std::string describe(int active_features) const;  // "rbf C=4 gamma=0.0667 (i=1)"
};

// Whether libsvm fits Platt's sigmoids after training (svm_parameter::probability).
enum class PlattFit : bool { kNo = false, kYes = true };

// The libsvm parameters of every C-SVC cellsight trains, so the cross-validation scores the very machine that is
// shipped: C-SVC, the kernel of `hyper` (gamma from `active_features`), eps 1e-3, shrinking, a 100 MB kernel cache
// (speed only, never the result; libsvm allocates it as the columns are used). They differ on purpose only in
// `platt`: the shipped model needs probabilities (kYes); a cross-validation model is scored on its decision alone
// (kNo), and Platt's fit would run an inner 5-fold CV per model and shuffle with the process-wide rand() from
// several threads at once.
[[nodiscard]] svm_parameter make_svm_parameter(const SvmHyper& hyper, int active_features, PlattFit platt);

struct ClassInfo {
  std::string name;
  int id = 0;  // the part's PLC id (robot program)
};

// Per-feature map onto [-1, 1] fitted on the training split (libsvm's svm-scale practice) and stored with the
// model. Heavy-tailed features (Hu I3..I8, kFeatureTable) are first compressed with asinh(v / s), s = median |v|
// of the training samples, so a few large values do not squash every other sample onto one point. Values outside
// the training range extrapolate linearly, clipped at +-kClip so a wild scan cannot blow up a polynomial kernel.
class Scaler {
 public:
  static constexpr double kClip = 3.0;
  struct Range {
    double compress = 0.0;  // asinh scale s; 0 = no compression
    double lo = 0.0, hi = 0.0;
  };

  Scaler() = default;
  // Fits all 74 features; an empty sample set gives the identity-like zero map.
  [[nodiscard]] static Scaler fit(std::span<const FeatureVector> samples);
  [[nodiscard]] double scale(int feature, double value) const;
  // The active features of `mask`, in table order, scaled; out.size() must be mask.count().
  void apply(const FeatureVector& features, const FeatureMask& mask, std::span<double> out) const;
  [[nodiscard]] const std::array<Range, kFeatureCount>& ranges() const { return ranges_; }
  [[nodiscard]] static Scaler from_ranges(const std::array<Range, kFeatureCount>& ranges);

 private:
  std::array<Range, kFeatureCount> ranges_{};
};

struct ClassProbability {
  int class_index = -1;  // into SvmModel::classes()
  double probability = 0.0;
};

// libsvm prints its training progress to stdout; this routes it nowhere (once per process, thread-safe).
void silence_libsvm();

// A trained probability C-SVC. libsvm trains it; prediction is our port of libsvm's svm_predict_probability
// (decision values, Platt sigmoids, Wu-Lin-Weng pairwise coupling) on dense arrays, because libsvm 3.24's own
// function mallocs 2k + 7 blocks per call (dec_values, pairwise_prob[k], kvalue, start, vote, Q[k], Qp) and walks
// sparse nodes. The test checks the port against libsvm's function.
class SvmModel {
 public:
  static constexpr std::uint32_t kFormatVersion = 1;

  SvmModel() = default;

  // Trains on the rows of `features` with labels in [0, classes.size()); every class needs two samples. libsvm's
  // probability fit shuffles with rand(): it is seeded with `seed` (a process-wide side effect; call from one
  // thread at a time).
  [[nodiscard]] static Expected<SvmModel> train(std::span<const FeatureVector> features, std::span<const int> labels,
                                                std::vector<ClassInfo> classes, const FeatureMask& mask,
                                                const Scaler& scaler, const SvmHyper& hyper, std::uint64_t seed);

  // Probabilities of every class for one scan, best first (they sum to 1). Uses the model's scratch: it never
  // allocates and is not thread-safe (one model copy per thread). Empty for an empty model.
  [[nodiscard]] std::span<const ClassProbability> predict(const FeatureVector& features);

  // The model as bytes (for the model database, which writes files atomically): header, feature version and the
  // 74 names, mask, scaler, classes, kernel, support vectors and coefficients, CRC-32.
  [[nodiscard]] std::string serialize() const;
  // Refuses anything it cannot fully verify (magic, versions, feature names, sizes, values, checksum).
  [[nodiscard]] static Expected<SvmModel> deserialize(std::string_view blob);

  [[nodiscard]] bool empty() const { return classes_.empty(); }
  [[nodiscard]] const std::vector<ClassInfo>& classes() const { return classes_; }
  [[nodiscard]] const FeatureMask& mask() const { return mask_; }
  [[nodiscard]] const Scaler& scaler() const { return scaler_; }
  [[nodiscard]] const SvmHyper& hyper() const { return hyper_; }
  [[nodiscard]] int active_features() const { return dims_; }
  [[nodiscard]] int support_vectors() const { return sv_count_; }

 private:
  void allocate_scratch();
  [[nodiscard]] double kernel(const double* a, const double* b) const;

  std::vector<ClassInfo> classes_;
  FeatureMask mask_{};
  Scaler scaler_{};
  SvmHyper hyper_{};
  int dims_ = 0;      // active features
  int sv_count_ = 0;  // l
  // libsvm's layout: classes in libsvm's slot order (slot_class_[s] = our class index), support vectors grouped
  // by slot, sv_coef[(k-1) x l], rho/probA/probB per pair (i < j in slot order).
  std::vector<int> slot_class_, slot_sv_count_;
  std::vector<double> sv_, coef_, rho_, prob_a_, prob_b_;
  // Prediction scratch, sized when the model is built.
  std::vector<double> x_, kvalue_, decision_, pairwise_, q_, qp_, p_;
  std::vector<int> start_;
  std::vector<ClassProbability> out_;
};

}  // namespace cellsight::algo
