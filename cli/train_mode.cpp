// `cellsight train`: dataset from the taught scans, training (algo/training), thresholds, atomic database update.
#include "cli/train_mode.hpp"

#include <algorithm>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <mutex>
#include <optional>
#include <set>

#include "algo/augment.hpp"
#include "algo/cascade.hpp"
#include "algo/splitmix.hpp"
#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "app/train_progress.hpp"
#include "app/train_report.hpp"
#include "base/atomic_file.hpp"
#include "base/crc32.hpp"
#include "base/file_read.hpp"
#include "base/local_time.hpp"
#include "base/parallel_for.hpp"
#include "cli/cli.hpp"
#include "cli/mode_args.hpp"
#include "drivers/log.hpp"
#include "formats/calibration_file.hpp"
#include "formats/ply.hpp"

namespace cellsight::cli {
namespace {

std::atomic<bool> g_stop{false};  // set by SIGINT/SIGTERM while training: keep the best so far

extern "C" void on_train_stop_signal(int /*signal*/) {
  g_stop.store(true);
}

// SIGINT/SIGTERM -> g_stop for the lifetime of the object; the previous handlers come back afterwards.
class StopOnSignal {
 public:
  StopOnSignal() {
    g_stop.store(false);
    struct sigaction sa {};
    sa.sa_handler = on_train_stop_signal;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGINT, &sa, &old_int_);
    sigaction(SIGTERM, &sa, &old_term_);
  }
  ~StopOnSignal() {
    sigaction(SIGINT, &old_int_, nullptr);
    sigaction(SIGTERM, &old_term_, nullptr);
  }
  StopOnSignal(const StopOnSignal&) = delete;
  StopOnSignal& operator=(const StopOnSignal&) = delete;

 private:
  struct sigaction old_int_ {};
  struct sigaction old_term_ {};
};

std::size_t max_scan_points(const app::Config& config) {
  return app::scan_builder_params(config).max_points;
}

// Seed of variant v of taught scan `scan`: reproducible for svm.seed, different for every scan and variant.
std::uint64_t augment_seed(const app::Config& config, std::size_t scan, int variant) {
  return algo::stream_seed(algo::stream_seed(static_cast<std::uint64_t>(config.svm.seed), scan),
                           static_cast<std::uint64_t>(variant));
}

// What a thread of build_dataset keeps from one scan to the next (built on that thread, at its first scan).
struct FeatureWorker {
  FeatureWorker(const app::Config& config, const algo::Plane& support, bool with_cascade)
      : preparer(config, support, max_scan_points(config)) {
    if (with_cascade)
      cascade.emplace(app::cascade_params(config), app::perfect_match_params(config), app::grid_spec(config));
  }
  app::ScanPreparer preparer;
  std::vector<algo::ScanPoint> origin, variant;
  std::optional<algo::Cascade> cascade;
};

// ... and a thread of cross_matches.
struct MatchWorker {
  MatchWorker(const app::Config& config, const algo::Plane& support)
      : preparer(config, support, max_scan_points(config)),
        cascade(app::cascade_params(config), app::perfect_match_params(config), app::grid_spec(config)) {}
  app::ScanPreparer preparer;
  algo::Cascade cascade;
};

}  // namespace

Expected<std::vector<algo::ScanPoint>> load_taught_scan(const app::ModelDb& db, const formats::ScanEntry& scan) {
  const std::string path = db.path_of(scan.file);
  auto bytes = base::read_file(path, app::kMaxTaughtScanBytes);
  if (!bytes) return bytes.error();
  const std::uint32_t crc = base::crc32(*bytes);
  if (crc != scan.crc32) {
    return make_error(path +
                      ": checksum differs from the manifest: the scan was changed or damaged; delete the "
                      "part ('cellsight parts delete') and teach it again");
  }
  auto points = app::parse_taught_scan(*bytes);
  if (!points) return make_error(path + ": " + points.error().message);
  return points;
}

