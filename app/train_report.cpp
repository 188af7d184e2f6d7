// The report of `cellsight train`: its summary text and the folder the whole report is written into.
#include "app/train_report.hpp"

#include <algorithm>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "app/train_report_plots.hpp"
#include "base/atomic_file.hpp"
#include "base/local_time.hpp"
#include "base/string_printf.hpp"

namespace cellsight::app {
namespace {

namespace fs = std::filesystem;

constexpr double kPercent = 100.0;
constexpr int kWorstConfusionsShown = 5;
constexpr double kOverfitGap = 0.03;  // CV above test by more than this: the model learned its training scans
constexpr std::size_t kWrapColumn = 100;
constexpr int kMaxSubfolderTries = 100;

// ---- text helpers -----------------------------------------------------------------------------------------------

using base::string_printf;

std::string percent_text(double fraction) {
  if (!std::isfinite(fraction)) return "n/a";
  return string_printf("%.1f %%", fraction * kPercent);
}

}  // namespace

std::string classifier_display_name(algo::Classifier classifier) {
  switch (classifier) {
    case algo::Classifier::kSvm: return "SVM";
    case algo::Classifier::kKnn: return "kNN";
    case algo::Classifier::kMlp: return "MLP";
  }
  return "?";
}

int active_feature_count(const algo::ClassifierReport& r) {
  return r.features.empty() ? static_cast<int>(r.mask.count()) : static_cast<int>(r.features.size());
}

std::vector<const algo::ClassifierReport*> report_classifiers(const algo::TrainingReport& report) {
  std::vector<const algo::ClassifierReport*> all = {&report.svm};
  if (report.knn) all.push_back(&*report.knn);
  if (report.mlp) all.push_back(&*report.mlp);
  return all;
}

std::string report_file_stem(const algo::ClassifierReport& r) {
  return std::string(algo::to_string(r.classifier));
}

namespace {

// "0.4 s", "12.3 s", "2 min 48 s", "1 h 05 min".
std::string human_duration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0.0) return "unknown";
  constexpr double kMinute = 60.0, kHour = 3600.0;
  if (seconds < kMinute) return string_printf("%.1f s", seconds);
  const auto whole = static_cast<long long>(seconds);
  if (seconds < kHour) return string_printf("%lld min %02lld s", whole / 60, whole % 60);
  return string_printf("%lld h %02lld min", whole / 3600, (whole % 3600) / 60);
}

// "2025-01-31 14:05:09" -> "report-2025-01-31_140509"
std::string subfolder_name(const std::string& date) {
  std::string name = "report-";
  for (char ch : date) {
    if ((ch >= '0' && ch <= '9') || ch == '-') {
      name += ch;
    } else if (ch == ' ' || ch == 'T') {
      name += '_';
    }
  }
  return name;
}

// Appends `words` wrapped at kWrapColumn, separated by spaces: the first line starts with `lead`, the others with as
// many spaces. Nothing when there are no words.
void append_words(std::string& out, const std::string& lead, const std::vector<std::string>& words) {
  const std::size_t start = lead.size();
  std::string line = lead;
  for (const std::string& word : words) {
    if (word.empty()) continue;
    if (line.size() > start && line.size() + 1 + word.size() > kWrapColumn) {
      out += line + "\n";
      line.assign(start, ' ');
    }
    if (line.size() > start) line += ' ';
    line += word;
  }
  if (line.size() > start) out += line + "\n";
}

// Appends `words` joined by ", " as lines no longer than kWrapColumn, each starting with `indent`.
void append_wrapped(std::string& out, const std::vector<std::string>& words, const std::string& indent) {
  std::vector<std::string> listed;
  listed.reserve(words.size());
  for (std::size_t i = 0; i < words.size(); ++i) listed.push_back(words[i] + (i + 1 < words.size() ? "," : ""));
  append_words(out, indent, listed);
}

int row_sum(const std::vector<int>& row) {
  int s = 0;
  for (int v : row) s += v;
  return s;
}

