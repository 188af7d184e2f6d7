// The report of `cellsight train` and its progress line.
#include "app/train_report.hpp"

#include <sys/ioctl.h>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstdarg>
#include <ctime>
#include <filesystem>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "base/atomic_file.hpp"
#include "base/local_time.hpp"

namespace cellsight::app {
namespace {

namespace fs = std::filesystem;

constexpr double kPercent = 100.0;
constexpr int kReportFormatVersion = 1;
constexpr int kWorstConfusionsShown = 5;
constexpr double kOverfitGap = 0.03;  // CV above test by more than this: the model learned its training scans
constexpr std::size_t kWrapColumn = 100;
constexpr int kMaxSubfolderTries = 100;

// ---- text helpers -----------------------------------------------------------------------------------------------

std::string fmt(const char* format, ...) __attribute__((format(printf, 1, 2)));
std::string fmt(const char* format, ...) {
  char buffer[512];
  va_list args;
  va_start(args, format);
  const int n = std::vsnprintf(buffer, sizeof buffer, format, args);
  va_end(args);
  if (n < 0) return {};
  if (static_cast<std::size_t>(n) < sizeof buffer) return std::string(buffer, static_cast<std::size_t>(n));
  std::string big(static_cast<std::size_t>(n) + 1, '\0');
  va_start(args, format);
  std::vsnprintf(big.data(), big.size(), format, args);
  va_end(args);
  big.resize(static_cast<std::size_t>(n));
  return big;
}

std::string percent_text(double fraction) {
  if (!std::isfinite(fraction)) return "n/a";
  return fmt("%.1f %%", fraction * kPercent);
}

std::string display_name(algo::Classifier classifier) {
  switch (classifier) {
    case algo::Classifier::kSvm:
      return "SVM";
    case algo::Classifier::kKnn:
      return "kNN";
    case algo::Classifier::kMlp:
      return "MLP";
  }
  return "?";
}

// "0.4 s", "12.3 s", "2 min 48 s", "1 h 05 min".
std::string human_duration(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0.0) return "unknown";
  constexpr double kMinute = 60.0, kHour = 3600.0;
  if (seconds < kMinute) return fmt("%.1f s", seconds);
  const auto whole = static_cast<long long>(seconds);
  if (seconds < kHour) return fmt("%lld min %02lld s", whole / 60, whole % 60);
  return fmt("%lld h %02lld min", whole / 3600, (whole % 3600) / 60);
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

int active_count(const algo::ClassifierReport& r) {
  return r.features.empty() ? static_cast<int>(r.mask.count()) : static_cast<int>(r.features.size());
}

std::vector<const algo::ClassifierReport*> all_classifiers(const algo::TrainingReport& report) {
  std::vector<const algo::ClassifierReport*> all = {&report.svm};
  if (report.knn) all.push_back(&*report.knn);
  if (report.mlp) all.push_back(&*report.mlp);
  return all;
}

std::string file_stem(const algo::ClassifierReport& r) {
  return std::string(algo::to_string(r.classifier));
}

Status validate_report(const algo::TrainingReport& report) {
  const std::size_t k = report.class_names.size();
  if (k == 0) return make_error("training report: no classes");
  for (const algo::ClassifierReport* r : all_classifiers(report)) {
    const std::string who = "training report (" + display_name(r->classifier) + "): ";
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
    return fmt("RBF, C = %g, gamma = %.4g (i = %g over %d active features), degree: not used by RBF", h.c, gamma,
               h.gamma_factor, active);
  }
  return fmt("polynomial, degree = %d, C = %g, gamma = %.4g (i = %g over %d active features), coef0 = %g", h.degree,
             h.c, gamma, h.gamma_factor, active, h.coef0);
}

std::string test_split_text(const algo::TrainingReport& report) {
  int lo = std::numeric_limits<int>::max(), hi = 0;
  for (const auto& row : report.svm.confusion) {
    lo = std::min(lo, row_sum(row));
    hi = std::max(hi, row_sum(row));
  }
  if (report.test_samples == 0 || report.svm.confusion.empty()) return "no scans held back for the test";
  if (lo == hi) return fmt("%d held back for the test (%d per class)", report.test_samples, lo);
  return fmt("%d held back for the test (%d to %d per class)", report.test_samples, lo, hi);
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
      fmt("If the accuracy is low (SVM test accuracy below %.1f %%)", context.target_accuracy * kPercent);
  s += "\n" + heading + "\n" + std::string(heading.size(), '-') + "\n";
  if (!low) s += "It is not low now; these steps are for a later training that falls short.\n";
  int step = 1;
  auto item = [&](const std::string& text) { append_paragraph(s, fmt("%d. ", step++), text); };
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

std::string training_summary_text(const algo::TrainingReport& report, const TrainReportContext& context) {
  if (Status ok = validate_report(report); !ok) {
    return "cellsight training report\n\nThe report is inconsistent: " + ok.error().message + "\n";
  }
  const algo::ClassifierReport& svm = report.svm;
  const std::string date = context.date.empty() ? local_time_text() : context.date;
  const std::size_t k = report.class_names.size();
  std::string s;
  s += "cellsight training report\n=========================\n";
  s += "Date:            " + date + "\n";
  s +=
      "Model database:  " + (context.model_db_path.empty() ? std::string("(not given)") : context.model_db_path) + "\n";
  if (!context.dataset.empty()) s += "Dataset:         " + context.dataset + "\n";
  s += fmt("Classes:         %zu taught parts\n", k);
  s += fmt("Scans:           %d for training, ", report.train_samples) + test_split_text(report) + "\n";
  if (report.synthetic_samples > 0) {
    s += fmt("Variants:        %d synthetic (re-posed, thinned, dropouts, noise) of the training scans; the feature "
             "search scored %d samples\n",
             report.synthetic_samples, report.search_samples);
  }
  s += fmt("Features:        version %u, %d computed per scan\n", context.feature_version, algo::kFeatureCount);

  const bool low = !(svm.test_accuracy >= context.target_accuracy);
  s += "\n";
  if (!std::isfinite(svm.test_accuracy)) {
    s += "RESULT: UNKNOWN - no test scans were held back, so the SVM was not measured on unseen scans.\n";
  } else if (low) {
    s += fmt("RESULT: LOW - SVM test accuracy %s, below the %.1f %% target; see the advice at the end.\n",
             percent_text(svm.test_accuracy).c_str(), context.target_accuracy * kPercent);
  } else {
    s += fmt("RESULT: OK - SVM test accuracy %s reaches the %.1f %% target.\n", percent_text(svm.test_accuracy).c_str(),
             context.target_accuracy * kPercent);
  }
  if (report.stopped) s += "WARNING: the training was stopped early (see \"Training\").\n";

  s += "\nSVM (the recogniser used in production)\n---------------------------------------\n";
  s += "Test accuracy (held-back scans):   " + percent_text(svm.test_accuracy);
  if (report.test_samples > 0) s += fmt("  (%d of %d scans)", trace(svm.confusion), report.test_samples);
  s += "\n";
  s +=
      fmt("Cross-validation accuracy (%d-fold, training scans): ", report.folds) + percent_text(svm.cv_accuracy) + "\n";
  if (report.test_samples > 0) {
    s += "True part among the two most probable (test): " + percent_text(svm.test_top2) + "\n";
    s += fmt("Calibration of the top probability (test): expected calibration error %.3f\n", svm.test_ece);
    for (const algo::CalibrationBin& b : svm.reliability) {
      s += fmt("  p in [%.1f, %.1f): %3d scans, mean p %.3f, right %.3f\n", b.lo, b.hi, b.scans, b.mean_probability,
               b.accuracy);
    }
  }
  append_paragraph(s, "Kernel: ", kernel_text(report.svm_hyper, active_count(svm)));
  s += fmt("Chosen features (%d of %d):\n", active_count(svm), algo::kFeatureCount);
  append_wrapped(s, svm.features, "  ");

  const std::vector<double> recall = per_class_recall(svm.confusion);
  std::size_t name_w = 4;
  for (const std::string& n : report.class_names) name_w = std::max(name_w, n.size());
  s += "\nPer-class recall on the test split (share of a part's test scans recognised as that part)\n";
  s += fmt("  %-*s  test scans  correct  recall\n", static_cast<int>(name_w), "part");
  for (std::size_t i = 0; i < k; ++i) {
    s += fmt("  %-*s  %10d  %7d  %s\n", static_cast<int>(name_w), report.class_names[i].c_str(),
             row_sum(svm.confusion[i]), svm.confusion[i][i],
             std::isfinite(recall[i]) ? fmt("%5.1f %%", recall[i] * kPercent).c_str() : "  n/a (no test scans)");
  }

  const std::vector<Confusion> worst = worst_confusions(svm.confusion, kWorstConfusionsShown);
  s += "\nWorst confusions on the test split (true part -> recognised as)\n";
  if (worst.empty()) s += "  none: every test scan was recognised as its own part.\n";
  for (const Confusion& c : worst) {
    s += fmt("  %s -> %s: %d of %d scans (%.1f %%)\n",
             report.class_names[static_cast<std::size_t>(c.true_class)].c_str(),
             report.class_names[static_cast<std::size_t>(c.predicted_class)].c_str(), c.count,
             row_sum(svm.confusion[static_cast<std::size_t>(c.true_class)]), c.share * kPercent);
  }

  if (report.knn || report.mlp) {
    s += "\nComparison (thesis 4.2; only the SVM is used in production)\n";
    s += "  classifier  test      CV        features  time\n";
    for (const algo::ClassifierReport* r : all_classifiers(report)) {
      s += fmt("  %-10s  %-8s  %-8s  %8d  %s%s\n", display_name(r->classifier).c_str(),
               percent_text(r->test_accuracy).c_str(), percent_text(r->cv_accuracy).c_str(), active_count(*r),
               human_duration(r->seconds).c_str(), r->stopped ? "  (stopped early)" : "");
    }
    s += "  parameters chosen by cross-validation:\n";
    for (const algo::ClassifierReport* r : all_classifiers(report)) {
      append_paragraph(s, "    " + display_name(r->classifier) + ": ", r->parameters);
    }
  }

  s += "\nTraining\n--------\n";
  s += fmt("Time: %s in all on %d threads; the SVM annealing took %s.\n", human_duration(report.seconds).c_str(),
           report.threads, human_duration(svm.seconds).c_str());
  const int steps = svm.curve.empty() ? 0 : static_cast<int>(svm.curve.size()) - 1;
  s += fmt("SVM annealing: %d steps; %d feature sets scored by %d-fold cross-validation, %d met again.\n", steps,
           svm.evaluations, report.folds, svm.cache_hits);
  std::string stop_text = "no, the annealing ran all its steps.";
  if (report.stopped) {
    stop_text = "YES - ";
    if (svm.stopped) {
      stop_text += context.planned_iterations > 0
                       ? fmt("after %d of %d SVM annealing steps", steps, context.planned_iterations)
                       : fmt("after %d SVM annealing steps", steps);
      stop_text += "; the model uses the best feature set found until then";
      if (!report.knn && !report.mlp) stop_text += " (no kNN/MLP comparison was run)";
    } else {
      stop_text += "during the kNN/MLP comparison; the SVM annealing ran to its end";
    }
    stop_text += ".";
  }
  append_paragraph(s, "Stopped early: ", stop_text);

  append_advice(s, report, context, worst);

  s += "\nFiles in this folder\n--------------------\n";
  s += "summary.txt        this text\nreport.yaml        the same figures for programs (curve, confusion, features)\n";
  for (const algo::ClassifierReport* r : all_classifiers(report)) {
    const std::string stem = file_stem(*r);
    s += fmt("confusion_%s.png  %s confusion matrix of the test split (rows: true part, columns: recognised as)\n",
             stem.c_str(), display_name(r->classifier).c_str());
    s += fmt("annealing_%s.png  %s feature-selection curve; its numbers in annealing_%s.csv\n", stem.c_str(),
             display_name(r->classifier).c_str(), stem.c_str());
  }
  return s;
}

// ---- YAML and CSV -------------------------------------------------------------------------------------------------

namespace {

void emit_number(YAML::Emitter& out, double v) {
  if (std::isfinite(v)) {
    out << v;
  } else {
    out << YAML::Null;
  }
}

void emit_classifier(YAML::Emitter& out, const algo::ClassifierReport& r, const std::vector<std::string>& names) {
  out << YAML::BeginMap;
  out << YAML::Key << "parameters" << YAML::Value << r.parameters;
  out << YAML::Key << "test_accuracy" << YAML::Value;
  emit_number(out, r.test_accuracy);
  out << YAML::Key << "cv_accuracy" << YAML::Value;
  emit_number(out, r.cv_accuracy);
  if (r.classifier == algo::Classifier::kSvm) {
    out << YAML::Key << "test_top2" << YAML::Value;
    emit_number(out, r.test_top2);
    out << YAML::Key << "test_ece" << YAML::Value;
    emit_number(out, r.test_ece);
    out << YAML::Key << "reliability" << YAML::Value << YAML::BeginSeq;
    for (const algo::CalibrationBin& b : r.reliability) {
      out << YAML::Flow << std::vector<double>{b.lo, b.hi, static_cast<double>(b.scans), b.mean_probability, b.accuracy};
    }
    out << YAML::EndSeq;
  }
  out << YAML::Key << "active_features" << YAML::Value << active_count(r);
  out << YAML::Key << "features" << YAML::Value << YAML::Flow << r.features;
  out << YAML::Key << "evaluations" << YAML::Value << r.evaluations;
  out << YAML::Key << "cache_hits" << YAML::Value << r.cache_hits;
  out << YAML::Key << "seconds" << YAML::Value << r.seconds;
  out << YAML::Key << "stopped" << YAML::Value << r.stopped;
  const std::vector<double> recall = per_class_recall(r.confusion);
  out << YAML::Key << "per_class_recall" << YAML::Value << YAML::BeginMap;
  for (std::size_t i = 0; i < names.size() && i < recall.size(); ++i) {
    out << YAML::Key << names[i] << YAML::Value;
    emit_number(out, recall[i]);
  }
  out << YAML::EndMap;
  out << YAML::Key << "confusion" << YAML::Value << YAML::BeginSeq;
  for (const auto& row : r.confusion) out << YAML::Flow << row;
  out << YAML::EndSeq;
  out << YAML::Key << "curve" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "columns" << YAML::Value << YAML::Flow
      << std::vector<std::string>{"iteration",        "temperature",   "candidate_accuracy",
                                  "current_accuracy", "best_accuracy", "candidate_active",
                                  "accepted"};
  out << YAML::Key << "rows" << YAML::Value << YAML::BeginSeq;
  for (const algo::AnnealingStep& st : r.curve) {
    out << YAML::Flow << YAML::BeginSeq << st.iteration << st.temperature << st.candidate_accuracy
        << st.current_accuracy << st.best_accuracy << st.candidate_active << st.accepted << YAML::EndSeq;
  }
  out << YAML::EndSeq << YAML::EndMap;
  out << YAML::EndMap;
}

}  // namespace

std::string training_report_yaml(const algo::TrainingReport& report, const TrainReportContext& context) {
  YAML::Emitter out;
  out.SetDoublePrecision(8);
  out << YAML::Comment(
      "cellsight training report; accuracies are fractions (0.983 = 98.3 %); confusion rows are the true class,\n"
      "columns the predicted class, both in the order of `classes`");
  out << YAML::BeginMap;
  out << YAML::Key << "format_version" << YAML::Value << kReportFormatVersion;
  out << YAML::Key << "date" << YAML::Value << (context.date.empty() ? local_time_text() : context.date);
  out << YAML::Key << "model_db" << YAML::Value << context.model_db_path;
  out << YAML::Key << "dataset" << YAML::Value << context.dataset;
  out << YAML::Key << "feature_version" << YAML::Value << context.feature_version;
  out << YAML::Key << "feature_count" << YAML::Value << algo::kFeatureCount;
  out << YAML::Key << "classes" << YAML::Value << YAML::Flow << report.class_names;
  out << YAML::Key << "train_samples" << YAML::Value << report.train_samples;
  out << YAML::Key << "test_samples" << YAML::Value << report.test_samples;
  out << YAML::Key << "synthetic_samples" << YAML::Value << report.synthetic_samples;
  out << YAML::Key << "search_samples" << YAML::Value << report.search_samples;
  out << YAML::Key << "folds" << YAML::Value << report.folds;
  out << YAML::Key << "threads" << YAML::Value << report.threads;
  out << YAML::Key << "seconds" << YAML::Value << report.seconds;
  out << YAML::Key << "stopped" << YAML::Value << report.stopped;
  out << YAML::Key << "target_accuracy" << YAML::Value << context.target_accuracy;
  const algo::SvmHyper& h = report.svm_hyper;
  out << YAML::Key << "svm_hyper" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "kernel" << YAML::Value << std::string(algo::to_string(h.kernel));
  out << YAML::Key << "c" << YAML::Value << h.c;
  out << YAML::Key << "gamma_factor" << YAML::Value << h.gamma_factor;
  out << YAML::Key << "gamma" << YAML::Value;
  emit_number(
      out, active_count(report.svm) > 0 ? h.gamma(active_count(report.svm)) : std::numeric_limits<double>::quiet_NaN());
  out << YAML::Key << "degree" << YAML::Value << h.degree;
  out << YAML::Key << "coef0" << YAML::Value << h.coef0;
  out << YAML::EndMap;
  out << YAML::Key << "classifiers" << YAML::Value << YAML::BeginMap;
  for (const algo::ClassifierReport* r : all_classifiers(report)) {
    out << YAML::Key << file_stem(*r) << YAML::Value;
    emit_classifier(out, *r, report.class_names);
  }
  out << YAML::EndMap << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

std::string annealing_curve_csv(const algo::ClassifierReport& report) {
  std::string s = "iteration,temperature,candidate_accuracy,current_accuracy,best_accuracy,candidate_active,accepted\n";
  for (const algo::AnnealingStep& st : report.curve) {
    s += fmt("%d,%.9g,%.9g,%.9g,%.9g,%d,%d\n", st.iteration, st.temperature, st.candidate_accuracy, st.current_accuracy,
             st.best_accuracy, st.candidate_active, st.accepted ? 1 : 0);
  }
  return s;
}

// ---- drawing ------------------------------------------------------------------------------------------------------

namespace {

constexpr int kFont = cv::FONT_HERSHEY_SIMPLEX;
constexpr double kTextScale = 0.45;
constexpr double kSmallTextScale = 0.38;
constexpr double kTitleScale = 0.6;
constexpr Bgr kWhite{255, 255, 255};
constexpr Bgr kBlack{0, 0, 0};
constexpr Bgr kAxisColor{60, 60, 60};
constexpr Bgr kGridColor{228, 228, 228};
constexpr Bgr kCellLineColor{200, 200, 200};
constexpr Bgr kZeroTextColor{195, 195, 195};
constexpr Bgr kDiagonalFull{70, 160, 70};  // green for the correctly recognised share
constexpr Bgr kErrorFull{60, 60, 210};     // red for scans recognised as another part
// A cell with any count gets at least this much colour, so one stray scan is visible.
constexpr double kMinShade = 0.15;

cv::Size text_size(const std::string& text, double scale, int thickness = 1) {
  int baseline = 0;
  cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  size.height += baseline;
  return size;
}

// Text with its left end at x and its vertical middle at y_mid.
void put_text(cv::Mat& image, const std::string& text, int x, int y_mid, double scale, const cv::Scalar& color,
              int thickness = 1) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  cv::putText(image, text, {x, y_mid + size.height / 2}, kFont, scale, color, thickness, cv::LINE_AA);
}

void put_text_centered(cv::Mat& image, const std::string& text, int x_mid, int y_mid, double scale,
                       const cv::Scalar& color, int thickness = 1) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  put_text(image, text, x_mid - size.width / 2, y_mid, scale, color, thickness);
}

void put_text_right(cv::Mat& image, const std::string& text, int x_right, int y_mid, double scale,
                    const cv::Scalar& color) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, 1, &baseline);
  put_text(image, text, x_right - size.width, y_mid, scale, color);
}

// Text reading bottom to top; (x_mid, y_bottom) is where its start lands. Clipped to the image.
void put_text_vertical(cv::Mat& image, const std::string& text, int x_mid, int y_bottom, double scale,
                       const cv::Scalar& color) {
  const cv::Size size = text_size(text, scale);
  cv::Mat label(size.height + 2, size.width + 2, image.type(), kWhite);
  put_text(label, text, 1, label.rows / 2, scale, color);
  cv::Mat turned;
  cv::rotate(label, turned, cv::ROTATE_90_COUNTERCLOCKWISE);
  cv::Rect where(x_mid - turned.cols / 2, y_bottom - turned.rows, turned.cols, turned.rows);
  const cv::Rect inside = where & cv::Rect(0, 0, image.cols, image.rows);
  if (inside.empty()) return;
  turned(cv::Rect(inside.x - where.x, inside.y - where.y, inside.width, inside.height)).copyTo(image(inside));
}

cv::Scalar blend(const cv::Scalar& full, double t) {
  t = std::clamp(t, 0.0, 1.0);
  const cv::Scalar white = kWhite;
  return {white[0] + (full[0] - white[0]) * t, white[1] + (full[1] - white[1]) * t,
          white[2] + (full[2] - white[2]) * t};
}

double luminance(const cv::Scalar& bgr) {
  return 0.114 * bgr[0] + 0.587 * bgr[1] + 0.299 * bgr[2];
}

// 1-2-5 tick step giving about `target` intervals over `span`.
double nice_step(double span, int target) {
  if (!(span > 0.0)) return 1.0;
  const double raw = span / target;
  const double magnitude = std::pow(10.0, std::floor(std::log10(raw)));
  const double f = raw / magnitude;
  const double nice = f < 1.5 ? 1.0 : (f < 3.0 ? 2.0 : (f < 7.0 ? 5.0 : 10.0));
  return nice * magnitude;
}

std::vector<double> ticks_between(double lo, double hi, double step) {
  std::vector<double> t;
  constexpr double kSlack = 1e-9;
  constexpr int kMaxTicks = 100;  // a bad step must not flood the axis
  const double first = std::ceil(lo / step - kSlack);
  for (int i = 0; i < kMaxTicks; ++i) {
    const double v = (first + i) * step;
    if (v > hi + step * kSlack) break;
    t.push_back(std::abs(v) < step * kSlack ? 0.0 : v);
  }
  return t;
}

std::string tick_label(double v) {
  return fmt("%g", v);
}

}  // namespace