Expected<TaughtData> build_dataset(const app::Config& config, const app::ModelDb& db, const algo::Plane& support,
                                   int threads, const std::atomic<bool>* stop, const app::LoadedTemplates* templates,
                                   app::ProgressLines* progress) {
  const formats::Manifest& m = db.manifest();
  struct Job {
    int label;
    const formats::ScanEntry* scan;
  };
  std::vector<Job> jobs;
  TaughtData out;
  algo::Dataset& data = out.data;
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    data.classes.push_back({m.parts[c].name, m.parts[c].id});
    for (const formats::ScanEntry& s : m.parts[c].scans) jobs.push_back({static_cast<int>(c), &s});
  }
  // Features of every taught scan and of its synthetic variants (svm.augment_per_scan; algo/augment), by job.
  const int variants = config.svm.augment_per_scan;
  std::vector<std::vector<algo::FeatureVector>> job_features(jobs.size());
  std::vector<algo::MatchReport> matches(templates != nullptr ? jobs.size() : 0);
  std::mutex mutex;
  std::string first_error;
  std::atomic<std::size_t> done{0};
  const bool with_cascade = templates != nullptr;
  const bool complete = base::parallel_for_with_state<FeatureWorker>(
      static_cast<int>(jobs.size()), std::max(1, threads), stop,
      [&](int job, FeatureWorker& w) {
        const auto i = static_cast<std::size_t>(job);
        auto points = load_taught_scan(db, *jobs[i].scan);
        std::string error;
        if (!points) {
          error = points.error().message;
        } else {
          const app::PrepareReport r = w.preparer.prepare(*points);
          if (r.status != app::PrepareStatus::kOk) {
            error =
                db.path_of(jobs[i].scan->file) + ": " + std::string(to_string(r.status)) + " (" + r.describe() + ")";
          } else {
            job_features[i].push_back(w.preparer.features());
            if (w.cascade) {
              matches[i] = w.cascade->evaluate_own(templates->models[static_cast<std::size_t>(jobs[i].label)],
                                                   w.preparer.part_points());
            }
            const std::span<const algo::ScanPoint> part = w.preparer.part_points();
            w.origin.assign(part.begin(), part.end());
            for (int v = 1; v <= variants; ++v) {
              algo::augment_scan(w.origin, algo::AugmentParams{}, augment_seed(config, i, v), w.variant);
              if (w.preparer.prepare_part(w.variant).status == app::PrepareStatus::kOk)
                job_features[i].push_back(w.preparer.features());  // a variant that lost the part is left out
            }
          }
        }
        if (!error.empty()) {
          const std::lock_guard<std::mutex> lock(mutex);
          if (first_error.empty()) first_error = error;
          return false;
        }
        const std::size_t n = ++done;
        if (progress != nullptr) progress->step(app::TrainPhase::kFeatures, n, jobs.size());
        if (n % 50 == 0 || n == jobs.size()) CS_LOG_INFO("train", "features of %zu / %zu scans", n, jobs.size());
        return true;
      },
      config, support, with_cascade);
  if (!first_error.empty()) return make_error(first_error);
  if (!complete || (stop != nullptr && stop->load())) {
    return make_error("stopped before the features of every scan were computed");
  }
  for (std::size_t i = 0; i < jobs.size(); ++i) {
    for (std::size_t v = 0; v < job_features[i].size(); ++v)
      data.push(job_features[i][v], jobs[i].label, static_cast<int>(i), static_cast<int>(v));
  }
  if (templates != nullptr) {
    out.own_matches.resize(data.classes.size());
    for (std::size_t i = 0; i < jobs.size(); ++i) {
      out.own_matches[static_cast<std::size_t>(jobs[i].label)].push_back(matches[i]);
    }
  }
  return out;
}

