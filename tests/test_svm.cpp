// Probability SVM against libsvm itself, its byte format against corruption, and the training machinery
// (k-fold, simulated annealing, determinism, stop flag, kNN and MLP) on seeded synthetic data.
#include <libsvm/svm.h>

#include <algorithm>
#include <atomic>
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "algo/svm.hpp"
#include "algo/training.hpp"
#include "tests/support/alloc_counter.hpp"

using namespace cellsight;
using algo::FeatureMask;
using algo::FeatureVector;

namespace {

// Gaussian clusters in 74-D: `informative` features carry the class (centres 1.5 sd apart on average), every other
// feature is noise drawn the same way for all classes. Indices avoid the heavy-tailed Hu features on purpose
// (they would be asinh-compressed; the scaler is tested separately).
const std::vector<int> kInformative = {0, 1, 20, 45, 70, 72};

// one_hot: class c sits at +spread on informative feature c and at 0 on the others, so telling all classes
// apart needs at least classes - 1 of the informative features.
algo::Dataset make_clusters(int classes, int per_class, std::uint64_t seed,
                            const std::vector<int>& informative = kInformative, double spread = 1.5,
                            bool one_hot = false) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::vector<std::vector<double>> centres(static_cast<std::size_t>(classes), std::vector<double>(informative.size()));
  for (std::size_t c = 0; c < centres.size(); ++c) {
    for (std::size_t k = 0; k < informative.size(); ++k)
      centres[c][k] = one_hot ? (c == k ? spread : 0.0) : spread * g(rng);
  }
  algo::Dataset d;
  for (int c = 0; c < classes; ++c) d.classes.push_back({"class_" + std::to_string(c), 100 + c});
  for (int i = 0; i < per_class; ++i) {
    for (int c = 0; c < classes; ++c) {
      FeatureVector f{};
      for (float& v : f) v = static_cast<float>(g(rng));
      for (std::size_t k = 0; k < informative.size(); ++k) {
        f[static_cast<std::size_t>(informative[k])] =
            static_cast<float>(centres[static_cast<std::size_t>(c)][k] + 0.5 * g(rng));
      }
      d.features.push_back(f);
      d.labels.push_back(c);
    }
  }
  return d;
}

FeatureMask mask_of(const std::vector<int>& features) {
  FeatureMask m;
  for (int f : features) m.set(static_cast<std::size_t>(f));
  return m;
}

// libsvm trained directly on the same scaled rows and parameters, queried with its own svm_predict_probability.
class LibsvmReference {
 public:
  LibsvmReference(const algo::Dataset& train, const algo::SvmModel& model, std::uint64_t seed) : model_(model) {
    const int dims = model.active_features();
    stride_ = static_cast<std::size_t>(dims) + 1;
    nodes_.resize(train.size() * stride_);
    for (std::size_t i = 0; i < train.size(); ++i) {
      fill(train.features[i], &nodes_[i * stride_]);
      rows_.push_back(&nodes_[i * stride_]);
      y_.push_back(train.labels[i]);
    }
    svm_problem problem{static_cast<int>(train.size()), y_.data(), rows_.data()};
    svm_parameter p{};
    p.svm_type = C_SVC;
    p.kernel_type = model.hyper().kernel == algo::KernelType::kRbf ? RBF : POLY;
    p.degree = model.hyper().degree;
    p.gamma = model.hyper().gamma_factor / dims;
    p.coef0 = model.hyper().coef0;
    p.cache_size = 100;
    p.eps = 1e-3;
    p.C = model.hyper().c;
    p.shrinking = 1;
    p.probability = 1;
    std::srand(static_cast<unsigned>(seed));
    lib_ = svm_train(&problem, &p);
  }
  ~LibsvmReference() { svm_free_and_destroy_model(&lib_); }
  LibsvmReference(const LibsvmReference&) = delete;
  LibsvmReference& operator=(const LibsvmReference&) = delete;

  // Probability of each class index.
  std::vector<double> probabilities(const FeatureVector& f) {
    std::vector<svm_node> x(stride_);
    fill(f, x.data());
    std::vector<double> by_slot(static_cast<std::size_t>(lib_->nr_class)), by_class(by_slot.size());
    svm_predict_probability(lib_, x.data(), by_slot.data());
    for (int s = 0; s < lib_->nr_class; ++s)
      by_class[static_cast<std::size_t>(lib_->label[s])] = by_slot[static_cast<std::size_t>(s)];
    return by_class;
  }