int trace(const std::vector<std::vector<int>>& confusion) {
  int s = 0;
  for (std::size_t i = 0; i < confusion.size(); ++i) s += i < confusion[i].size() ? confusion[i][i] : 0;
  return s;
}

Status validate_report(const algo::TrainingReport& report) {
  const std::size_t k = report.class_names.size();
  if (k == 0) return make_error("training report: no classes");
  for (const algo::ClassifierReport* r : report_classifiers(report)) {
    const std::string who = "training report (" + classifier_display_name(r->classifier) + "): ";
    if (r->confusion.size() != k) {
      return make_error(who + "the confusion matrix has " + std::to_string(r->confusion.size()) + " rows for " +
                        std::to_string(k) + " classes");
    }
    for (const auto& row : r->confusion) {
      if (row.size() != k) return make_error(who + "a confusion matrix row does not have one column per class");
      for (int v : row) {
        if (v < 0) return make_error(who + "negative count in the confusion matrix");
      }
    }
  }
  return {};
}

// ---- summary ------------------------------------------------------------------------------------------------------

std::string kernel_text(const algo::SvmHyper& h, int active) {
  const double gamma = active > 0 ? h.gamma(active) : std::numeric_limits<double>::quiet_NaN();
  if (h.kernel == algo::KernelType::kRbf) {
    return string_printf("RBF, C = %g, gamma = %.4g (i = %g over %d active features), degree: not used by RBF", h.c,
                         gamma, h.gamma_factor, active);
  }
  return string_printf("polynomial, degree = %d, C = %g, gamma = %.4g (i = %g over %d active features), coef0 = %g",
                       h.degree, h.c, gamma, h.gamma_factor, active, h.coef0);
}

std::string test_split_text(const algo::TrainingReport& report) {
  int lo = std::numeric_limits<int>::max(), hi = 0;
  for (const auto& row : report.svm.confusion) {
    lo = std::min(lo, row_sum(row));
    hi = std::max(hi, row_sum(row));
  }
  if (report.test_samples == 0 || report.svm.confusion.empty()) return "no scans held back for the test";
  if (lo == hi) return string_printf("%d held back for the test (%d per class)", report.test_samples, lo);
  return string_printf("%d held back for the test (%d to %d per class)", report.test_samples, lo, hi);
}

// Appends `text` wrapped at kWrapColumn: the first line starts with `lead`, the others are indented to match.
void append_paragraph(std::string& out, const std::string& lead, const std::string& text) {
  std::vector<std::string> words;
  std::size_t pos = 0;
  while (pos < text.size()) {
    const std::size_t space = text.find(' ', pos);
    words.push_back(text.substr(pos, space == std::string::npos ? std::string::npos : space - pos));
    pos = space == std::string::npos ? text.size() : space + 1;
  }
  append_words(out, lead, words);
}

void append_advice(std::string& s, const algo::TrainingReport& report, const TrainReportContext& context,
                   const std::vector<Confusion>& worst) {
  const algo::ClassifierReport& svm = report.svm;
  const bool low = !(svm.test_accuracy >= context.target_accuracy);
  const std::string heading =
      string_printf("If the accuracy is low (SVM test accuracy below %.1f %%)", context.target_accuracy * kPercent);
  s += "\n" + heading + "\n" + std::string(heading.size(), '-') + "\n";
  if (!low) s += "It is not low now; these steps are for a later training that falls short.\n";
  int step = 1;
  auto item = [&](const std::string& text) { append_paragraph(s, string_printf("%d. ", step++), text); };
  std::string alike = "Read \"Worst confusions\": those parts look alike to the scanner";
  if (!worst.empty()) {
    alike += " (here " + report.class_names[static_cast<std::size_t>(worst.front().true_class)] + " and " +
             report.class_names[static_cast<std::size_t>(worst.front().predicted_class)] + ")";
  }
  item(alike +
       ". Teach more scans of them, in the poses and coatings seen in production (cellsight teach --part "
       "NAME ...), then train again.");
  const double gap = svm.cv_accuracy - svm.test_accuracy;
  std::string compare =
      "Cross-validation " + percent_text(svm.cv_accuracy) + " vs test " + percent_text(svm.test_accuracy) + ": ";
  if (std::isfinite(gap) && gap > kOverfitGap) {
    compare +=
        "a gap this large means the model learned its training scans rather than the parts. Teach more scans "
        "per part (the thesis used 35 per part for training and 15 for the test).";
  } else {
    compare +=
        "close together, so more scans of the same kind will help little; if both are low, the scans "
        "themselves need attention (next step).";
  }
  item(compare);
  item(
      "When every part is low, check the cell before the model: the calibration (cellsight calibrate "
      "camera|laser|support), the empty-carrier support plane, a dirty laser window, the exposure. Look at single "
      "scans with cellsight classify --json SCAN.ply and at labelled scans with cellsight eval --scans DIR.");
  if (report.stopped) item("This training was stopped early: run it again to the end when the cell is free.");
  item(
      "Parts the scanner cannot tell apart even with more scans are left to Perfect Match at run time (it compares "
      "the two best SVM candidates); if they need the same robot program, give them one PLC id.");
}

}  // namespace

