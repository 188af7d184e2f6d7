// Probability SVM: libsvm training, dense allocation-free prediction (a port of libsvm 3.24's), serialization.
#include "algo/svm.hpp"

#include <libsvm/svm.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <type_traits>

#include "base/crc32.hpp"

namespace cellsight::algo {

static_assert(std::endian::native == std::endian::little, "the model byte format is written in host order");

namespace {

constexpr std::array<char, 8> kMagic = {'C', 'S', 'S', 'V', 'M', '\x1a', '\r', '\n'};
constexpr double kMinProbability = 1e-7;  // libsvm's clamp of the pairwise probabilities
constexpr int kMaxDegree = 10;
constexpr int kMaxClasses = 4096;

void discard_libsvm_output(const char* /*text*/) {}

class ByteWriter {
 public:
  template <class T>
  void put(T value) {
    static_assert(std::is_trivially_copyable_v<T>);
    char raw[sizeof(T)];
    std::memcpy(raw, &value, sizeof(T));
    out_.append(raw, sizeof(T));
  }
  void put_string(std::string_view s) {
    put(static_cast<std::uint16_t>(s.size()));
    out_.append(s);
  }
  void put_doubles(const std::vector<double>& v) {
    for (double d : v) put(d);
  }
  std::string& bytes() { return out_; }