 private:
  void fill(const FeatureVector& f, svm_node* row) const {
    std::vector<double> scaled(stride_ - 1);
    model_.scaler().apply(f, model_.mask(), scaled);
    for (std::size_t j = 0; j + 1 < stride_; ++j) row[j] = {static_cast<int>(j) + 1, scaled[j]};
    row[stride_ - 1] = {-1, 0.0};
  }
  const algo::SvmModel& model_;
  std::size_t stride_ = 0;
  std::vector<svm_node> nodes_;
  std::vector<svm_node*> rows_;
  std::vector<double> y_;
  svm_model* lib_ = nullptr;
};

// Bitwise CRC-32 (IEEE, reflected) written independently of the table-driven one in svm.cpp.
std::uint32_t crc32_bitwise(const std::string& bytes) {
  std::uint32_t crc = 0xFFFFFFFFU;
  for (unsigned char c : bytes) {
    crc ^= c;
    for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xEDB88320U & (0U - (crc & 1U)));
  }
  return ~crc;
}

// Replaces `count` bytes at `offset` and re-seals the blob with a valid checksum (a well-formed foreign model).
std::string patched(std::string blob, std::size_t offset, const void* bytes, std::size_t count) {
  std::memcpy(blob.data() + offset, bytes, count);
  const std::string body = blob.substr(0, blob.size() - 4);
  const std::uint32_t crc = crc32_bitwise(body);
  std::memcpy(blob.data() + blob.size() - 4, &crc, 4);
  return blob;
}

algo::SvmModel train_model(const algo::Dataset& train, const algo::SvmHyper& hyper, std::uint64_t seed = 7) {
  auto m = algo::SvmModel::train(train.features, train.labels, train.classes, mask_of(kInformative),
                                 algo::Scaler::fit(train.features), hyper, seed);
  REQUIRE(m.ok());
  return std::move(*m);
}

algo::TrainParams small_params() {
  algo::TrainParams p;
  p.folds = 3;
  p.seed = 5;
  p.threads = 2;
  p.c_grid = {1.0, 16.0};
  p.gamma_factors = {1.0};
  p.annealing.iterations = 12;
  p.annealing.start_temperature = 2.0;
  p.annealing.cooling_ratio = 0.8;
  return p;
}

// The split trained twice: with `p`, then with `change` applied to it (both must succeed).
std::pair<algo::TrainingResult, algo::TrainingResult> train_twice(
    const algo::DatasetSplit& split, algo::TrainParams p, const std::function<void(algo::TrainParams&)>& change) {
  auto a = algo::train_recogniser(split, p);
  change(p);
  auto b = algo::train_recogniser(split, p);
  REQUIRE(a.ok());
  REQUIRE(b.ok());
  return {std::move(*a), std::move(*b)};
}

}  // namespace

SCENARIO("The probability SVM classifies held-out clusters and its probabilities are a distribution", "[svm]") {
  GIVEN("5 classes of 74-D clusters, 30 training and 20 test samples each") {
    const algo::Dataset all = make_clusters(5, 50, 1);
    algo::Dataset train = all, test = all;  // the first 150 samples train, the other 100 test
    train.features.resize(150);
    train.labels.resize(150);
    test.features.erase(test.features.begin(), test.features.begin() + 150);
    test.labels.erase(test.labels.begin(), test.labels.begin() + 150);
    WHEN("an RBF SVM is trained on the informative features and asked about the test samples") {
      algo::SvmModel model = train_model(train, {algo::KernelType::kRbf, 4.0, 1.0, 3, 0.0});
      THEN("accuracy is high, probabilities sum to 1, come sorted, and the winner's reflects the accuracy") {
        int correct = 0;
        double winner_probability = 0.0;
        for (std::size_t i = 0; i < test.size(); ++i) {
          const auto p = model.predict(test.features[i]);
          REQUIRE(p.size() == 5);
          double sum = 0.0;
          for (std::size_t k = 0; k < p.size(); ++k) {
            sum += p[k].probability;
            if (k > 0) CHECK(p[k - 1].probability >= p[k].probability);
          }
          CHECK(sum == Approx(1.0).margin(1e-6));
          CHECK(p[0].probability > p[1].probability);
          correct += p[0].class_index == test.labels[i] ? 1 : 0;
          winner_probability += p[0].probability;
        }
        const double accuracy = static_cast<double>(correct) / static_cast<double>(test.size());
        const double mean_p1 = winner_probability / static_cast<double>(test.size());
        INFO("accuracy " << accuracy << " mean winner probability " << mean_p1);
        CHECK(accuracy >= 0.9);
        // Calibrated-ish: Platt scaling on CV decision values should put the mean winner probability near the
        // accuracy, not at 1.0 (over-confident) nor near 1/5.
        CHECK(std::abs(mean_p1 - accuracy) < 0.15);
      }
    }
  }
}