// ---- tables -------------------------------------------------------------------------------------------------------

std::vector<double> per_class_recall(const std::vector<std::vector<int>>& confusion) {
  std::vector<double> recall;
  recall.reserve(confusion.size());
  for (std::size_t i = 0; i < confusion.size(); ++i) {
    const int total = row_sum(confusion[i]);
    const int hit = i < confusion[i].size() ? confusion[i][i] : 0;
    recall.push_back(total > 0 ? static_cast<double>(hit) / total : std::numeric_limits<double>::quiet_NaN());
  }
  return recall;
}

std::vector<Confusion> worst_confusions(const std::vector<std::vector<int>>& confusion, int limit) {
  std::vector<Confusion> all;
  for (std::size_t i = 0; i < confusion.size(); ++i) {
    const int total = row_sum(confusion[i]);
    for (std::size_t j = 0; j < confusion[i].size(); ++j) {
      if (i == j || confusion[i][j] <= 0) continue;
      all.push_back(
          {static_cast<int>(i), static_cast<int>(j), confusion[i][j], static_cast<double>(confusion[i][j]) / total});
    }
  }
  std::stable_sort(all.begin(), all.end(), [](const Confusion& a, const Confusion& b) {
    if (a.count != b.count) return a.count > b.count;
    return a.share > b.share;
  });
  if (limit >= 0 && all.size() > static_cast<std::size_t>(limit)) all.resize(static_cast<std::size_t>(limit));
  return all;
}