cv::Mat render_confusion_image(const std::vector<std::string>& class_names,
                               const std::vector<std::vector<int>>& confusion, const std::string& title,
                               ConfusionLayout* layout) {
  const int k = static_cast<int>(class_names.size());
  auto count_at = [&](int i, int j) {
    const auto ui = static_cast<std::size_t>(i), uj = static_cast<std::size_t>(j);
    return ui < confusion.size() && uj < confusion[ui].size() ? std::max(confusion[ui][uj], 0) : 0;
  };
  const double scale = k > 20 ? kSmallTextScale : kTextScale;
  int max_count = 0;
  for (const auto& row : confusion) {
    for (int v : row) max_count = std::max(max_count, v);
  }
  int label_w = text_size("part", scale).width;
  for (const std::string& n : class_names) label_w = std::max(label_w, text_size(n, scale).width);
  constexpr int kMargin = 10, kAxisTitle = 22, kTitleBand = 34, kFooter = 30, kMinCell = 34, kCellPad = 14;
  const int cell = std::max(kMinCell, text_size(std::to_string(max_count), scale).width + kCellPad);
  const int recall_w = text_size("100.0 %", scale).width + 2 * kMargin;
  ConfusionLayout geo;
  geo.cell_px = cell;
  geo.origin = {kMargin + kAxisTitle + label_w + kMargin, kTitleBand + kAxisTitle + label_w + kMargin};
  const int matrix = k * cell;
  const int width =
      std::max(geo.origin.x + matrix + recall_w + kMargin, text_size(title, kTitleScale).width + 2 * kMargin);
  const int height = geo.origin.y + matrix + kFooter;
  cv::Mat image(height, width, CV_8UC3, kWhite);
  put_text(image, title, kMargin, kTitleBand / 2, kTitleScale, kBlack);

  // Axis titles and names.
  put_text_centered(image, "recognised as", geo.origin.x + matrix / 2, kTitleBand + kAxisTitle / 2, scale, kAxisColor);
  put_text_vertical(image, "true part", kMargin + kAxisTitle / 2,
                    geo.origin.y + matrix / 2 + text_size("true part", scale).width / 2, scale, kAxisColor);
  for (int i = 0; i < k; ++i) {
    const std::string& n = class_names[static_cast<std::size_t>(i)];
    put_text_right(image, n, geo.origin.x - kMargin, geo.origin.y + i * cell + cell / 2, scale, kBlack);
    put_text_vertical(image, n, geo.origin.x + i * cell + cell / 2, geo.origin.y - kMargin, scale, kBlack);
  }
  put_text_centered(image, "recall", geo.origin.x + matrix + recall_w / 2, geo.origin.y - kMargin - 6, scale,
                    kAxisColor);

  // Cells: shade by share of the row (thesis 6.4.2 measures per part), count in the middle.
  for (int i = 0; i < k; ++i) {
    int total = 0;
    for (int j = 0; j < k; ++j) total += count_at(i, j);
    for (int j = 0; j < k; ++j) {
      const int count = count_at(i, j);
      const cv::Rect r = geo.cell(i, j);
      cv::Scalar fill = kWhite;
      if (count > 0) {
        const double share = static_cast<double>(count) / total;
        fill = blend(i == j ? kDiagonalFull : kErrorFull, kMinShade + (1.0 - kMinShade) * share);
      }
      cv::rectangle(image, r, fill, cv::FILLED);
      cv::rectangle(image, r, kCellLineColor, 1);
      const cv::Scalar ink = count == 0 ? kZeroTextColor : (luminance(fill) < 140.0 ? kWhite : kBlack);
      put_text_centered(image, std::to_string(count), r.x + r.width / 2, r.y + r.height / 2, scale, ink);
    }
    const std::string recall = total > 0 ? fmt("%.1f %%", kPercent * count_at(i, i) / total) : std::string("n/a");
    put_text_right(image, recall, geo.origin.x + matrix + recall_w - kMargin, geo.origin.y + i * cell + cell / 2, scale,
                   kBlack);
  }
  cv::rectangle(image, cv::Rect(geo.origin.x, geo.origin.y, matrix, matrix), kAxisColor, 1);
  put_text(image, "cell shade: share of the row's test scans (green: right part, red: another part)", kMargin,
           height - kFooter / 2, kSmallTextScale, kAxisColor);
  if (layout != nullptr) *layout = geo;
  return image;
}