SCENARIO("Our allocation-free prediction equals libsvm's svm_predict_probability", "[svm]") {
  GIVEN("models trained by SvmModel and, independently, by libsvm on the same scaled data and seed") {
    struct Case {
      int classes;
      algo::SvmHyper hyper;
    };
    const std::vector<Case> cases = {{5, {algo::KernelType::kRbf, 4.0, 1.0, 3, 0.0}},
                                     {4, {algo::KernelType::kPoly, 2.0, 1.0, 3, 0.0}},
                                     {3, {algo::KernelType::kPoly, 1.0, 10.0, 2, 1.0}},
                                     {2, {algo::KernelType::kRbf, 16.0, 10.0, 3, 0.0}},
                                     // many classes: the rescaled coupling runs many sweeps (issue 11)
                                     {60, {algo::KernelType::kRbf, 1.0, 1.0, 3, 0.0}}};
    WHEN("both predict 10 fresh samples of every class") {
      THEN("every class probability agrees to 1e-9") {
        for (const Case& c : cases) {
          const algo::Dataset train = make_clusters(c.classes, 25, 3);
          const algo::Dataset fresh = make_clusters(c.classes, 10, 99);
          algo::SvmModel model = train_model(train, c.hyper, 11);
          LibsvmReference reference(train, model, 11);
          double worst = 0.0;
          for (const FeatureVector& f : fresh.features) {
            const std::vector<double> expected = reference.probabilities(f);
            for (const algo::ClassProbability& p : model.predict(f)) {
              worst = std::max(worst, std::abs(p.probability - expected[static_cast<std::size_t>(p.class_index)]));
            }
          }
          INFO(c.classes << " classes, " << c.hyper.describe(model.active_features()));
          CHECK(worst < 1e-9);
        }
      }
    }
  }
}

SCENARIO("predict() does not allocate", "[svm]") {
  GIVEN("a trained 5-class model") {
    const algo::Dataset train = make_clusters(5, 20, 2);
    algo::SvmModel model = train_model(train, {algo::KernelType::kRbf, 4.0, 1.0, 3, 0.0});
    WHEN("it predicts 100 samples") {
      double total = 0.0;
      long allocations = 0;
      {
        const test::AllocationWindow window;
        for (int i = 0; i < 100; ++i) {
          total += model.predict(train.features[static_cast<std::size_t>(i)])[0].probability;
        }
        allocations = window.count();
      }
      THEN("no allocation happened") {
        CHECK(total > 0.0);
        CHECK(allocations == 0);
      }
    }
  }
}

