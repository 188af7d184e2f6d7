// The screen's long actions — teach, delete, retrain, debug classify — run as child `cellsight` processes (the same
// commands a technician types, with their atomic saves and clear errors), one at a time, at low priority (nice), so
// neither a crash nor the CPU they take can touch the production loop. Their output is read by a thread of the
// runner into a bounded tail; progress lines ("progress: 0.37 ...") move the bar; the result (a JSON document the
// command printed, or the training report) is kept for the page.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "base/result.hpp"

namespace cellsight::hmi {

enum class JobKind : std::uint8_t { kTeach, kDelete, kTrain, kClassify };

struct JobView {
  std::uint64_t id = 0;  // 0: no job yet
  JobKind kind = JobKind::kTeach;
  std::string title;            // what the page shows ("retrain", "teach bracket_7 (5 scans)")
  std::string state = "idle";   // idle | running | done | failed | cancelled
  double progress = -1.0;       // 0..1, or -1 when the command tells none
  std::string progress_text;    // the words after the fraction of the last progress line ("annealing 40/96")
  std::int64_t started_ms = 0;  // CLOCK_REALTIME
  std::int64_t ended_ms = 0;
  int exit_code = -1;                 // the command's exit status; 128 + N when signal N ended it
  std::vector<std::string> log_tail;  // the last lines of its output (stdout and stderr), progress lines left out
  // classify --json's answer (an array of the JSON objects the command printed, one per line on stdout), the
  // training report's summary (JobHooks::result), or null.
  nlohmann::json result;
};

[[nodiscard]] nlohmann::json to_json(const JobView& view);

// What the caller of start() adds to a job. Both run on the runner's thread after the child has ended.
struct JobHooks {
  // Replaces the default result (the JSON lines of stdout) before the job counts as ended, so the page never sees
  // an ended job without its result (the training report's summary is read here).
  std::function<nlohmann::json(const JobView&)> result;
  // After the job has ended (e.g. to reload the models after a retrain).
  std::function<void(const JobView&)> on_done;
};

class JobRunner {
 public:
  // Bounds of what is kept of a job's output.
  static constexpr std::size_t kTailLines = 200;
  static constexpr std::size_t kLineBytes = 1000;  // a longer line is cut (the tail is for reading)
  static constexpr std::size_t kResultLineBytes = std::size_t{1} << 18;  // a JSON line of stdout, whole
  static constexpr std::size_t kResultLines = 1000;                      // JSON lines of stdout kept
  static constexpr int kNice = 10;                                       // the children's niceness

  // exe: the cellsight binary (/proc/self/exe); config_path and models_dir are passed to every command
  // (config_path empty: none, the child finds the same built-in defaults the parent found).
  JobRunner(const std::string& exe, const std::string& config_path, const std::string& models_dir);
  // The calibration `run` uses: teach, train and classify jobs get `--calibration PATH` after their mode word (they
  // read the scans in its carrier frame). Before the first start().
  void set_calibration(std::string path);
  // Any program: every job runs `command_prefix... args...` (tests run /bin/sh -c SCRIPT sh ARGS).
  explicit JobRunner(std::vector<std::string> command_prefix);
  ~JobRunner();  // cancels a running job and waits for it
  JobRunner(const JobRunner&) = delete;
  JobRunner& operator=(const JobRunner&) = delete;

  // Starts `cellsight --config C --models M <args>`; an error when a job is running (busy() tells which) or the
  // process cannot be started.
  [[nodiscard]] Expected<std::uint64_t> start(JobKind kind, std::vector<std::string> args, std::string title,
                                              JobHooks hooks = {});
  [[nodiscard]] JobView view() const;  // the running job, or the last one
  [[nodiscard]] bool busy() const;     // a job is running
  // SIGTERM to the running job (its saves are atomic: nothing half-written); SIGKILL kKillAfter later if it has not
  // ended by then. False when no job runs.
  bool cancel();

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

[[nodiscard]] const char* to_string(JobKind kind);

}  // namespace cellsight::hmi