namespace {

// The other classes' scans that could reach a template's verification, and what they scored against it.
struct CrossMatches {
  std::vector<std::vector<algo::MatchReport>> reports;  // [class c]: scans of other classes against c's template
  std::vector<std::vector<std::size_t>> from;           // [class c][k]: the class of the scan of reports[c][k]
};

// A taught scan is matched against the templates of the classes its SVM ranks highest: this many at least, and
// twice cascade.pm_candidates (taught scans sit closer to the model than tomorrow's scans do, hence the margin).
constexpr int kMinCrossRivals = 8;
constexpr int kCrossRivalsPerCandidate = 2;

// Per taught scan (manifest order): the classes whose templates it is matched against. At run time a scan is
// verified only against the SVM's most probable pm_candidates and the passing class's look-alikes (algo/cascade),
// so a template's thresholds need a margin only to scans that can reach its verification: the classes the
// just-trained SVM ranks in the scan's top N, its own class left out. Look-alikes are learnt from these same
// matches, so they stay within that reach too. With N >= classes - 1 (small catalogues) every other template,
// as before issue 11; at 300 parts this turns 3600 x 299 Perfect Match evaluations (~1.5 h) into 3600 x N.
std::vector<std::vector<std::size_t>> cross_match_rivals(const app::Config& config, const TaughtData& taught,
                                                         algo::SvmModel& model) {
  const algo::Dataset& data = taught.data;
  const std::size_t classes = data.classes.size();
  const auto reach = static_cast<std::size_t>(
      std::max(kMinCrossRivals, kCrossRivalsPerCandidate * app::cascade_params(config).pm_candidates));
  std::vector<std::vector<std::size_t>> rivals;
  for (std::size_t i = 0; i < data.size(); ++i) {
    if (data.variant_of(i) != 0) continue;  // groups are the scans in manifest order, the taught scan first
    const auto own = static_cast<std::size_t>(data.labels[i]);
    std::vector<std::size_t>& r = rivals.emplace_back();
    // In the SVM's rank order: the first ones are the scan's closest rivals, matched as decide() matches its
    // first-ranked candidates (cross_matches).
    for (const algo::ClassProbability& p : model.predict(data.features[i])) {
      if (r.size() == reach || r.size() + 1 == classes) break;
      if (static_cast<std::size_t>(p.class_index) != own) r.push_back(static_cast<std::size_t>(p.class_index));
    }
  }
  return rivals;
}

// The taught scans against the templates of their rivals (the runner-ups learn_thresholds() keeps a margin to).
// rivals[j]: the classes scan j (manifest order) is matched against. own_limits[c]: template c's limits from its own
// scans alone (learn_thresholds without rivals), an upper bound of the learnt ones: a rival that fails them by far
// at Perfect Match's pose is not retried at the outline pose (Cascade::evaluate). Runs on `threads` threads.
Expected<CrossMatches> cross_matches(const app::Config& config, const app::ModelDb& db, const algo::Plane& support,
                                     int threads, const app::LoadedTemplates& templates,
                                     const std::vector<std::vector<std::size_t>>& rivals,
                                     std::span<const algo::TemplateThresholds> own_limits,
                                     const std::atomic<bool>* stop, app::ProgressLines& progress) {
  const formats::Manifest& m = db.manifest();
  struct Job {
    std::size_t label;
    const formats::ScanEntry* scan;
  };
  std::vector<Job> jobs;
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    for (const formats::ScanEntry& s : m.parts[c].scans) jobs.push_back({c, &s});
  }
  const std::size_t classes = m.parts.size();
  if (rivals.size() != jobs.size() || own_limits.size() != classes) {
    return make_error("the rivals or the own-class limits do not match the taught parts and scans");
  }
  // reports[j][k]: scan j against the template of rivals[j][k].
  std::vector<std::vector<algo::MatchReport>> reports(jobs.size());
  std::mutex mutex;
  std::string first_error;
  std::atomic<std::size_t> done{0};
  const bool complete = base::parallel_for_with_state<MatchWorker>(
      static_cast<int>(jobs.size()), std::max(1, threads), stop,
      [&](int job, MatchWorker& w) {
        const auto i = static_cast<std::size_t>(job);
        auto points = load_taught_scan(db, *jobs[i].scan);
        if (!points || w.preparer.prepare(*points).status != app::PrepareStatus::kOk) {
          const std::lock_guard<std::mutex> lock(mutex);
          if (first_error.empty()) first_error = db.path_of(jobs[i].scan->file) + ": cannot be prepared";
          return false;
        }
        reports[i].resize(rivals[i].size());
        w.cascade.set_scan(w.preparer.part_points());  // once for all of this scan's rivals
        for (std::size_t k = 0; k < rivals[i].size(); ++k) {
          const std::size_t c = rivals[i][k];
          if (templates.models[c].map.valid()) {
            // The closest rivals (Cascade::kFirstRanked) without the gross-failure shortcut, as decide() checks
            // its first-ranked candidates: were the scan ranked so there, its figures must be the ones learnt here.
            reports[i][k] = w.cascade.evaluate_prepared(templates.models[c], w.preparer.part_points(),
                                                        k < algo::Cascade::kFirstRanked ? nullptr : &own_limits[c]);
          }
        }
        const std::size_t n = ++done;
        progress.step(app::TrainPhase::kThresholds, n, jobs.size());
        if (n % 200 == 0 || n == jobs.size())
          CS_LOG_INFO("train", "rivals matched for %zu / %zu scans", n, jobs.size());
        return true;
      },
      config, support);
  if (!first_error.empty()) return make_error(first_error);
  if (!complete || (stop != nullptr && stop->load())) return make_error("stopped");
  CrossMatches out;
  out.reports.resize(classes);
  out.from.resize(classes);
  for (std::size_t i = 0; i < jobs.size(); ++i) {
    for (std::size_t k = 0; k < rivals[i].size(); ++k) {
      const std::size_t c = rivals[i][k];
      if (!templates.models[c].map.valid()) continue;
      out.reports[c].push_back(reports[i][k]);
      out.from[c].push_back(jobs[i].label);
    }
  }
  return out;
}