SCENARIO("A model survives serialization bit for bit, and damaged or foreign blobs are refused", "[svm]") {
  GIVEN("a trained model and its bytes") {
    const algo::Dataset train = make_clusters(4, 20, 4);
    algo::SvmModel model = train_model(train, {algo::KernelType::kPoly, 2.0, 1.0, 3, 0.5});
    const std::string blob = model.serialize();
    WHEN("the bytes are read back") {
      auto back = algo::SvmModel::deserialize(blob);
      REQUIRE(back.ok());
      THEN("classes, mask, kernel and every prediction are identical, and it serializes to the same bytes") {
        CHECK(back->classes().size() == 4);
        CHECK(back->classes()[2].name == "class_2");
        CHECK(back->classes()[2].id == 102);
        CHECK(back->mask() == model.mask());
        CHECK(back->hyper().kernel == algo::KernelType::kPoly);
        CHECK(back->hyper().coef0 == 0.5);
        CHECK(back->support_vectors() == model.support_vectors());
        const algo::Dataset fresh = make_clusters(4, 10, 44);
        for (const FeatureVector& f : fresh.features) {
          const auto a = model.predict(f);
          const std::vector<algo::ClassProbability> expected(a.begin(), a.end());
          const auto b = back->predict(f);
          REQUIRE(b.size() == expected.size());
          for (std::size_t k = 0; k < b.size(); ++k) {
            CHECK(b[k].class_index == expected[k].class_index);
            CHECK(b[k].probability == expected[k].probability);  // bit-identical
          }
        }
        CHECK(back->serialize() == blob);
      }
    }
    WHEN("the bytes are damaged, cut or foreign") {
      THEN("each is refused with a reason") {
        auto refused = [](const std::string& bytes, const std::string& reason) {
          auto r = algo::SvmModel::deserialize(bytes);
          REQUIRE_FALSE(r.ok());
          INFO(r.error().message);
          CHECK(r.error().message.find(reason) != std::string::npos);
        };
        std::string flipped = blob;
        flipped[blob.size() / 2] = static_cast<char>(flipped[blob.size() / 2] ^ 0x10);
        refused(flipped, "checksum");
        refused(blob.substr(0, blob.size() - 9), "checksum");
        refused(blob.substr(0, 5), "not a cellsight SVM model");
        refused("", "not a cellsight SVM model");
        refused(std::string(blob.size(), 'x'), "not a cellsight SVM model");
        // Well-sealed blobs from another build: feature version 2, then a renamed feature, then format 9.
        const std::uint32_t other_version = algo::kFeatureVersion + 1;
        refused(patched(blob, 12, &other_version, 4), "feature version");
        const std::size_t first_name = 8 + 4 + 4 + 4 + 2;  // magic, format, feature version, count, name length
        refused(patched(blob, first_name, "W", 1), "feature 'Width_m'");
        const std::uint32_t other_format = 9;
        refused(patched(blob, 8, &other_format, 4), "format version 9");
        // A sealed blob whose declared content is shorter than the bytes: refused, not half-read.
        std::string longer = blob.substr(0, blob.size() - 4) + std::string(16, '\0') + blob.substr(blob.size() - 4);
        refused(patched(longer, 0, "C", 1), "unexpected bytes");
      }
    }
  }
}

SCENARIO("k-fold cross-validation refuses a class with fewer samples than folds", "[training]") {
  GIVEN("three classes of 10 samples and one of 3") {
    algo::Dataset d = make_clusters(3, 10, 6);
    d.classes.push_back({"rare_part", 9});
    for (int i = 0; i < 3; ++i) {
      d.features.push_back(d.features[static_cast<std::size_t>(i)]);
      d.labels.push_back(3);
    }
    WHEN("5 folds are asked for") {
      auto folds = algo::stratified_folds(d, 5, 1);
      THEN("the error names the class and the need") {
        REQUIRE_FALSE(folds.ok());
        CHECK(folds.error().message.find("'rare_part' has 3 training sample(s); 5-fold") != std::string::npos);
      }
    }
    WHEN("3 folds are asked for") {
      auto folds = algo::stratified_folds(d, 3, 1);
      REQUIRE(folds.ok());
      THEN("every class is spread evenly: each fold holds floor or ceil of its share") {
        for (int c = 0; c < 4; ++c) {
          std::vector<int> per_fold(3, 0);
          for (std::size_t i = 0; i < d.size(); ++i) {
            if (d.labels[i] == c) ++per_fold[static_cast<std::size_t>((*folds)[i])];
          }
          CHECK(*std::max_element(per_fold.begin(), per_fold.end()) -
                    *std::min_element(per_fold.begin(), per_fold.end()) <=
                1);
        }
      }
    }
    WHEN("the whole training is asked for with 5 folds") {
      algo::DatasetSplit split{d, d};
      algo::TrainParams p = small_params();
      p.folds = 5;
      auto r = algo::train_recogniser(split, p);
      THEN("it fails with the same reason") {
        REQUIRE_FALSE(r.ok());
        CHECK(r.error().message.find("rare_part") != std::string::npos);
      }
    }
  }
}