namespace {

// Date, database, dataset and the verdict against the target accuracy.
void append_summary_header(std::string& s, const algo::TrainingReport& report, const TrainReportContext& context) {
  const algo::ClassifierReport& svm = report.svm;
  const std::string date = context.date.empty() ? base::local_time_text() : context.date;
  const std::size_t k = report.class_names.size();
  s += "cellsight training report\n=========================\n";
  s += "Date:            " + date + "\n";
  s +=
      "Model database:  " + (context.model_db_path.empty() ? std::string("(not given)") : context.model_db_path) + "\n";
  if (!context.dataset.empty()) s += "Dataset:         " + context.dataset + "\n";
  s += string_printf("Classes:         %zu taught parts\n", k);
  s += string_printf("Scans:           %d for training, ", report.train_samples) + test_split_text(report) + "\n";
  if (report.synthetic_samples > 0) {
    s += string_printf(
        "Variants:        %d synthetic (re-posed, thinned, dropouts, noise) of the training scans; the feature "
        "search scored %d samples\n",
        report.synthetic_samples, report.search_samples);
  }
  if (const std::string scope = algo::search_scope_text(report); !scope.empty())
    s += "Search:          " + scope + "\n";
  s += string_printf("Features:        version %u, %d computed per scan\n", context.feature_version,
                     algo::kFeatureCount);

  const bool low = !(svm.test_accuracy >= context.target_accuracy);
  s += "\n";
  if (!std::isfinite(svm.test_accuracy)) {
    s += "RESULT: UNKNOWN - no test scans were held back, so the SVM was not measured on unseen scans.\n";
  } else if (low) {
    s += string_printf("RESULT: LOW - SVM test accuracy %s, below the %.1f %% target; see the advice at the end.\n",
                       percent_text(svm.test_accuracy).c_str(), context.target_accuracy * kPercent);
  } else {
    s += string_printf("RESULT: OK - SVM test accuracy %s reaches the %.1f %% target.\n",
                       percent_text(svm.test_accuracy).c_str(), context.target_accuracy * kPercent);
  }
  if (report.stopped) s += "WARNING: the training was stopped early (see \"Training\").\n";
}

// The production recogniser: accuracies, calibration, kernel, chosen features and recall per part.
void append_svm_section(std::string& s, const algo::TrainingReport& report) {
  const algo::ClassifierReport& svm = report.svm;
  const std::size_t k = report.class_names.size();
  s += "\nSVM (the recogniser used in production)\n---------------------------------------\n";
  s += "Test accuracy (held-back scans):   " + percent_text(svm.test_accuracy);
  if (report.test_samples > 0) s += string_printf("  (%d of %d scans)", trace(svm.confusion), report.test_samples);
  s += "\n";
  s += string_printf("Cross-validation accuracy (%d-fold, training scans): ", report.folds) +
       percent_text(svm.cv_accuracy) + "\n";
  if (report.test_samples > 0) {
    s += "True part among the two most probable (test): " + percent_text(svm.test_top2) + "\n";
    s += string_printf("Calibration of the top probability (test): expected calibration error %.3f\n", svm.test_ece);
    for (const algo::CalibrationBin& b : svm.reliability) {
      s += string_printf("  p in [%.1f, %.1f): %3d scans, mean p %.3f, right %.3f\n", b.lo, b.hi, b.scans,
                         b.mean_probability, b.accuracy);
    }
  }
  append_paragraph(s, "Kernel: ", kernel_text(report.svm_hyper, active_feature_count(svm)));
  s += string_printf("Chosen features (%d of %d):\n", active_feature_count(svm), algo::kFeatureCount);
  append_wrapped(s, svm.features, "  ");

  const std::vector<double> recall = per_class_recall(svm.confusion);
  std::size_t name_w = 4;
  for (const std::string& n : report.class_names) name_w = std::max(name_w, n.size());
  s += "\nPer-class recall on the test split (share of a part's test scans recognised as that part)\n";
  s += string_printf("  %-*s  test scans  correct  recall\n", static_cast<int>(name_w), "part");
  for (std::size_t i = 0; i < k; ++i) {
    s += string_printf(
        "  %-*s  %10d  %7d  %s\n", static_cast<int>(name_w), report.class_names[i].c_str(), row_sum(svm.confusion[i]),
        svm.confusion[i][i],
        std::isfinite(recall[i]) ? string_printf("%5.1f %%", recall[i] * kPercent).c_str() : "  n/a (no test scans)");
  }
}

void append_worst_confusions(std::string& s, const algo::TrainingReport& report, const std::vector<Confusion>& worst) {
  const algo::ClassifierReport& svm = report.svm;
  s += "\nWorst confusions on the test split (true part -> recognised as)\n";
  if (worst.empty()) s += "  none: every test scan was recognised as its own part.\n";
  for (const Confusion& c : worst) {
    s += string_printf("  %s -> %s: %d of %d scans (%.1f %%)\n",
                       report.class_names[static_cast<std::size_t>(c.true_class)].c_str(),
                       report.class_names[static_cast<std::size_t>(c.predicted_class)].c_str(), c.count,
                       row_sum(svm.confusion[static_cast<std::size_t>(c.true_class)]), c.share * kPercent);
  }
}

// kNN and MLP beside the SVM, when they were trained for comparison (thesis 4.2).
void append_comparison(std::string& s, const algo::TrainingReport& report) {
  if (report.knn || report.mlp) {
    s += "\nComparison (thesis 4.2; only the SVM is used in production)\n";
    s += "  classifier  test      CV        features  time\n";
    for (const algo::ClassifierReport* r : report_classifiers(report)) {
      s += string_printf("  %-10s  %-8s  %-8s  %8d  %s%s\n", classifier_display_name(r->classifier).c_str(),
                         percent_text(r->test_accuracy).c_str(), percent_text(r->cv_accuracy).c_str(),
                         active_feature_count(*r), human_duration(r->seconds).c_str(),
                         r->stopped ? "  (stopped early)" : "");
    }
    s += "  parameters chosen by cross-validation:\n";
    for (const algo::ClassifierReport* r : report_classifiers(report)) {
      append_paragraph(s, "    " + classifier_display_name(r->classifier) + ": ", r->parameters);
    }
  }
}

// Time, annealing steps and whether the training was stopped early.
void append_training_section(std::string& s, const algo::TrainingReport& report, const TrainReportContext& context) {
  const algo::ClassifierReport& svm = report.svm;
  s += "\nTraining\n--------\n";
  s += string_printf("Time: %s in all on %d threads; the SVM annealing took %s.\n",
                     human_duration(report.seconds).c_str(), report.threads, human_duration(svm.seconds).c_str());
  const int steps = svm.curve.empty() ? 0 : static_cast<int>(svm.curve.size()) - 1;
  s += string_printf("SVM annealing: %d steps; %d feature sets scored by %d-fold cross-validation, %d met again.\n",
                     steps, svm.evaluations, report.folds, svm.cache_hits);
  std::string stop_text = "no, the annealing ran all its steps.";
  if (report.stopped) {
    stop_text = "YES - ";
    if (svm.stopped) {
      stop_text += context.planned_iterations > 0
                       ? string_printf("after %d of %d SVM annealing steps", steps, context.planned_iterations)
                       : string_printf("after %d SVM annealing steps", steps);
      stop_text += "; the model uses the best feature set found until then";
      if (!report.knn && !report.mlp) stop_text += " (no kNN/MLP comparison was run)";
    } else {
      stop_text += "during the kNN/MLP comparison; the SVM annealing ran to its end";
    }
    stop_text += ".";
  }
  append_paragraph(s, "Stopped early: ", stop_text);
}

void append_file_list(std::string& s, const algo::TrainingReport& report) {
  s += "\nFiles in this folder\n--------------------\n";
  s += "summary.txt        this text\nreport.yaml        the same figures for programs (curve, confusion, features)\n";
  for (const algo::ClassifierReport* r : report_classifiers(report)) {
    const std::string stem = report_file_stem(*r);
    s += string_printf(
        "confusion_%s.png  %s confusion matrix of the test split (rows: true part, columns: recognised as)\n",
        stem.c_str(), classifier_display_name(r->classifier).c_str());
    s += string_printf("annealing_%s.png  %s feature-selection curve; its numbers in annealing_%s.csv\n", stem.c_str(),
                       classifier_display_name(r->classifier).c_str(), stem.c_str());
  }
}

}  // namespace