// A refusal of `cellsight train`: the exit code and the message printed after "cellsight train: ".
struct TrainFailure {
  int code = kExitUsage;
  std::string message;
};

int report_failure(const TrainFailure& failure) {
  std::fprintf(stderr, "cellsight train: %s\n", failure.message.c_str());
  return failure.code;
}

// The training parameters: the configuration's, then --iterations, --seed and --compare.
std::optional<TrainFailure> read_train_params(const ModeArgs& args, const app::Config& config,
                                              algo::TrainParams& params) {
  params.annealing.start_temperature = config.svm.sa_start_temperature;
  params.annealing.cooling_ratio = config.svm.sa_cooling_ratio;
  params.annealing.iterations = config.svm.sa_iterations;
  params.folds = config.svm.folds;
  params.seed = static_cast<std::uint64_t>(config.svm.seed);
  params.threads = config.svm.threads;
  params.search_variants = config.svm.augment_search_per_scan;
  params.search_classes = config.svm.search_classes;
  params.kernel = config.svm.kernel == "poly" ? algo::KernelType::kPoly : algo::KernelType::kRbf;
  params.compare = args.has("--compare");
  if (const std::string* v = args.value("--iterations")) {
    std::int64_t n = 0;
    if (!parse_whole(*v, 0, 100000, n))
      return TrainFailure{kExitUsage, "--iterations '" + *v + "': expected 0..100000"};
    params.annealing.iterations = static_cast<int>(n);
  }
  if (const std::string* v = args.value("--seed")) {
    std::int64_t n = 0;
    if (!parse_whole(*v, 0, INT64_MAX, n))
      return TrainFailure{kExitUsage, "--seed '" + *v + "': expected a whole number"};
    params.seed = static_cast<std::uint64_t>(n);
  }
  return std::nullopt;
}

// Training scans per part: train_fraction of the fewest scans any part has. Refuses a database that cannot be
// trained (fewer than two parts, a part with too few scans) before hours of work start, and lowers the folds to
// the training scans when they are fewer.
Expected<int> train_scans_per_part(const formats::Manifest& m, const app::Config& config, const std::string& models_dir,
                                   algo::TrainParams& params) {
  if (m.parts.size() < 2) {
    return make_error("the database " + models_dir + " has " + std::to_string(m.parts.size()) +
                      " part(s); the SVM needs at least two taught parts");
  }
  // A part taught with few scans (5 is a normal first teach) lowers the folds to its training scans rather than
  // being refused: cross-validation needs at least two, and one scan must stay back for the test.
  constexpr int kMinFolds = 2;
  int min_scans = INT32_MAX;
  for (const formats::PartEntry& p : m.parts) {
    const int n = static_cast<int>(p.scans.size());
    const int train_n = static_cast<int>(std::lround(config.svm.train_fraction * n));
    if (train_n < kMinFolds || n - train_n < 1) {
      int need = kMinFolds + 1;
      while (static_cast<int>(std::lround(config.svm.train_fraction * need)) < kMinFolds ||
             need - static_cast<int>(std::lround(config.svm.train_fraction * need)) < 1) {
        ++need;
      }
      return make_error("part '" + p.name + "' has " + std::to_string(n) + " scans: with train_fraction " +
                        std::to_string(config.svm.train_fraction) + " it needs at least " + std::to_string(need) +
                        " (two for cross-validation, one held back for the test; " +
                        "teach more: cellsight teach --part " + p.name + " ...)");
    }
    min_scans = std::min(min_scans, n);
  }
  const int train_per_class = static_cast<int>(std::lround(config.svm.train_fraction * min_scans));
  if (train_per_class < params.folds) {
    std::printf(
        "note: %d-fold cross-validation instead of %d: the part with the fewest scans has %d for training "
        "(teach more scans for the configured folds)\n",
        train_per_class, params.folds, train_per_class);
    params.folds = train_per_class;
  }
  return train_per_class;
}