SCENARIO("Simulated annealing selects the informative features", "[training]") {
  GIVEN(
      "4 classes, each marked by one of 4 informative features (3 are needed), 70 noise features, and an initial "
      "mask of 6 noise features") {
    const std::vector<int> informative = {3, 30, 50, 71};
    auto split = algo::split_per_class(make_clusters(4, 30, 12, informative, 2.0, true), 20, 3);
    REQUIRE(split.ok());
    algo::TrainParams p = small_params();
    p.annealing.initial_mask = mask_of({8, 9, 10, 11, 12, 13});
    // Cool enough for 150 steps to settle: T from 1 to 0.002 percentage points, 1 point per extra feature.
    p.annealing.iterations = 150;
    p.annealing.start_temperature = 1.0;
    p.annealing.cooling_ratio = 0.96;
    p.annealing.feature_penalty_pct = 1.0;
    WHEN("the annealing runs") {
      auto r = algo::train_recogniser(*split, p);
      REQUIRE(r.ok());
      const algo::ClassifierReport& svm = r->report.svm;
      THEN("the informative features are chosen far more often than noise, and accuracy rises") {
        int informative_on = 0;
        for (int f : informative) informative_on += svm.mask.test(static_cast<std::size_t>(f)) ? 1 : 0;
        const int noise_on = static_cast<int>(svm.mask.count()) - informative_on;
        INFO("selected: " << svm.mask.count() << " features, informative " << informative_on << ", noise " << noise_on
                          << ", cv " << svm.cv_accuracy << " (initial " << svm.curve.front().current_accuracy << ")");
        CHECK(informative_on >= 3);
        CHECK(static_cast<double>(informative_on) / 4.0 > static_cast<double>(noise_on) / 70.0 + 0.5);
        CHECK(svm.cv_accuracy > svm.curve.front().current_accuracy + 0.4);
        CHECK(svm.test_accuracy >= 0.9);
        CHECK(svm.curve.size() == 151);
        CHECK(svm.evaluations + svm.cache_hits == 151);
      }
    }
  }
}

SCENARIO("Training is deterministic for a seed, whatever the thread count", "[training]") {
  GIVEN("a dataset and two runs with seed 5, on 1 and on 2 threads") {
    auto split = algo::split_per_class(make_clusters(3, 18, 8), 12, 1);
    REQUIRE(split.ok());
    algo::TrainParams p = small_params();
    p.threads = 1;
    auto [ra, rb] = train_twice(*split, p, [](algo::TrainParams& q) { q.threads = 2; });
    const auto* a = &ra;
    const auto* b = &rb;
    THEN("masks, parameters, annealing curves and model bytes are identical") {
      CHECK(a->report.svm.mask == b->report.svm.mask);
      CHECK(a->report.svm.parameters == b->report.svm.parameters);
      REQUIRE(a->report.svm.curve.size() == b->report.svm.curve.size());
      for (std::size_t i = 0; i < a->report.svm.curve.size(); ++i) {
        CHECK(a->report.svm.curve[i].candidate_accuracy == b->report.svm.curve[i].candidate_accuracy);
        CHECK(a->report.svm.curve[i].accepted == b->report.svm.curve[i].accepted);
      }
      CHECK(a->model.serialize() == b->model.serialize());
    }
  }
}

SCENARIO("The stop flag ends the annealing early and keeps the best so far", "[training]") {
  auto split = algo::split_per_class(make_clusters(3, 18, 9), 12, 1);
  REQUIRE(split.ok());
  algo::TrainParams p = small_params();
  p.annealing.iterations = 50;
  GIVEN("a flag raised by the progress callback after step 3") {
    std::atomic<bool> stop{false};
    std::vector<int> seen;
    auto r = algo::train_recogniser(
        *split, p,
        [&](const algo::TrainingProgress& progress) {
          seen.push_back(progress.iteration);
          CHECK(progress.iterations == 50);
          CHECK(progress.eta_s >= 0.0);
          if (progress.iteration == 3) stop.store(true);
        },
        &stop);
    THEN("a usable model comes back, marked as stopped, after exactly 3 steps") {
      REQUIRE(r.ok());
      CHECK(r->report.stopped);
      CHECK(r->report.svm.curve.size() == 4);
      CHECK(seen == std::vector<int>{1, 2, 3});
      CHECK_FALSE(r->model.empty());
      CHECK(r->report.svm.test_accuracy > 0.5);
    }
  }
  GIVEN("a flag already raised") {
    std::atomic<bool> stop{true};
    auto r = algo::train_recogniser(*split, p, {}, &stop);
    THEN("there is nothing to keep: a clear error") {
      REQUIRE_FALSE(r.ok());
      CHECK(r.error().message.find("stopped before") != std::string::npos);
    }
  }
}