cv::Point2d PlotAxes::to_px(double x, double y) const {
  const double fx = x_max > x_min ? (x - x_min) / (x_max - x_min) : 0.0;
  double fy = 0.0;
  if (log_y) {
    const double lo = std::log10(y_min), hi = std::log10(y_max);
    fy = hi > lo && y > 0.0 ? (std::log10(y) - lo) / (hi - lo) : 0.0;
  } else {
    fy = y_max > y_min ? (y - y_min) / (y_max - y_min) : 0.0;
  }
  return {area.x + fx * (area.width - 1), area.y + (area.height - 1) * (1.0 - fy)};
}

namespace {

cv::Point px(const PlotAxes& axes, double x, double y) {
  const cv::Point2d p = axes.to_px(x, y);
  return {static_cast<int>(std::lround(p.x)), static_cast<int>(std::lround(p.y))};
}

// Horizontal then vertical segments: the value holds until the next step ("best so far").
void draw_steps(cv::Mat& image, const PlotAxes& axes, const std::vector<cv::Point2d>& points, const cv::Scalar& color,
                int thickness) {
  for (std::size_t i = 0; i + 1 < points.size(); ++i) {
    const cv::Point a = px(axes, points[i].x, points[i].y);
    const cv::Point corner = px(axes, points[i + 1].x, points[i].y);
    const cv::Point b = px(axes, points[i + 1].x, points[i + 1].y);
    cv::line(image, a, corner, color, thickness, cv::LINE_AA);
    cv::line(image, corner, b, color, thickness, cv::LINE_AA);
  }
}

void draw_x_axis(cv::Mat& image, const PlotAxes& axes, const std::vector<double>& ticks, bool labels) {
  const int bottom = axes.area.y + axes.area.height - 1;
  for (double t : ticks) {
    const int x = px(axes, t, axes.y_min).x;
    cv::line(image, {x, axes.area.y}, {x, bottom}, kGridColor, 1);
    cv::line(image, {x, bottom}, {x, bottom + 5}, kAxisColor, 1);
    if (labels) put_text_centered(image, tick_label(t), x, bottom + 16, kTextScale, kAxisColor);
  }
}

void draw_y_ticks(cv::Mat& image, const PlotAxes& axes, const std::vector<double>& ticks, bool right, bool grid,
                  const std::string& suffix) {
  const int side = right ? axes.area.x + axes.area.width - 1 : axes.area.x;
  for (double t : ticks) {
    const int y = px(axes, axes.x_min, t).y;
    if (grid) cv::line(image, {axes.area.x, y}, {axes.area.x + axes.area.width - 1, y}, kGridColor, 1);
    cv::line(image, {side, y}, {right ? side + 5 : side - 5, y}, kAxisColor, 1);
    if (right) {
      put_text(image, tick_label(t) + suffix, side + 8, y, kTextScale, kAxisColor);
    } else {
      put_text_right(image, tick_label(t) + suffix, side - 8, y, kTextScale, kAxisColor);
    }
  }
}

// A legend row: a sample mark and a label per entry, left to right from x at height y_mid.
struct LegendEntry {
  std::string label;
  cv::Scalar color;
  enum class Mark : std::uint8_t { kLine, kDot, kRing } mark;
};
void draw_legend(cv::Mat& image, const std::vector<LegendEntry>& entries, int x, int y_mid) {
  constexpr int kSample = 22, kGap = 8, kSpacing = 24;
  for (const LegendEntry& e : entries) {
    switch (e.mark) {
      case LegendEntry::Mark::kLine:
        cv::line(image, {x, y_mid}, {x + kSample, y_mid}, e.color, 2, cv::LINE_AA);
        break;
      case LegendEntry::Mark::kDot:
        cv::circle(image, {x + kSample / 2, y_mid}, 3, e.color, cv::FILLED, cv::LINE_AA);
        break;
      case LegendEntry::Mark::kRing:
        cv::circle(image, {x + kSample / 2, y_mid}, 3, e.color, 1, cv::LINE_AA);
        break;
    }
    put_text(image, e.label, x + kSample + kGap, y_mid, kTextScale, kBlack);
    x += kSample + kGap + text_size(e.label, kTextScale).width + kSpacing;
  }
}

}  // namespace