// What training learns for each part beside the SVM (manifest order).
struct LearntParts {
  std::vector<formats::PartThresholds> thresholds;
  std::vector<algo::TemplateThresholds> template_thresholds;
  std::vector<std::vector<std::string>> flagged;  // taught scans that disagree with the part's others
  std::vector<std::set<std::string>> confusable;  // look-alikes verified with the part
};

// Acceptance thresholds of every template from its own taught scans that agree with each other, with a margin to
// the other parts' scans (the unknown-part decision, algo/cascade); warns about scans that disagree.
void learn_part_thresholds(const formats::Manifest& m, const app::Config& config, const TaughtData& taught,
                           const CrossMatches& others, LearntParts& learnt_parts) {
  learnt_parts.flagged.assign(m.parts.size(), {});
  for (std::size_t c = 0; c < taught.own_matches.size(); ++c) {
    const algo::ThresholdLearning learnt =
        algo::learn_thresholds(taught.own_matches[c], others.reports[c], app::cascade_params(config));
    const algo::TemplateThresholds& t = learnt.thresholds;
    learnt_parts.template_thresholds.push_back(t);
    learnt_parts.thresholds.push_back(app::part_thresholds(t, true));
    const formats::PartEntry& part = m.parts[c];
    for (const int i : learnt.flagged) {
      learnt_parts.flagged[c].push_back(part.scans[static_cast<std::size_t>(i)].file);
      const algo::MatchReport& r = taught.own_matches[c][static_cast<std::size_t>(i)];
      std::printf(
          "warning: %s: taught scan %s disagrees with the other scans of the part (PM error %.3g, missing "
          "%.0f mm2, extra %.0f mm2): it does not widen the thresholds; check it (glare, a stray part, the "
          "wrong part?)\n",
          part.name.c_str(), part.scans[static_cast<std::size_t>(i)].file.c_str(), r.pm.error, r.missing_area_m2 * 1e6,
          r.extra_area_m2 * 1e6);
    }
    if (learnt.other_scans_inseparable > 0) {
      std::printf(
          "warning: %s: %d scans of other parts cannot be told from it by any gate: those parts may be "
          "reported as %s; teach more scans or check the parts differ\n",
          part.name.c_str(), learnt.other_scans_inseparable, part.name.c_str());
    }
  }
}

// Look-alikes: a part whose scans came within kNearPassFactor of passing another's template (either way round) is
// verified with it at run time (algo::CascadeParams, candidate policy).
void find_look_alikes(const formats::Manifest& m, const CrossMatches& others, LearntParts& learnt_parts) {
  constexpr double kNearPassFactor = 3.0;
  std::vector<std::set<std::string>>& confusable = learnt_parts.confusable;
  confusable.assign(m.parts.size(), {});
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    for (std::size_t k = 0; k < others.reports[c].size(); ++k) {
      if (algo::near_pass(others.reports[c][k], learnt_parts.template_thresholds[c], kNearPassFactor)) {
        const std::size_t o = others.from[c][k];
        confusable[c].insert(m.parts[o].name);
        confusable[o].insert(m.parts[c].name);
      }
    }
  }
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    if (confusable[c].empty()) continue;
    std::string list;
    for (const std::string& n : confusable[c]) list += (list.empty() ? "" : ", ") + n;
    std::printf("%s: look-alikes verified with it: %s\n", m.parts[c].name.c_str(), list.c_str());
  }
}