SCENARIO("kNN and the MLP run in the same frame and beat chance", "[training]") {
  GIVEN("4 classes and a --compare run with small budgets") {
    auto split = algo::split_per_class(make_clusters(4, 30, 10), 20, 2);
    REQUIRE(split.ok());
    algo::TrainParams p = small_params();
    p.compare = true;
    p.annealing.iterations = 4;
    p.knn_iterations = 4;
    p.mlp_iterations = 1;
    p.mlp_layouts = {{8}, {8, 4}};
    p.mlp.epochs = 60;
    auto r = algo::train_recogniser(*split, p);
    REQUIRE(r.ok());
    THEN("all three report accuracies well above the 25 % of chance, with confusion matrices") {
      REQUIRE(r->report.knn.has_value());
      REQUIRE(r->report.mlp.has_value());
      for (const algo::ClassifierReport* c : {&r->report.svm, &*r->report.knn, &*r->report.mlp}) {
        INFO(algo::to_string(c->classifier) << ": " << c->parameters << " test " << c->test_accuracy);
        CHECK(c->test_accuracy > 0.6);
        CHECK(c->cv_accuracy > 0.5);
        REQUIRE(c->confusion.size() == 4);
        int total = 0;
        for (const auto& row : c->confusion) {
          for (int v : row) total += v;
        }
        CHECK(total == r->report.test_samples);
        CHECK_FALSE(c->features.empty());
      }
    }
  }
}

SCENARIO("knn_classify votes by hand-checkable rules", "[training]") {
  // 1-D points: class 0 at 0.0 and 0.1, class 1 at 1.0, 1.1 and 1.2.
  const std::vector<double> rows = {0.0, 0.1, 1.0, 1.1, 1.2};
  const std::vector<int> labels = {0, 0, 1, 1, 1};
  const std::vector<double> x = {0.4};
  CHECK(algo::knn_classify(rows, labels, 1, 2, 1, x) == 0);  // nearest is 0.1
  CHECK(algo::knn_classify(rows, labels, 1, 2, 3, x) == 0);  // 0.1, 0.0, 1.0 -> two votes for 0
  CHECK(algo::knn_classify(rows, labels, 1, 2, 5, x) == 1);  // everyone: three votes for 1
  // A 2-2 tie at k = 4 goes to the class with the nearest member (0.1 -> class 0).
  CHECK(algo::knn_classify(rows, labels, 1, 2, 4, x) == 0);
}

SCENARIO("The scaler maps the training range onto [-1, 1] and compresses heavy-tailed features", "[svm]") {
  std::vector<FeatureVector> samples(3);
  for (std::size_t i = 0; i < 3; ++i) samples[i].fill(0.0F);
  samples[0][algo::kWidthIndex] = 0.4F;
  samples[1][algo::kWidthIndex] = 0.5F;
  samples[2][algo::kWidthIndex] = 0.6F;
  samples[0][algo::kHuIndex + 4] = 1e-12F;  // hu5: heavy-tailed
  samples[1][algo::kHuIndex + 4] = -2e-12F;
  samples[2][algo::kHuIndex + 4] = 5e-9F;
  const algo::Scaler s = algo::Scaler::fit(samples);
  CHECK(s.scale(algo::kWidthIndex, 0.4) == Approx(-1.0));
  CHECK(s.scale(algo::kWidthIndex, 0.5) == Approx(0.0).margin(1e-6));  // 0.5F sits mid-way to float precision
  CHECK(s.scale(algo::kWidthIndex, 0.6) == Approx(1.0));
  CHECK(s.scale(algo::kWidthIndex, 5.0) == Approx(algo::Scaler::kClip));  // far outside: clipped
  CHECK(s.scale(algo::kAreaIndex, 1.0) == 0.0);                           // constant in training
  // asinh(v / median|v|) keeps the two small values apart instead of squashing them against the large one.
  const double small_a = s.scale(algo::kHuIndex + 4, 1e-12), small_b = s.scale(algo::kHuIndex + 4, -2e-12);
  CHECK(s.scale(algo::kHuIndex + 4, 5e-9) == Approx(1.0));
  CHECK(small_b == Approx(-1.0));
  CHECK(small_a - small_b > 0.25);  // without compression: 0.001
}

