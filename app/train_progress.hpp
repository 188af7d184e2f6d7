// The progress line of `cellsight train` (algo::TrainingProgress as text) and the printer that redraws or logs it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <mutex>
#include <optional>
#include <string>

#include "algo/training.hpp"

namespace cellsight::app {

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

// Machine-readable progress of the whole training (`train --progress`, what the operator's screen reads): lines
//   "progress: 0.420 SVM 1/1 annealing 40/96"
// whose fraction runs over the three phases, weighted by their usual share of the time: features of the taught scans
// (first kFeaturesEnd), the classifiers' annealing stages (up to kTrainingEnd), the thresholds (every taught scan
// against its rivals' templates). A line when the fraction has grown by kMinStep, or when the phase changes.
// Thread-safe: the features and the threshold matches report from their worker threads.
enum class TrainPhase : std::uint8_t { kFeatures, kTraining, kThresholds };

class ProgressLines {
 public:
  static constexpr double kFeaturesEnd = 0.25;
  static constexpr double kTrainingEnd = 0.85;
  static constexpr double kMinStep = 0.005;

  explicit ProgressLines(std::FILE* out) : out_(out) {}  // nullptr: prints nothing; `out` is borrowed
  // `done` of `total` items of a phase (features, thresholds).
  void step(TrainPhase phase, std::size_t done, std::size_t total);
  void training(const algo::TrainingProgress& progress);
  void finished(const char* text);  // "progress: 1.000 TEXT"

 private:
  void print(double fraction, TrainPhase phase, const std::string& text);

  std::FILE* out_;
  std::mutex mutex_;
  double last_ = -1.0;
  int last_phase_ = -1;
};

}  // namespace cellsight::app