// Atomic update: the new model under a new name, then the manifest that points at it, then the old one goes.
// Returns the model's file name (relative to the database).
Expected<std::string> store_trained_model(app::ModelDb& db, const algo::TrainingResult& trained,
                                          const LearntParts& learnt_parts) {
  const algo::TrainingReport& report = trained.report;
  const std::string model_file = "svm-" + base::local_time_text().substr(0, 10) + "-" +
                                 std::to_string(static_cast<long long>(std::time(nullptr))) + ".model";
  const std::string blob = trained.model.serialize();
  if (auto ok = base::write_file_atomic(db.path_of(model_file), blob); !ok) return ok.error();
  const std::string old_model = db.manifest().svm.present ? db.manifest().svm.file : "";
  formats::Manifest& mm = db.manifest();
  mm.feature_version = algo::kFeatureVersion;
  mm.learn_version = algo::kLearnVersion;
  mm.svm.present = true;
  mm.svm.file = model_file;
  mm.svm.crc32 = base::crc32(blob);
  mm.svm.trained_at = base::local_time_text();
  mm.svm.parts_fingerprint = db.parts_fingerprint();
  mm.svm.test_accuracy = report.svm.test_accuracy;
  mm.svm.cv_accuracy = report.svm.cv_accuracy;
  mm.svm.train_scans = report.train_samples;
  mm.svm.test_scans = report.test_samples;
  mm.svm.active_features = trained.model.active_features();
  mm.svm.hyper = report.svm.parameters;
  for (std::size_t c = 0; c < mm.parts.size(); ++c) {
    mm.parts[c].thresholds = learnt_parts.thresholds[c];
    mm.parts[c].confusable.assign(learnt_parts.confusable[c].begin(), learnt_parts.confusable[c].end());
    mm.parts[c].flagged = learnt_parts.flagged[c];
  }
  if (auto ok = db.save(); !ok) {
    std::error_code ec;
    std::filesystem::remove(db.path_of(model_file), ec);
    return make_error(ok.error().message + " (the database is unchanged)");
  }
  if (!old_model.empty() && old_model != model_file) {
    std::error_code ec;
    std::filesystem::remove(db.path_of(old_model), ec);
  }
  return model_file;
}

void print_training_result(const algo::TrainingResult& trained, const std::string& model_path) {
  const algo::TrainingReport& report = trained.report;
  std::printf("SVM: %.2f %% on the %d held-back test scans (%d-fold CV %.2f %%), %d of %d features, %s\n",
              report.svm.test_accuracy * 100.0, report.test_samples, report.folds, report.svm.cv_accuracy * 100.0,
              trained.model.active_features(), algo::kFeatureCount, report.svm.parameters.c_str());
  if (report.knn) {
    std::printf("kNN: %.2f %% test (CV %.2f %%), %s\n", report.knn->test_accuracy * 100.0,
                report.knn->cv_accuracy * 100.0, report.knn->parameters.c_str());
  }
  if (report.mlp) {
    std::printf("MLP: %.2f %% test (CV %.2f %%), %s\n", report.mlp->test_accuracy * 100.0,
                report.mlp->cv_accuracy * 100.0, report.mlp->parameters.c_str());
  }
  if (const std::string scope = algo::search_scope_text(report); !scope.empty()) std::printf("%s\n", scope.c_str());
  std::printf("model -> %s (%.1f s)\n", model_path.c_str(), report.seconds);
}

}  // namespace