SCENARIO("The scaler's fit leaves out NaN and infinite feature values", "[svm]") {
  GIVEN("samples with NaN and infinities among finite values, a NaN first") {
    constexpr float kNaN = std::numeric_limits<float>::quiet_NaN(), kInf = std::numeric_limits<float>::infinity();
    std::vector<FeatureVector> samples(7);
    for (FeatureVector& f : samples) f.fill(0.0F);
    const float width[] = {kNaN, 0.4F, kInf, 0.5F, 0.6F, -kInf, kNaN};
    // Heavy-tailed (Hu I5, I6): compressed by the median |v| of the finite values, the (n/2)-th smallest of n.
    const float hu5[] = {kNaN, 1e-12F, -kInf, -2e-12F, 5e-9F, kNaN, kNaN};    // finite 1, 2, 5000 (e-12): 2e-12
    const float hu6[] = {6e-12F, 5e-12F, kNaN, kNaN, kNaN, -2e-12F, 1e-12F};  // finite 1, 2, 5, 6 (e-12): 5e-12
    for (std::size_t i = 0; i < samples.size(); ++i) {
      samples[i][algo::kWidthIndex] = width[i];
      samples[i][algo::kHuIndex + 4] = hu5[i];
      samples[i][algo::kHuIndex + 5] = hu6[i];
      samples[i][algo::kAreaIndex] = kNaN;  // no finite value at all
    }
    WHEN("the scaler is fitted") {
      const algo::Scaler s = algo::Scaler::fit(samples);
      THEN("each range and compression is that of the finite values alone, and a feature without any is constant") {
        CHECK(s.ranges()[algo::kWidthIndex].lo == Approx(0.4));
        CHECK(s.ranges()[algo::kWidthIndex].hi == Approx(0.6));
        CHECK(s.scale(algo::kWidthIndex, 0.4) == Approx(-1.0));
        CHECK(s.scale(algo::kWidthIndex, 0.6) == Approx(1.0));
        CHECK(s.ranges()[algo::kHuIndex + 4].compress == Approx(2e-12).epsilon(1e-6));
        CHECK(s.scale(algo::kHuIndex + 4, -2e-12) == Approx(-1.0));
        CHECK(s.scale(algo::kHuIndex + 4, 5e-9) == Approx(1.0));
        CHECK(s.ranges()[algo::kHuIndex + 5].compress == Approx(5e-12).epsilon(1e-6));
        CHECK(s.scale(algo::kAreaIndex, 1.0) == 0.0);
      }
    }
  }
  GIVEN("a training set with one NaN feature") {
    algo::Dataset d = make_clusters(3, 10, 6);
    d.features[7][algo::kWidthIndex] = std::numeric_limits<float>::quiet_NaN();
    THEN("training refuses it before any scaling, naming the sample") {
      const Status valid = algo::validate_dataset(d);
      REQUIRE_FALSE(valid.ok());
      CHECK(valid.error().message == "dataset: sample 7 has a non-finite feature");
    }
  }
}

SCENARIO("The held-back test reports the top-2 rate and the calibration of the SVM's probabilities", "[training]") {
  GIVEN("4 overlapping classes (some test scans are confused)") {
    auto split = algo::split_per_class(make_clusters(4, 30, 6, kInformative, 3.0), 20, 2);
    REQUIRE(split.ok());
    algo::TrainParams p = small_params();
    p.annealing.iterations = 5;
    WHEN("the recogniser is trained") {
      auto r = algo::train_recogniser(*split, p);
      REQUIRE(r.ok());
      const algo::ClassifierReport& svm = r->report.svm;
      THEN("top-2 is at least top-1, the bins hold every test scan, and the ECE is their weighted gap") {
        CHECK(svm.test_top2 >= svm.test_accuracy);
        int scans = 0;
        double ece = 0.0, right = 0.0;
        for (const algo::CalibrationBin& b : svm.reliability) {
          CHECK(b.mean_probability >= b.lo);
          CHECK(b.mean_probability <= b.hi);
          scans += b.scans;
          ece += b.scans * std::abs(b.mean_probability - b.accuracy);
          right += b.scans * b.accuracy;
        }
        CHECK(scans == static_cast<int>(split->test.size()));
        CHECK(svm.test_ece == Approx(ece / scans));
        CHECK(right / scans == Approx(svm.test_accuracy));
      }
    }
  }
}

