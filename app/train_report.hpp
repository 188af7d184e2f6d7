// The report of `cellsight train` (summary text, YAML/CSV, the plots of train_report_plots.hpp) written into a folder;
// its progress line is train_progress.hpp.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "algo/features.hpp"
#include "algo/result.hpp"
#include "algo/training.hpp"

namespace cellsight::app {

// What write_training_report does when the folder given exists and already holds something.
enum class ExistingReportDir : std::uint8_t {
  kNewSubfolder,  // write into a new subfolder named after the date, e.g. DIR/report-2025-01-31_140509[-2]
  kRefuse,        // refuse with a clear error
};

// Facts the training report does not carry itself; the caller (train mode) knows them.
struct TrainReportContext {
  std::string model_db_path;  // where the trained model was stored
  std::string dataset;        // one line, e.g. "models/: 15 taught parts, 50 scans each"
  std::string date;           // local time of the training, "YYYY-MM-DD HH:MM:SS"; empty: now
  std::uint32_t feature_version = algo::kFeatureVersion;
  int planned_iterations = 0;     // SVM annealing iterations asked for (0: unknown), for "stopped after N of M"
  double target_accuracy = 0.97;  // issue 4 acceptance: below this the summary says the model needs work
  ExistingReportDir if_not_empty = ExistingReportDir::kNewSubfolder;
};

// Writes the report into `dir` atomically (filled under a temporary name, then renamed into place):
//   summary.txt             for a maintenance engineer (figures, chosen features, confusions, what to do)
//   report.yaml             the same numbers, machine-readable (per classifier: accuracies, parameters, features,
//                           per-class recall, confusion, annealing curve)
//   confusion_svm.png       confusion matrix of the test split; annealing_svm.png the annealing curve;
//   annealing_svm.csv       the curve for a spreadsheet; the same three for knn / mlp when present.
// `dir` may be missing or an empty folder (its parent must exist). When it holds something, nothing in it is
// overwritten: context.if_not_empty chooses between a new dated subfolder (staged as a hidden folder beside it,
// removed again on failure) and a refusal. Returns the folder written.
[[nodiscard]] Expected<std::string> write_training_report(const std::string& dir, const algo::TrainingReport& report,
                                                          const TrainReportContext& context);

// ---- the pieces (each usable alone) -------------------------------------------------------------------------------

[[nodiscard]] std::string training_summary_text(const algo::TrainingReport& report, const TrainReportContext& context);
[[nodiscard]] std::string training_report_yaml(const algo::TrainingReport& report, const TrainReportContext& context);
// Header line and one line per annealing step.
[[nodiscard]] std::string annealing_curve_csv(const algo::ClassifierReport& report);

// Recall per class from a [true][predicted] confusion matrix: diagonal over row sum; NaN for a class without
// test scans.
[[nodiscard]] std::vector<double> per_class_recall(const std::vector<std::vector<int>>& confusion);

struct Confusion {
  int true_class = 0, predicted_class = 0;
  int count = 0;
  double share = 0.0;  // of the true class's test scans
};
// Off-diagonal cells with a count, most scans first (ties: larger share, then matrix order); at most `limit`.
[[nodiscard]] std::vector<Confusion> worst_confusions(const std::vector<std::vector<int>>& confusion, int limit);

// "SVM", "kNN", "MLP": how the report and the progress line name a classifier.
[[nodiscard]] std::string classifier_display_name(algo::Classifier classifier);
// The classifiers of a report: the SVM, then kNN and MLP when they were trained for comparison.
[[nodiscard]] std::vector<const algo::ClassifierReport*> report_classifiers(const algo::TrainingReport& report);
// How many features the classifier uses.
[[nodiscard]] int active_feature_count(const algo::ClassifierReport& r);
// The stem of its files in the report folder: "svm", "knn", "mlp".
[[nodiscard]] std::string report_file_stem(const algo::ClassifierReport& r);

}  // namespace cellsight::app