cv::Mat render_annealing_image(const algo::ClassifierReport& report, const std::string& title,
                               AnnealingPlotLayout* layout) {
  constexpr int kWidth = 1000, kHeight = 720, kLeft = 80, kRight = 80;
  constexpr int kTopY = 62, kTopH = 380, kBottomY = 506, kBottomH = 150;
  constexpr int kTargetTicks = 8;
  cv::Mat image(kHeight, kWidth, CV_8UC3, kWhite);
  put_text(image, title, 10, 22, kTitleScale, kBlack);
  const auto& curve = report.curve;

  AnnealingPlotLayout geo;
  // x: iterations, from 0 to the last step (at least 1 so a one-point curve has an axis).
  const double last = curve.empty() ? 1.0 : std::max(1.0, static_cast<double>(curve.back().iteration));
  const double x_step = nice_step(last, kTargetTicks);
  const std::vector<double> x_ticks = ticks_between(0.0, last, x_step);

  // Accuracy panel in percent: from a round value below the lowest point to 100.
  double lo = kPercent;
  for (const algo::AnnealingStep& s : curve) {
    lo = std::min({lo, s.candidate_accuracy * kPercent, s.current_accuracy * kPercent, s.best_accuracy * kPercent});
  }
  lo = std::clamp(lo, 0.0, kPercent - 1.0);
  const double y_step = nice_step(kPercent - lo, 5);
  double y_min = std::floor(lo / y_step) * y_step;
  if (lo - y_min < 0.02 * (kPercent - y_min)) y_min -= y_step;
  y_min = std::max(0.0, y_min);
  geo.accuracy = {cv::Rect(kLeft, kTopY, kWidth - kLeft - kRight, kTopH),
                  0.0,
                  last,
                  y_min,
                  kPercent + 0.03 * (kPercent - y_min),
                  false};

  // Temperature panel, log scale over whole decades.
  double t_lo = std::numeric_limits<double>::infinity(), t_hi = 0.0;
  int max_active = 1;
  for (const algo::AnnealingStep& s : curve) {
    if (s.temperature > 0.0) {
      t_lo = std::min(t_lo, s.temperature);
      t_hi = std::max(t_hi, s.temperature);
    }
    max_active = std::max(max_active, s.candidate_active);
  }
  if (!(t_hi > 0.0)) t_lo = t_hi = 1.0;
  double d_lo = std::floor(std::log10(t_lo)), d_hi = std::ceil(std::log10(t_hi));
  if (d_hi <= d_lo) d_hi = d_lo + 1.0;
  const cv::Rect bottom(kLeft, kBottomY, kWidth - kLeft - kRight, kBottomH);
  geo.temperature = {bottom, 0.0, last, std::pow(10.0, d_lo), std::pow(10.0, d_hi), true};
  const double f_step = nice_step(max_active, 4);
  geo.features = {bottom, 0.0, last, 0.0, std::ceil((max_active + 1) / f_step) * f_step, false};  // headroom

  // Accuracy panel.
  const PlotAxes& acc = geo.accuracy;
  draw_x_axis(image, acc, x_ticks, true);
  draw_y_ticks(image, acc, ticks_between(acc.y_min, kPercent, y_step), false, true, "");
  put_text_vertical(image, "CV accuracy [%]", 18, acc.area.y + acc.area.height / 2 + 60, kTextScale, kBlack);
  draw_legend(image,
              {{"candidate (accepted)", kAcceptedPointColor, LegendEntry::Mark::kDot},
               {"candidate (rejected)", kRejectedPointColor, LegendEntry::Mark::kRing},
               {"current", kCurrentLineColor, LegendEntry::Mark::kLine},
               {"best so far", kBestLineColor, LegendEntry::Mark::kLine}},
              kLeft, kTopY - 14);
  std::vector<cv::Point2d> current, best, temperature, active;
  for (const algo::AnnealingStep& s : curve) {
    current.emplace_back(s.iteration, s.current_accuracy * kPercent);
    best.emplace_back(s.iteration, s.best_accuracy * kPercent);
    temperature.emplace_back(s.iteration, s.temperature);
    active.emplace_back(s.iteration, s.candidate_active);
  }
  // Current line under the candidates (an accepted candidate is the new current), best line on top.
  draw_steps(image, acc, current, kCurrentLineColor, 1);
  for (const algo::AnnealingStep& s : curve) {
    const cv::Point p = px(acc, s.iteration, s.candidate_accuracy * kPercent);
    if (s.accepted) {
      cv::circle(image, p, 3, kAcceptedPointColor, cv::FILLED, cv::LINE_AA);
    } else {
      cv::circle(image, p, 3, kRejectedPointColor, 1, cv::LINE_AA);
    }
  }
  draw_steps(image, acc, best, kBestLineColor, 2);
  cv::rectangle(image, acc.area, kAxisColor, 1);
  if (curve.empty()) {
    put_text_centered(image, "no annealing steps recorded", acc.area.x + acc.area.width / 2,
                      acc.area.y + acc.area.height / 2, kTitleScale, kAxisColor);
  }

  // Temperature and active-feature panel.
  const PlotAxes& temp = geo.temperature;
  draw_x_axis(image, temp, x_ticks, true);
  std::vector<double> decades;
  for (int d = static_cast<int>(d_lo); d <= static_cast<int>(d_hi); ++d) decades.push_back(std::pow(10.0, d));
  draw_y_ticks(image, temp, decades, false, true, "");
  draw_y_ticks(image, geo.features, ticks_between(0.0, geo.features.y_max, f_step), true, false, "");
  put_text_vertical(image, "temperature", 18, temp.area.y + temp.area.height / 2 + 40, kTextScale, kBlack);
  put_text_vertical(image, "active features", kWidth - 14, temp.area.y + temp.area.height / 2 + 55, kTextScale, kBlack);
  draw_legend(image,
              {{"temperature (left, log scale)", kTemperatureLineColor, LegendEntry::Mark::kLine},
               {"active features of the candidate (right)", kFeaturesLineColor, LegendEntry::Mark::kLine}},
              kLeft, kBottomY - 14);
  draw_steps(image, geo.features, active, kFeaturesLineColor, 1);
  for (std::size_t i = 0; i + 1 < temperature.size(); ++i) {
    cv::line(image, px(temp, temperature[i].x, temperature[i].y), px(temp, temperature[i + 1].x, temperature[i + 1].y),
             kTemperatureLineColor, 2, cv::LINE_AA);
  }
  cv::rectangle(image, temp.area, kAxisColor, 1);
  put_text_centered(image, "annealing iteration (one candidate feature set per iteration)", kWidth / 2,
                    kBottomY + kBottomH + 40, kTextScale, kBlack);
  if (layout != nullptr) *layout = geo;
  return image;
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
  if (ctx.date.empty()) ctx.date = local_time_text();
  auto target = resolve_target(dir, ctx);
  if (!target) return target.error();
  auto staged = StagedDirectory::create(*target);
  if (!staged) return staged.error();
  const fs::path folder = staged->path();
  auto put = [&](const std::string& name, std::string_view content) {
    return write_file_atomic((folder / name).string(), content);
  };
  if (Status s = put("summary.txt", training_summary_text(report, ctx)); !s) return s.error();
  if (Status s = put("report.yaml", training_report_yaml(report, ctx)); !s) return s.error();
  for (const algo::ClassifierReport* r : all_classifiers(report)) {
    const std::string stem = file_stem(*r);
    const std::string who = display_name(r->classifier);
    const std::string confusion_title =
        who + " confusion on the held-back test split - accuracy " + percent_text(r->test_accuracy);
    auto confusion = encode_png(render_confusion_image(report.class_names, r->confusion, confusion_title),
                                "confusion_" + stem + ".png");
    if (!confusion) return confusion.error();
    if (Status s = put("confusion_" + stem + ".png", *confusion); !s) return s.error();
    const std::string curve_title = who + " feature selection by simulated annealing - best CV " +
                                    percent_text(r->cv_accuracy) + fmt(" with %d features", active_count(*r));
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

// ---- progress -----------------------------------------------------------------------------------------------------

std::string format_duration(double seconds, bool round_up) {
  constexpr double kLimitS = 1e8;  // ~3 years: anything longer is no estimate
  constexpr double kSlackS = 1e-6;
  if (!std::isfinite(seconds) || seconds < 0.0 || seconds > kLimitS) return "--:--";
  const auto whole = static_cast<long long>(round_up ? std::ceil(seconds - kSlackS) : std::floor(seconds + kSlackS));
  const long long h = whole / 3600, m = (whole % 3600) / 60, s = whole % 60;
  if (h > 0) return fmt("%lld:%02lld:%02lld", h, m, s);
  return fmt("%lld:%02lld", m, s);
}

std::string format_progress(const algo::TrainingProgress& progress) {
  constexpr int kBarWidth = 20;
  const int iterations = std::max(progress.iterations, 0);
  const int done = std::clamp(progress.iteration, 0, iterations);
  const double fraction = iterations > 0 ? static_cast<double>(done) / iterations : 1.0;
  const int filled = std::clamp(static_cast<int>(std::floor(fraction * kBarWidth)), 0, kBarWidth);
  std::string line = display_name(progress.classifier);
  if (progress.stages > 1) line += fmt(" %d/%d", progress.stage + 1, progress.stages);
  line += " [" + std::string(static_cast<std::size_t>(filled), '#') +
          std::string(static_cast<std::size_t>(kBarWidth - filled), '.') + "]";
  const int digits = static_cast<int>(std::to_string(iterations).size());
  line += fmt(" %*d/%d %3d%%", digits, done, iterations, static_cast<int>(std::floor(fraction * kPercent)));
  line += fmt("  best %.1f %% (%d features)", progress.best_accuracy * kPercent, progress.best_active);
  line += "  elapsed " + format_duration(progress.elapsed_s, false);
  line += "  ETA " + (done == 0 && iterations > 0 ? std::string("--:--") : format_duration(progress.eta_s, true));
  return line;
}

ProgressPrinter::ProgressPrinter(std::FILE* out, bool terminal, double log_interval_s, int columns)
    : out_(out), terminal_(terminal), log_interval_s_(log_interval_s), columns_(std::max(columns, 0)) {}

ProgressPrinter ProgressPrinter::for_stream(std::FILE* out, double log_interval_s) {
  const int fd = out != nullptr ? ::fileno(out) : -1;
  const bool terminal = fd >= 0 && ::isatty(fd) == 1;
  winsize size{};
  const int columns = terminal && ::ioctl(fd, TIOCGWINSZ, &size) == 0 ? size.ws_col : 0;
  return ProgressPrinter(out, terminal, log_interval_s, columns);
}

ProgressPrinter::ProgressPrinter(ProgressPrinter&& other) noexcept
    : out_(other.out_),
      terminal_(other.terminal_),
      log_interval_s_(other.log_interval_s_),
      columns_(other.columns_),
      last_print_s_(other.last_print_s_),
      stage_(other.stage_),
      last_width_(other.last_width_),
      line_open_(other.line_open_),
      prints_(other.prints_),
      pending_(other.pending_) {
  other.out_ = nullptr;
  other.line_open_ = false;
  other.pending_.reset();
}

ProgressPrinter::~ProgressPrinter() {
  finish();
}

void ProgressPrinter::update(const algo::TrainingProgress& progress) {
  if (out_ == nullptr) return;
  const bool new_stage = progress.stage != stage_;
  const bool stage_end = progress.iteration >= progress.iterations;
  const double since_s = progress.elapsed_s - last_print_s_;
  const double interval_s = terminal_ ? kRedrawIntervalS : log_interval_s_;
  if (!new_stage && !stage_end && since_s < interval_s) {
    pending_ = progress;
    return;
  }
  print(progress, new_stage, stage_end);
}

void ProgressPrinter::print(const algo::TrainingProgress& progress, bool new_stage, bool stage_end) {
  pending_.reset();
  std::string line = format_progress(progress);
  std::string text;
  if (terminal_) {
    // The last column stays free: writing into it makes some terminals wrap at once.
    if (columns_ > 1 && line.size() >= static_cast<std::size_t>(columns_)) {
      line.resize(static_cast<std::size_t>(columns_ - 1));
    }
    if (new_stage && line_open_) {
      text += '\n';
      last_width_ = 0;
    }
    text += '\r';
    text += line;
    if (line.size() < last_width_) text.append(last_width_ - line.size(), ' ');  // rub out a longer line
    last_width_ = line.size();
    line_open_ = true;
    if (stage_end) {  // keep each finished stage on screen
      text += '\n';
      line_open_ = false;
      last_width_ = 0;
    }
  } else {
    text = line + "\n";
  }
  std::fputs(text.c_str(), out_);
  std::fflush(out_);
  ++prints_;
  stage_ = progress.stage;
  last_print_s_ = progress.elapsed_s;
}

void ProgressPrinter::finish() {
  // A run stopped between two prints ends showing where it stopped.
  if (out_ != nullptr && pending_) print(*pending_, pending_->stage != stage_, false);
  if (out_ != nullptr && line_open_) {
    std::fputc('\n', out_);
    std::fflush(out_);
  }
  line_open_ = false;
  last_width_ = 0;
}

}  // namespace cellsight::app