int run_train(const std::vector<std::string>& words, const app::Config& config, const std::string& models_dir) {
  ModeArgs args;
  std::string error;
  if (!parse_mode_args(words, {"--report", "--calibration", "--iterations", "--seed"}, {"--compare", "--progress"},
                       args, error) ||
      !args.positional.empty()) {
    std::fprintf(stderr, "cellsight train: %s\n",
                 error.empty() ? ("unexpected argument '" + args.positional.front() + "'").c_str() : error.c_str());
    return kExitUsage;
  }
  auto db = app::ModelDb::open_for_writing(models_dir, app::grid_spec(config), false);
  if (!db) return report_failure({kExitUsage, db.error().message});
  const formats::Manifest& m = db->manifest();

  algo::TrainParams params;
  if (auto refused = read_train_params(args, config, params)) return report_failure(*refused);
  auto train_per_class = train_scans_per_part(m, config, models_dir, params);
  if (!train_per_class) return report_failure({kExitUsage, train_per_class.error().message});

  const std::string* calibration_arg = args.value("--calibration");
  auto support = app::load_support_plane(calibration_arg ? *calibration_arg : app::default_calibration_path(config));
  if (!support) return report_failure({kExitUsage, support.error().message});

  StopOnSignal stop_on_signal;
  const int threads = config.svm.threads > 0 ? config.svm.threads : base::hardware_threads();
  std::printf(
      "computing the features of %zu taught scans of %zu parts...\n",
      [&] {
        std::size_t n = 0;
        for (const formats::PartEntry& p : m.parts) n += p.scans.size();
        return n;
      }(),
      m.parts.size());
  const app::LoadedTemplates templates = app::open_templates(config, *db);
  if (!templates.problems.empty()) {
    std::string all;
    for (const std::string& p : templates.problems) all += "\n  " + p;
    return report_failure({kExitUsage, "refused templates:" + all +
                                           "\n(delete the part with 'cellsight parts delete' and teach it again)"});
  }
  // --progress: "progress: F TEXT" lines for the operator's screen (app::ProgressLines), beside the usual output.
  app::ProgressLines progress(args.has("--progress") ? stdout : nullptr);
  auto taught = build_dataset(config, *db, *support, threads, &g_stop, &templates, &progress);
  if (!taught) return report_failure({kExitUsage, taught.error().message});
  auto split = algo::split_per_class(taught->data, *train_per_class, params.seed);
  if (!split) return report_failure({kExitUsage, split.error().message});

  app::ProgressPrinter printer = app::ProgressPrinter::for_stream(stdout);
  auto trained = algo::train_recogniser(
      *split, params,
      [&](const algo::TrainingProgress& p) {
        printer.update(p);
        progress.training(p);
      },
      &g_stop);
  printer.finish();
  if (!trained) return report_failure({kExitFailure, trained.error().message});
  const algo::TrainingReport& report = trained->report;
  if (report.stopped) std::printf("stopped: the model is trained on the best feature set found so far\n");

  const std::vector<std::vector<std::size_t>> rivals = cross_match_rivals(config, *taught, trained->model);
  std::printf(
      "learning the acceptance thresholds (every taught scan against the templates of its %zu most "
      "probable other parts)...\n",
      rivals.empty() ? std::size_t{0} : rivals.front().size());
  std::vector<algo::TemplateThresholds> own_limits;
  for (const std::vector<algo::MatchReport>& own : taught->own_matches)
    own_limits.push_back(algo::learn_thresholds(own, app::cascade_params(config)));
  auto others = cross_matches(config, *db, *support, threads, templates, rivals, own_limits, &g_stop, progress);
  if (!others) return report_failure({kExitFailure, "thresholds: " + others.error().message});
  LearntParts learnt_parts;
  learn_part_thresholds(m, config, *taught, *others, learnt_parts);
  find_look_alikes(m, *others, learnt_parts);

  auto model_file = store_trained_model(*db, *trained, learnt_parts);
  if (!model_file) return report_failure({kExitFailure, model_file.error().message});
  print_training_result(*trained, db->path_of(*model_file));
  if (const std::string* dir = args.value("--report")) {
    app::TrainReportContext context;
    context.model_db_path = db->path_of(*model_file);
    context.dataset = models_dir + ": " + std::to_string(m.parts.size()) + " taught parts, " +
                      std::to_string(taught->data.size()) + " scans";
    context.planned_iterations = params.annealing.iterations;
    auto written = app::write_training_report(*dir, report, context);
    if (!written) {
      return report_failure({kExitFailure, "the model is saved, but the report failed: " + written.error().message});
    }
    std::printf("report -> %s\n", written->c_str());
  }
  progress.finished("saved");
  return kExitOk;
}

}  // namespace cellsight::cli
