// The progress line of `cellsight train`: redrawn in place on a terminal, logged now and then otherwise.
#include "app/train_progress.hpp"

#include <sys/ioctl.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>

#include "app/train_report.hpp"
#include "base/string_printf.hpp"

namespace cellsight::app {
namespace {

using base::string_printf;

constexpr double kPercent = 100.0;

}  // namespace

// ---- progress -----------------------------------------------------------------------------------------------------

std::string format_duration(double seconds, bool round_up) {
  constexpr double kLimitS = 1e8;  // ~3 years: anything longer is no estimate
  constexpr double kSlackS = 1e-6;
  if (!std::isfinite(seconds) || seconds < 0.0 || seconds > kLimitS) return "--:--";
  const auto whole = static_cast<long long>(round_up ? std::ceil(seconds - kSlackS) : std::floor(seconds + kSlackS));
  const long long h = whole / 3600, m = (whole % 3600) / 60, s = whole % 60;
  if (h > 0) return string_printf("%lld:%02lld:%02lld", h, m, s);
  return string_printf("%lld:%02lld", m, s);
}

std::string format_progress(const algo::TrainingProgress& progress) {
  constexpr int kBarWidth = 20;
  const int iterations = std::max(progress.iterations, 0);
  const int done = std::clamp(progress.iteration, 0, iterations);
  const double fraction = iterations > 0 ? static_cast<double>(done) / iterations : 1.0;
  const int filled = std::clamp(static_cast<int>(std::floor(fraction * kBarWidth)), 0, kBarWidth);
  std::string line = classifier_display_name(progress.classifier);
  if (progress.stages > 1) line += string_printf(" %d/%d", progress.stage + 1, progress.stages);
  line += " [" + std::string(static_cast<std::size_t>(filled), '#') +
          std::string(static_cast<std::size_t>(kBarWidth - filled), '.') + "]";
  const int digits = static_cast<int>(std::to_string(iterations).size());
  line += string_printf(" %*d/%d %3d%%", digits, done, iterations, static_cast<int>(std::floor(fraction * kPercent)));
  line += string_printf("  best %.1f %% (%d features)", progress.best_accuracy * kPercent, progress.best_active);
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

// ---- machine-readable progress ---------------------------------------------------------------------------------

void ProgressLines::step(TrainPhase phase, std::size_t done, std::size_t total) {
  const double part = total > 0 ? static_cast<double>(std::min(done, total)) / static_cast<double>(total) : 1.0;
  const bool features = phase == TrainPhase::kFeatures;
  const double lo = features ? 0.0 : kTrainingEnd;
  const double hi = features ? kFeaturesEnd : 1.0;
  print(lo + part * (hi - lo), phase,
        string_printf("%s %zu/%zu", features ? "features" : "thresholds", std::min(done, total), total));
}

void ProgressLines::training(const algo::TrainingProgress& p) {
  const int stages = std::max(p.stages, 1);
  const double in_stage =
      p.iterations > 0 ? std::clamp(static_cast<double>(p.iteration) / p.iterations, 0.0, 1.0) : 1.0;
  const double part = std::clamp((p.stage + in_stage) / stages, 0.0, 1.0);
  print(kFeaturesEnd + part * (kTrainingEnd - kFeaturesEnd), TrainPhase::kTraining,
        string_printf("%s %d/%d annealing %d/%d", classifier_display_name(p.classifier).c_str(), p.stage + 1, stages,
                      p.iteration, p.iterations));
}

void ProgressLines::finished(const char* text) {
  if (out_ == nullptr) return;
  const std::lock_guard<std::mutex> lock(mutex_);
  std::fprintf(out_, "progress: 1.000 %s\n", text);
  std::fflush(out_);  // a pipe is block-buffered: the screen must see each line as it comes
}

void ProgressLines::print(double fraction, TrainPhase phase, const std::string& text) {
  if (out_ == nullptr) return;
  const std::lock_guard<std::mutex> lock(mutex_);
  const int p = static_cast<int>(phase);
  if (p == last_phase_ && fraction < last_ + kMinStep) return;
  last_phase_ = p;
  last_ = fraction;
  std::fprintf(out_, "progress: %.3f %s\n", fraction, text.c_str());
  std::fflush(out_);
}

}  // namespace cellsight::app