std::string training_summary_text(const algo::TrainingReport& report, const TrainReportContext& context) {
  if (Status ok = validate_report(report); !ok) {
    return "cellsight training report\n\nThe report is inconsistent: " + ok.error().message + "\n";
  }
  std::string s;
  append_summary_header(s, report, context);
  append_svm_section(s, report);
  const std::vector<Confusion> worst = worst_confusions(report.svm.confusion, kWorstConfusionsShown);
  append_worst_confusions(s, report, worst);
  append_comparison(s, report);
  append_training_section(s, report, context);
  append_advice(s, report, context, worst);
  append_file_list(s, report);
  return s;
}

// ---- the folder ---------------------------------------------------------------------------------------------------

namespace {

Expected<std::string> encode_png(const cv::Mat& image, const std::string& name) {
  std::vector<uchar> bytes;
  try {
    if (!cv::imencode(".png", image, bytes)) return make_error(name + ": cannot encode the PNG");
  } catch (const cv::Exception& e) {  // OpenCV reports some failures by exception
    return make_error(name + ": " + e.what());
  }
  return std::string(bytes.begin(), bytes.end());
}

// The folder to create: `dir` itself when it is missing or empty, else per policy.
Expected<std::string> resolve_target(const std::string& dir, const TrainReportContext& context) {
  if (dir.empty()) return make_error("training report: no output folder given");
  fs::path target(dir);
  // "out/" and "." have no file name of their own; the staged folder needs one.
  if (!target.has_filename() || target.filename() == "." || target.filename() == "..") {
    target = fs::absolute(target).lexically_normal();
    if (!target.has_filename()) target = target.parent_path();
  }
  std::error_code ec;
  const fs::file_status st = fs::status(target, ec);
  if (!fs::exists(st)) return target.string();
  if (!fs::is_directory(st)) return make_error(target.string() + ": exists and is not a folder; nothing was written");
  if (fs::is_empty(target, ec)) return target.string();
  if (context.if_not_empty == ExistingReportDir::kRefuse) {
    return make_error(target.string() +
                      ": already holds files and the report never overwrites; nothing was written. Give a new or "
                      "empty folder");
  }
  const std::string base = subfolder_name(context.date);
  for (int n = 1; n <= kMaxSubfolderTries; ++n) {
    const fs::path candidate = target / (n == 1 ? base : base + "-" + std::to_string(n));
    if (!fs::exists(candidate, ec)) return candidate.string();
  }
  return make_error(target.string() + ": too many reports named " + base + " already; nothing was written");
}

}  // namespace