 private:
  std::string out_;
};

// Bounds-checked reader: every get fails (and stays failed) instead of reading past the end.
class ByteReader {
 public:
  explicit ByteReader(std::string_view bytes) : bytes_(bytes) {}
  template <class T>
  bool get(T& value) {
    if (!ok_ || bytes_.size() - pos_ < sizeof(T)) return ok_ = false;
    std::memcpy(&value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return true;
  }
  bool get_string(std::string& s) {
    std::uint16_t n = 0;
    if (!get(n) || bytes_.size() - pos_ < n) return ok_ = false;
    s.assign(bytes_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  // Reads count finite doubles; refuses a count the remaining bytes cannot hold before allocating.
  bool get_doubles(std::size_t count, std::vector<double>& v) {
    if (!ok_ || (bytes_.size() - pos_) / sizeof(double) < count) return ok_ = false;
    v.resize(count);
    for (double& d : v) {
      get(d);
      if (!std::isfinite(d)) return ok_ = false;
    }
    return ok_;
  }
  [[nodiscard]] std::size_t remaining() const { return bytes_.size() - pos_; }

 private:
  std::string_view bytes_;
  std::size_t pos_ = 0;
  bool ok_ = true;
};

// libsvm's powi: the same multiplication order, so the port matches libsvm to the last bit.
double powi(double base, int times) {
  double tmp = base, ret = 1.0;
  for (int t = times; t > 0; t /= 2) {
    if (t % 2 == 1) ret *= tmp;
    tmp = tmp * tmp;
  }
  return ret;
}

double sigmoid_predict(double decision_value, double a, double b) {
  const double f = decision_value * a + b;
  return f >= 0 ? std::exp(-f) / (1.0 + std::exp(-f)) : 1.0 / (1.0 + std::exp(f));
}

// Sum of a[m] * b[m] over m < n in four interleaved partial sums: the compiler may not reassociate one running
// sum (strict IEEE order), so a single accumulator waits on every add; four keep the FPU busy. The result differs
// from the sequential sum by rounding only (~1e-16 relative), which libsvm's own order does not promise either.
double dot4(const double* a, const double* b, std::size_t n) {
  double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
  std::size_t m = 0;
  for (; m + 4 <= n; m += 4) {
    s0 += a[m] * b[m];
    s1 += a[m + 1] * b[m + 1];
    s2 += a[m + 2] * b[m + 2];
    s3 += a[m + 3] * b[m + 3];
  }
  for (; m < n; ++m) s0 += a[m] * b[m];
  return (s0 + s1) + (s2 + s3);
}

// libsvm's multiclass_probability (Wu, Lin and Weng 2004, method 2) on caller-owned k x k / k buffers: the same
// iteration, start, stopping rule and fixed point. libsvm divides all k entries of p and Qp by (1 + diff) after
// each coordinate step, k^2 divisions per sweep: at 300 classes and up to 300 sweeps that alone took 11-35 ms
// (issue 11). Here p and Qp are kept as scale * stored value; a step updates the scale and adds diff / scale *
// Q[t] to the stored Qp (one multiply-add per entry), and every sweep starts from exactly rescaled values.
void multiclass_probability(int k, const double* r, double* q, double* qp, double* p) {
  const int max_iter = std::max(100, k);
  const double eps = 0.005 / k;
  const auto kk = static_cast<std::size_t>(k);
  for (std::size_t t = 0; t < kk; ++t) {
    p[t] = 1.0 / k;
    q[t * kk + t] = 0;
    for (std::size_t j = 0; j < t; ++j) {
      q[t * kk + t] += r[j * kk + t] * r[j * kk + t];
      q[t * kk + j] = q[j * kk + t];
    }
    for (std::size_t j = t + 1; j < kk; ++j) {
      q[t * kk + t] += r[j * kk + t] * r[j * kk + t];
      q[t * kk + j] = -r[j * kk + t] * r[t * kk + j];
    }
  }
  for (int iter = 0; iter < max_iter; ++iter) {
    double pqp = 0;
    for (std::size_t t = 0; t < kk; ++t) {
      qp[t] = dot4(&q[t * kk], p, kk);
      pqp += p[t] * qp[t];
    }
    double max_error = 0;
    for (std::size_t t = 0; t < kk; ++t) max_error = std::max(max_error, std::fabs(qp[t] - pqp));
    if (max_error < eps) break;
    double scale = 1.0;  // true p[j] = scale * p[j], true qp[j] = scale * qp[j]
    for (std::size_t t = 0; t < kk; ++t) {
      const double qpt = scale * qp[t];
      const double diff = (-qpt + pqp) / q[t * kk + t];
      const double step = diff / scale;  // diff in stored units
      p[t] += step;
      pqp = (pqp + diff * (diff * q[t * kk + t] + 2 * qpt)) / (1 + diff) / (1 + diff);
      const double* qt = &q[t * kk];
      for (std::size_t j = 0; j < kk; ++j) qp[j] += step * qt[j];
      scale /= (1 + diff);
    }
    for (std::size_t j = 0; j < kk; ++j) p[j] *= scale;
  }
}

struct LibsvmModelDeleter {
  void operator()(svm_model* m) const { svm_free_and_destroy_model(&m); }
};

}  // namespace

void silence_libsvm() {
  static std::once_flag once;
  std::call_once(once, [] { svm_set_print_string_function(&discard_libsvm_output); });
}

std::string_view to_string(KernelType kernel) {
  switch (kernel) {
    case KernelType::kRbf: return "rbf";
    case KernelType::kPoly: return "poly";
  }
  return "unknown";
}

std::string SvmHyper::describe(int active_features) const {
  char text[160];
  if (kernel == KernelType::kRbf) {
    std::snprintf(text, sizeof text, "rbf C=%g gamma=%.4g (i=%g / %d features)", c, gamma(active_features),
                  gamma_factor, active_features);
  } else {
    std::snprintf(text, sizeof text, "poly degree=%d C=%g gamma=%.4g (i=%g / %d features) coef0=%g", degree, c,
                  gamma(active_features), gamma_factor, active_features, coef0);
  }
  return text;
}

// ---- Scaler -------------------------------------------------------------------------------------------------------

Scaler Scaler::fit(std::span<const FeatureVector> samples) {
  Scaler s;
  if (samples.empty()) return s;
  std::vector<double> values(samples.size());
  for (int f = 0; f < kFeatureCount; ++f) {
    const auto fi = static_cast<std::size_t>(f);
    Range& r = s.ranges_[fi];
    for (std::size_t i = 0; i < samples.size(); ++i) values[i] = samples[i][fi];
    if (kFeatureTable[fi].heavy_tailed) {
      // Of the finite values only, as the range below: a NaN breaks nth_element's ordering (the median came out NaN
      // and switched the compression off).
      std::vector<double> magnitude;
      for (double v : values) {
        if (std::isfinite(v)) magnitude.push_back(std::fabs(v));
      }
      double scale = 0.0;
      if (!magnitude.empty()) {
        auto mid = magnitude.begin() + static_cast<std::ptrdiff_t>(magnitude.size() / 2);
        std::nth_element(magnitude.begin(), mid, magnitude.end());
        scale = *mid;
        if (!(scale > 0.0)) scale = *std::max_element(magnitude.begin(), magnitude.end());
      }
      r.compress = scale > 0.0 ? scale : 0.0;
    }
    r.lo = r.hi = 0.0;
    bool first = true;
    for (double v : values) {
      const double t = r.compress > 0.0 ? std::asinh(v / r.compress) : v;
      if (!std::isfinite(t)) continue;
      r.lo = first ? t : std::min(r.lo, t);
      r.hi = first ? t : std::max(r.hi, t);
      first = false;
    }
  }
  return s;
}

Scaler Scaler::from_ranges(const std::array<Range, kFeatureCount>& ranges) {
  Scaler s;
  s.ranges_ = ranges;
  return s;
}

double Scaler::scale(int feature, double value) const {
  const Range& r = ranges_[static_cast<std::size_t>(feature)];
  const double t = r.compress > 0.0 ? std::asinh(value / r.compress) : value;
  if (!(r.hi > r.lo)) return 0.0;  // constant in training: carries no information
  const double y = 2.0 * (t - r.lo) / (r.hi - r.lo) - 1.0;
  if (!std::isfinite(y)) return 0.0;
  return std::clamp(y, -kClip, kClip);
}

void Scaler::apply(const FeatureVector& features, const FeatureMask& mask, std::span<double> out) const {
  std::size_t k = 0;
  for (int f = 0; f < kFeatureCount && k < out.size(); ++f) {
    if (mask.test(static_cast<std::size_t>(f))) out[k++] = scale(f, features[static_cast<std::size_t>(f)]);
  }
}

// ---- training -----------------------------------------------------------------------------------------------------

svm_parameter make_svm_parameter(const SvmHyper& hyper, int active_features, PlattFit platt) {
  // Until both callers used this, the cross-validation had a 40 MB cache and the shipped model 100 MB: the cache
  // only saves recomputing kernel columns, so the models are the same with either.
  constexpr double kCacheMb = 100;
  constexpr double kStopTolerance = 1e-3;  // libsvm's default eps
  svm_parameter param{};
  param.svm_type = C_SVC;
  param.kernel_type = hyper.kernel == KernelType::kRbf ? RBF : POLY;
  param.degree = hyper.degree;
  param.gamma = hyper.gamma(active_features);
  param.coef0 = hyper.coef0;
  param.cache_size = kCacheMb;
  param.eps = kStopTolerance;
  param.C = hyper.c;
  param.shrinking = 1;
  param.probability = platt == PlattFit::kYes ? 1 : 0;
  return param;
}

Expected<SvmModel> SvmModel::train(std::span<const FeatureVector> features, std::span<const int> labels,
                                   std::vector<ClassInfo> classes, const FeatureMask& mask, const Scaler& scaler,
                                   const SvmHyper& hyper, std::uint64_t seed) {
  const int k = static_cast<int>(classes.size());
  const int dims = static_cast<int>(mask.count());
  if (features.size() != labels.size()) return make_error("SVM training: features and labels differ in count");
  if (k < 2 || k > kMaxClasses) return make_error("SVM training needs at least two classes");
  if (dims == 0) return make_error("SVM training: the feature mask selects no feature");
  if (!(hyper.c > 0.0) || !(hyper.gamma_factor > 0.0) ||
      (hyper.kernel == KernelType::kPoly && (hyper.degree < 1 || hyper.degree > kMaxDegree))) {
    return make_error("SVM training: C and gamma must be > 0 and the polynomial degree in 1.." +
                      std::to_string(kMaxDegree));
  }
  std::vector<int> per_class(static_cast<std::size_t>(k), 0);
  for (int y : labels) {
    if (y < 0 || y >= k) return make_error("SVM training: label " + std::to_string(y) + " is not a class index");
    ++per_class[static_cast<std::size_t>(y)];
  }
  for (int c = 0; c < k; ++c) {
    if (per_class[static_cast<std::size_t>(c)] < 2) {
      return make_error("SVM training: class '" + classes[static_cast<std::size_t>(c)].name + "' has " +
                        std::to_string(per_class[static_cast<std::size_t>(c)]) +
                        " training sample(s); at least 2 are needed for the probability model");
    }
  }

  // Dense rows as libsvm nodes (zeros kept, so libsvm's sums run in the same order as our prediction's).
  const std::size_t n = features.size(), stride = static_cast<std::size_t>(dims) + 1;
  std::vector<svm_node> nodes(n * stride);
  std::vector<svm_node*> rows(n);
  std::vector<double> y(n), scaled(static_cast<std::size_t>(dims));
  for (std::size_t i = 0; i < n; ++i) {
    scaler.apply(features[i], mask, scaled);
    svm_node* row = &nodes[i * stride];
    for (int j = 0; j < dims; ++j) row[j] = {j + 1, scaled[static_cast<std::size_t>(j)]};
    row[dims] = {-1, 0.0};
    rows[i] = row;
    y[i] = labels[i];
  }
  svm_problem problem{static_cast<int>(n), y.data(), rows.data()};
  const svm_parameter param = make_svm_parameter(hyper, dims, PlattFit::kYes);  // the shipped model: probabilities
  if (const char* why = svm_check_parameter(&problem, &param)) {
    return make_error(std::string("SVM training: libsvm refused the parameters: ") + why);
  }
  silence_libsvm();
  std::srand(static_cast<unsigned>(seed));  // libsvm's Platt cross-validation shuffles with rand()
  std::unique_ptr<svm_model, LibsvmModelDeleter> lib(svm_train(&problem, &param));
  if (!lib || lib->nr_class != k || lib->probA == nullptr || lib->probB == nullptr) {
    return make_error("SVM training: libsvm did not return a probability model for every class");
  }

  SvmModel m;
  m.classes_ = std::move(classes);
  m.mask_ = mask;
  m.scaler_ = scaler;
  m.hyper_ = hyper;
  m.dims_ = dims;
  m.sv_count_ = lib->l;
  const auto l = static_cast<std::size_t>(lib->l);
  const auto pairs = static_cast<std::size_t>(k * (k - 1) / 2);
  for (int s = 0; s < k; ++s) {
    m.slot_class_.push_back(lib->label[s]);
    m.slot_sv_count_.push_back(lib->nSV[s]);
  }
  m.sv_.assign(l * static_cast<std::size_t>(dims), 0.0);
  for (std::size_t i = 0; i < l; ++i) {
    for (const svm_node* p = lib->SV[i]; p->index != -1; ++p) {
      if (p->index >= 1 && p->index <= dims)
        m.sv_[i * (stride - 1) + static_cast<std::size_t>(p->index - 1)] = p->value;
    }
  }
  m.coef_.resize(static_cast<std::size_t>(k - 1) * l);
  for (int c = 0; c < k - 1; ++c) {
    std::copy_n(lib->sv_coef[c], l, m.coef_.begin() + static_cast<std::ptrdiff_t>(static_cast<std::size_t>(c) * l));
  }
  m.rho_.assign(lib->rho, lib->rho + pairs);
  m.prob_a_.assign(lib->probA, lib->probA + pairs);
  m.prob_b_.assign(lib->probB, lib->probB + pairs);
  m.allocate_scratch();
  return m;
}

void SvmModel::allocate_scratch() {
  const auto k = classes_.size();
  x_.assign(static_cast<std::size_t>(dims_), 0.0);
  kvalue_.assign(static_cast<std::size_t>(sv_count_), 0.0);
  decision_.assign(k * (k - 1) / 2, 0.0);
  pairwise_.assign(k * k, 0.0);
  q_.assign(k * k, 0.0);
  qp_.assign(k, 0.0);
  p_.assign(k, 0.0);
  start_.assign(k, 0);
  out_.assign(k, {});
}

// ---- prediction ---------------------------------------------------------------------------------------------------

double SvmModel::kernel(const double* a, const double* b) const {
  const double gamma = hyper_.gamma(dims_);  // the same expression libsvm was trained with
  double sum = 0.0;
  if (hyper_.kernel == KernelType::kRbf) {
    for (int i = 0; i < dims_; ++i) {
      const double d = a[i] - b[i];
      sum += d * d;
    }
    return std::exp(-gamma * sum);
  }
  for (int i = 0; i < dims_; ++i) sum += a[i] * b[i];
  return powi(gamma * sum + hyper_.coef0, hyper_.degree);
}

std::span<const ClassProbability> SvmModel::predict(const FeatureVector& features) {
  if (empty()) return {};
  const int k = static_cast<int>(classes_.size());
  const auto dims = static_cast<std::size_t>(dims_);
  scaler_.apply(features, mask_, x_);
  for (std::size_t i = 0; i < kvalue_.size(); ++i) kvalue_[i] = kernel(x_.data(), &sv_[i * dims]);

  // Decision values of the k(k-1)/2 one-against-one classifiers (libsvm's svm_predict_values, eq. 2.45).
  const auto l = static_cast<std::size_t>(sv_count_);
  const auto kk = static_cast<std::size_t>(k);
  start_[0] = 0;
  for (std::size_t s = 1; s < kk; ++s) start_[s] = start_[s - 1] + slot_sv_count_[s - 1];
  std::size_t p = 0;
  for (std::size_t i = 0; i < kk; ++i) {
    for (std::size_t j = i + 1; j < kk; ++j, ++p) {
      const auto si = static_cast<std::size_t>(start_[i]), sj = static_cast<std::size_t>(start_[j]);
      const auto ci = static_cast<std::size_t>(slot_sv_count_[i]), cj = static_cast<std::size_t>(slot_sv_count_[j]);
      const double* coef1 = &coef_[(j - 1) * l];
      const double* coef2 = &coef_[i * l];
      decision_[p] = dot4(&coef1[si], &kvalue_[si], ci) + dot4(&coef2[sj], &kvalue_[sj], cj) - rho_[p];
    }
  }
  // Pairwise Platt probabilities, coupled into one distribution (libsvm's svm_predict_probability).
  p = 0;
  for (std::size_t i = 0; i < kk; ++i) {
    for (std::size_t j = i + 1; j < kk; ++j, ++p) {
      const double r = std::min(std::max(sigmoid_predict(decision_[p], prob_a_[p], prob_b_[p]), kMinProbability),
                                1.0 - kMinProbability);
      pairwise_[i * kk + j] = r;
      pairwise_[j * kk + i] = 1.0 - r;
    }
  }
  if (k == 2) {  // libsvm >= 3.24 takes the pairwise probability itself for two classes
    p_[0] = pairwise_[1];
    p_[1] = pairwise_[2];
  } else {
    multiclass_probability(k, pairwise_.data(), q_.data(), qp_.data(), p_.data());
  }
  for (std::size_t s = 0; s < kk; ++s) out_[s] = {slot_class_[s], p_[s]};
  std::sort(out_.begin(), out_.end(), [](const ClassProbability& a, const ClassProbability& b) {
    return a.probability != b.probability ? a.probability > b.probability : a.class_index < b.class_index;
  });
  return out_;
}

// ---- serialization ------------------------------------------------------------------------------------------------

std::string SvmModel::serialize() const {
  ByteWriter w;
  w.bytes().append(kMagic.data(), kMagic.size());
  w.put(kFormatVersion);
  w.put(kFeatureVersion);
  w.put(static_cast<std::uint32_t>(kFeatureCount));
  for (const FeatureInfo& f : kFeatureTable) w.put_string(f.name);
  for (int f = 0; f < kFeatureCount; ++f)
    w.put(static_cast<std::uint8_t>(mask_.test(static_cast<std::size_t>(f)) ? 1 : 0));
  for (const Scaler::Range& r : scaler_.ranges()) {
    w.put(r.compress);
    w.put(r.lo);
    w.put(r.hi);
  }
  w.put(static_cast<std::uint32_t>(classes_.size()));
  for (const ClassInfo& c : classes_) {
    w.put(static_cast<std::int32_t>(c.id));
    w.put_string(c.name);
  }
  w.put(static_cast<std::uint8_t>(hyper_.kernel));
  w.put(hyper_.c);
  w.put(hyper_.gamma_factor);
  w.put(static_cast<std::int32_t>(hyper_.degree));
  w.put(hyper_.coef0);
  w.put(static_cast<std::uint32_t>(dims_));
  w.put(static_cast<std::uint32_t>(sv_count_));
  for (int c : slot_class_) w.put(static_cast<std::uint32_t>(c));
  for (int c : slot_sv_count_) w.put(static_cast<std::uint32_t>(c));
  w.put_doubles(sv_);
  w.put_doubles(coef_);
  w.put_doubles(rho_);
  w.put_doubles(prob_a_);
  w.put_doubles(prob_b_);
  const std::uint32_t crc = base::crc32(w.bytes());
  w.put(crc);
  return std::move(w.bytes());
}

namespace {

constexpr const char* kRefused = "SVM model refused: ";

Error refused(const std::string& why) {
  return make_error(kRefused + why);
}
Error truncated() {
  return refused("truncated or malformed content");
}

// Magic and checksum; `body` is what the checksum covers.
Status check_envelope(std::string_view blob, std::string_view& body) {
  if (blob.size() < kMagic.size() + 4 || std::memcmp(blob.data(), kMagic.data(), kMagic.size()) != 0) {
    return refused("not a cellsight SVM model (bad magic or too short)");
  }
  std::uint32_t stored_crc = 0;
  std::memcpy(&stored_crc, blob.data() + blob.size() - 4, 4);
  body = blob.substr(0, blob.size() - 4);
  if (base::crc32(body) != stored_crc) return refused("checksum mismatch (the file is corrupt or truncated)");
  return {};
}

// Format version, feature version and the 74 feature names: the model must have been trained on this build's.
Status read_versions(ByteReader& r) {
  std::uint32_t format = 0, feature_version = 0, feature_count = 0;
  if (!r.get(format) || !r.get(feature_version) || !r.get(feature_count)) return truncated();
  if (format != SvmModel::kFormatVersion) {
    return refused("format version " + std::to_string(format) + ", this build reads version " +
                   std::to_string(SvmModel::kFormatVersion));
  }
  if (feature_version != kFeatureVersion || feature_count != kFeatureCount) {
    return refused("trained on feature version " + std::to_string(feature_version) + " (" +
                   std::to_string(feature_count) + " features); this build computes version " +
                   std::to_string(kFeatureVersion) + " (" + std::to_string(kFeatureCount) +
                   " features): retrain the model");
  }
  for (const FeatureInfo& f : kFeatureTable) {
    std::string name;
    if (!r.get_string(name)) return truncated();
    if (name != f.name) {
      return refused("feature '" + name + "' where this build has '" + std::string(f.name) +
                     "': the model was trained on other features; retrain it");
    }
  }
  return {};
}

Status read_mask_and_scaler(ByteReader& r, FeatureMask& mask, Scaler& scaler) {
  for (int f = 0; f < kFeatureCount; ++f) {
    std::uint8_t bit = 0;
    if (!r.get(bit) || bit > 1) return truncated();
    mask.set(static_cast<std::size_t>(f), bit == 1);
  }
  std::array<Scaler::Range, kFeatureCount> ranges{};
  for (Scaler::Range& range : ranges) {
    if (!r.get(range.compress) || !r.get(range.lo) || !r.get(range.hi)) return truncated();
    if (!std::isfinite(range.compress) || !std::isfinite(range.lo) || !std::isfinite(range.hi) ||
        range.compress < 0.0 || range.hi < range.lo) {
      return refused("invalid scaler range");
    }
  }
  scaler = Scaler::from_ranges(ranges);
  return {};
}

Status read_classes(ByteReader& r, std::vector<ClassInfo>& classes) {
  std::uint32_t k = 0;
  if (!r.get(k)) return truncated();
  if (k < 2 || k > kMaxClasses) return refused("class count " + std::to_string(k) + " out of range");
  for (std::uint32_t c = 0; c < k; ++c) {
    std::int32_t id = 0;
    ClassInfo info;
    if (!r.get(id) || !r.get_string(info.name)) return truncated();
    info.id = id;
    classes.push_back(std::move(info));
  }
  return {};
}

Status read_kernel(ByteReader& r, SvmHyper& hyper) {
  std::uint8_t kernel = 0;
  std::int32_t degree = 0;
  if (!r.get(kernel) || !r.get(hyper.c) || !r.get(hyper.gamma_factor) || !r.get(degree) || !r.get(hyper.coef0)) {
    return truncated();
  }
  if (kernel > static_cast<std::uint8_t>(KernelType::kPoly) || !(hyper.c > 0.0) || !(hyper.gamma_factor > 0.0) ||
      !std::isfinite(hyper.c) || !std::isfinite(hyper.gamma_factor) || !std::isfinite(hyper.coef0) || degree < 1 ||
      degree > kMaxDegree) {
    return refused("invalid kernel parameters");
  }
  hyper.kernel = static_cast<KernelType>(kernel);
  hyper.degree = degree;
  return {};
}

// libsvm's slot order of the k classes (a permutation) and the support vectors per slot, adding up to `l`.
Status read_slots(ByteReader& r, std::uint32_t k, std::uint32_t l, std::vector<int>& slot_class,
                  std::vector<int>& slot_sv_count) {
  std::vector<bool> seen(k, false);
  std::uint64_t total = 0;
  for (std::uint32_t s = 0; s < k; ++s) {
    std::uint32_t c = 0;
    if (!r.get(c)) return truncated();
    if (c >= k || seen[c]) return refused("class slots are not a permutation of the classes");
    seen[c] = true;
    slot_class.push_back(static_cast<int>(c));
  }
  for (std::uint32_t s = 0; s < k; ++s) {
    std::uint32_t c = 0;
    if (!r.get(c)) return truncated();
    total += c;
    slot_sv_count.push_back(static_cast<int>(c));
  }
  if (total != l) return refused("per-class support vector counts do not add up");
  return {};
}

}  // namespace

Expected<SvmModel> SvmModel::deserialize(std::string_view blob) {
  std::string_view body;
  if (Status envelope = check_envelope(blob, body); !envelope) return envelope.error();
  ByteReader r(body.substr(kMagic.size()));
  if (Status versions = read_versions(r); !versions) return versions.error();
  SvmModel m;
  if (Status scaling = read_mask_and_scaler(r, m.mask_, m.scaler_); !scaling) return scaling.error();
  if (Status classes = read_classes(r, m.classes_); !classes) return classes.error();
  const auto k = static_cast<std::uint32_t>(m.classes_.size());
  if (Status kernel = read_kernel(r, m.hyper_); !kernel) return kernel.error();
  std::uint32_t dims = 0, l = 0;
  if (!r.get(dims) || !r.get(l)) return truncated();
  if (dims != m.mask_.count() || dims == 0) return refused("support vector size does not match the mask");
  if (l == 0 || l > r.remaining() / sizeof(double)) return refused("support vector count out of range");
  m.dims_ = static_cast<int>(dims);
  m.sv_count_ = static_cast<int>(l);
  if (Status slots = read_slots(r, k, l, m.slot_class_, m.slot_sv_count_); !slots) return slots.error();
  const std::size_t pairs = static_cast<std::size_t>(k) * (k - 1) / 2;
  if (!r.get_doubles(static_cast<std::size_t>(l) * dims, m.sv_) ||
      !r.get_doubles(static_cast<std::size_t>(k - 1) * l, m.coef_) || !r.get_doubles(pairs, m.rho_) ||
      !r.get_doubles(pairs, m.prob_a_) || !r.get_doubles(pairs, m.prob_b_)) {
    return truncated();
  }
  if (r.remaining() != 0) return refused("unexpected bytes after the model");
  m.allocate_scratch();
  return m;
}

}  // namespace cellsight::algo