namespace {

// make_clusters with class `twin` replaced by near copies of class `of`'s samples (a near twin: its centroid lies
// far closer to `of` than any two other classes' do).
algo::Dataset with_near_twin(int classes, int per_class, int twin, int of) {
  algo::Dataset d = make_clusters(classes, per_class, 21);
  std::mt19937_64 rng(3);
  std::normal_distribution<float> g(0.0F, 0.05F);
  std::vector<FeatureVector> originals;
  for (std::size_t i = 0; i < d.size(); ++i) {
    if (d.labels[i] == of) originals.push_back(d.features[i]);
  }
  std::size_t k = 0;
  for (std::size_t i = 0; i < d.size(); ++i) {
    if (d.labels[i] != twin) continue;
    d.features[i] = originals[k++ % originals.size()];
    for (float& v : d.features[i]) v += g(rng);
  }
  return d;
}

}  // namespace

SCENARIO("The search's class subset holds the near twins and is deterministic", "[training]") {
  GIVEN("12 classes where class 11 is a near twin of class 3") {
    const algo::Dataset d = with_near_twin(12, 6, 11, 3);
    WHEN("a subset of 4 classes is chosen, twice") {
      const std::vector<int> a = algo::search_class_subset(d, 4);
      const std::vector<int> b = algo::search_class_subset(d, 4);
      THEN("it has 4 classes in ascending order, both twins among them, the same both times") {
        REQUIRE(a.size() == 4);
        CHECK(std::is_sorted(a.begin(), a.end()));
        CHECK(std::find(a.begin(), a.end(), 3) != a.end());
        CHECK(std::find(a.begin(), a.end(), 11) != a.end());
        CHECK(a == b);
      }
    }
    THEN("no subset when every class fits or the limit is 0 (all)") {
      CHECK(algo::search_class_subset(d, 12).empty());
      CHECK(algo::search_class_subset(d, 0).empty());
    }
  }
}

SCENARIO("With many classes the annealing searches on the subset and the model still knows every class", "[training]") {
  GIVEN("8 classes (class 7 a near twin of class 2) and search_classes 4, on 1 and on 2 threads") {
    auto split = algo::split_per_class(with_near_twin(8, 9, 7, 2), 6, 1);
    REQUIRE(split.ok());
    algo::TrainParams p = small_params();
    p.annealing.iterations = 4;
    p.search_classes = 4;
    p.threads = 1;
    auto [ra, rb] = train_twice(*split, p, [](algo::TrainParams& q) { q.threads = 2; });
    algo::TrainingResult* a = &ra;
    const algo::TrainingResult* b = &rb;
    THEN("the report names 4 searched classes with both twins, the model predicts over all 8, deterministically") {
      const std::vector<std::string>& names = a->report.search_class_names;
      REQUIRE(names.size() == 4);
      CHECK(std::find(names.begin(), names.end(), "class_2") != names.end());
      CHECK(std::find(names.begin(), names.end(), "class_7") != names.end());
      CHECK(a->report.search_samples == 4 * 6);
      CHECK(a->model.predict(split->test.features[0]).size() == 8);
      CHECK(a->report.svm.confusion.size() == 8);
      CHECK(algo::search_scope_text(a->report).find("4 of 8 classes") != std::string::npos);
      CHECK(a->model.serialize() == b->model.serialize());
    }
  }
}

SCENARIO("A catalogue within search_classes trains exactly as the thesis search on all classes", "[training]") {
  GIVEN("3 classes, trained with search_classes 3 and with 0 (all)") {
    algo::TrainParams within = small_params();
    within.search_classes = 3;
    const auto split = algo::split_per_class(make_clusters(3, 18, 8), 12, 1);
    REQUIRE(split.ok());
    const auto [a, b] = train_twice(*split, within, [](algo::TrainParams& q) { q.search_classes = 0; });
    THEN("no subset is reported and the models are byte-identical") {
      CHECK(a.report.search_class_names.empty());
      CHECK(algo::search_scope_text(a.report).empty());
      CHECK(a.model.serialize() == b.model.serialize());
    }
  }
}
