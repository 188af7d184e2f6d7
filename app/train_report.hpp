// The report of `cellsight train` (summary text, confusion and annealing plots, YAML/CSV) and its progress line.
#pragma once

#include <cstdint>
#include <cstdio>
#include <opencv2/core.hpp>
#include <optional>
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

// Where render_confusion_image put the cells (for tests and anyone annotating the image).
struct ConfusionLayout {
  cv::Point origin;  // top-left corner of cell [0][0]
  int cell_px = 0;
  [[nodiscard]] cv::Rect cell(int true_class, int predicted_class) const {
    return {origin.x + predicted_class * cell_px, origin.y + true_class * cell_px, cell_px, cell_px};
  }
};
// BGR image: rows = true class, columns = predicted class, names on both axes, the count in every cell, cells
// shaded by their share of the row (green on the diagonal, red off it, white when empty), recall per row at the
// right.
[[nodiscard]] cv::Mat render_confusion_image(const std::vector<std::string>& class_names,
                                             const std::vector<std::vector<int>>& confusion, const std::string& title,
                                             ConfusionLayout* layout = nullptr);

// A plot panel: data coordinates -> pixels.
struct PlotAxes {
  cv::Rect area;
  double x_min = 0.0, x_max = 1.0, y_min = 0.0, y_max = 1.0;
  bool log_y = false;
  [[nodiscard]] cv::Point2d to_px(double x, double y) const;
};
struct AnnealingPlotLayout {
  PlotAxes accuracy;     // x: iteration, y: accuracy in %
  PlotAxes temperature;  // x: iteration, y: temperature (log scale)
  PlotAxes features;     // same area as temperature, y: active features of the candidate (right axis)
};
// BGR image, two panels sharing the iteration axis: top, the CV accuracy of every candidate (filled dot accepted,
// ring rejected) with the current and best accuracy lines; bottom, the temperature (log, left axis) and the number
// of active features of each candidate (right axis). Ticks, axis labels and legends included.
[[nodiscard]] cv::Mat render_annealing_image(const algo::ClassifierReport& report, const std::string& title,
                                             AnnealingPlotLayout* layout = nullptr);

// A colour as OpenCV stores it (blue, green, red); constexpr, unlike cv::Scalar.
struct Bgr {
  std::uint8_t b = 0, g = 0, r = 0;
  // NOLINTNEXTLINE(google-explicit-constructor): used wherever OpenCV takes a colour
  operator cv::Scalar() const { return {static_cast<double>(b), static_cast<double>(g), static_cast<double>(r)}; }
};
// Colours of the plots, shared with the tests that look for them.
inline constexpr Bgr kBestLineColor{40, 150, 40};
inline constexpr Bgr kCurrentLineColor{0, 140, 255};
inline constexpr Bgr kAcceptedPointColor{190, 110, 30};
inline constexpr Bgr kRejectedPointColor{150, 150, 150};
inline constexpr Bgr kTemperatureLineColor{40, 40, 190};
inline constexpr Bgr kFeaturesLineColor{150, 90, 150};

// ---- progress ---------------------------------------------------------------------------------------------------

// "m:ss" below an hour, "h:mm:ss" from there; "--:--" for a negative, NaN or infinite time. Elapsed time is
// truncated like a stopwatch (round_up false); an ETA is rounded up so it never reads 0:00 while work is left.
[[nodiscard]] std::string format_duration(double seconds, bool round_up);

// One line, no newline, at most ~100 characters:
//   "SVM 2/3 [#########...........]  90/200  45%  best 98.3 % (17 features)  elapsed 1:23  ETA 1:42"
// The stage counter is left out when there is one stage; the ETA covers the current stage ("--:--" before the
// first step).
[[nodiscard]] std::string format_progress(const algo::TrainingProgress& progress);

// Prints format_progress lines. On a terminal it redraws one line in place ('\r', at most every 0.1 s of training
// time, a new line per stage); otherwise (a log file, journald) it writes a full line at the first and last step
// of each stage and whenever log_interval_s of training time has passed since the last one. Times come from the
// progress itself, so what is printed depends only on the updates.
class ProgressPrinter {
 public:
  static constexpr double kDefaultLogIntervalS = 10.0;
  static constexpr double kRedrawIntervalS = 0.1;

  // `out` is borrowed and must outlive the printer. On a terminal `columns` (0: no limit) cuts the line short so
  // it never wraps, which would break the redraw in place.
  ProgressPrinter(std::FILE* out, bool terminal, double log_interval_s = kDefaultLogIntervalS, int columns = 0);
  // Terminal or not decided by isatty() on the stream, its width asked from the terminal.
  static ProgressPrinter for_stream(std::FILE* out, double log_interval_s = kDefaultLogIntervalS);
  ProgressPrinter(ProgressPrinter&& other) noexcept;
  ProgressPrinter& operator=(ProgressPrinter&&) = delete;
  ProgressPrinter(const ProgressPrinter&) = delete;
  ProgressPrinter& operator=(const ProgressPrinter&) = delete;
  ~ProgressPrinter();

  void update(const algo::TrainingProgress& progress);
  // Prints the last update if it was held back, then ends a line left open on a terminal; harmless to call twice.
  void finish();
  // Lines written (on a terminal every redraw counts).
  [[nodiscard]] int prints() const { return prints_; }

 private:
  void print(const algo::TrainingProgress& progress, bool new_stage, bool stage_end);

  std::FILE* out_;
  bool terminal_;
  double log_interval_s_;
  int columns_;
  double last_print_s_ = 0.0;
  int stage_ = -1;
  std::size_t last_width_ = 0;
  bool line_open_ = false;
  int prints_ = 0;
  std::optional<algo::TrainingProgress> pending_;  // the last update, when it was not printed
};

}  // namespace cellsight::app