Expected<std::string> write_training_report(const std::string& dir, const algo::TrainingReport& report,
                                            const TrainReportContext& context) {
  if (Status s = validate_report(report); !s) return s.error();
  TrainReportContext ctx = context;
  if (ctx.date.empty()) ctx.date = base::local_time_text();
  auto target = resolve_target(dir, ctx);
  if (!target) return target.error();
  auto staged = base::StagedDirectory::create(*target);
  if (!staged) return staged.error();
  const fs::path folder = staged->path();
  auto put = [&](const std::string& name, std::string_view content) {
    return base::write_file_atomic((folder / name).string(), content);
  };
  if (Status s = put("summary.txt", training_summary_text(report, ctx)); !s) return s.error();
  if (Status s = put("report.yaml", training_report_yaml(report, ctx)); !s) return s.error();
  for (const algo::ClassifierReport* r : report_classifiers(report)) {
    const std::string stem = report_file_stem(*r);
    const std::string who = classifier_display_name(r->classifier);
    const std::string confusion_title =
        who + " confusion on the held-back test split - accuracy " + percent_text(r->test_accuracy);
    auto confusion = encode_png(render_confusion_image(report.class_names, r->confusion, confusion_title),
                                "confusion_" + stem + ".png");
    if (!confusion) return confusion.error();
    if (Status s = put("confusion_" + stem + ".png", *confusion); !s) return s.error();
    const std::string curve_title = who + " feature selection by simulated annealing - best CV " +
                                    percent_text(r->cv_accuracy) +
                                    string_printf(" with %d features", active_feature_count(*r));
    auto curve = encode_png(render_annealing_image(*r, curve_title), "annealing_" + stem + ".png");
    if (!curve) return curve.error();
    if (Status s = put("annealing_" + stem + ".png", *curve); !s) return s.error();
    if (Status s = put("annealing_" + stem + ".csv", annealing_curve_csv(*r)); !s) return s.error();
  }
  // mkdtemp made the staging folder private (0700); a report is for everyone who maintains the cell.
  std::error_code ec;
  fs::permissions(folder,
                  fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec | fs::perms::others_read |
                      fs::perms::others_exec,
                  ec);
  if (ec) return make_error(folder.string() + ": cannot make the report readable: " + ec.message());
  if (Status s = staged->commit(); !s) return s.error();
  return *target;
}

}  // namespace cellsight::app
