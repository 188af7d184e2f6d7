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
  std::string title;           // what the page shows ("retrain", "teach bracket_7 (5 scans)")
  std::string state = "idle";  // idle | running | done | failed | cancelled
  double progress = -1.0;      // 0..1, or -1 when the command tells none
  std::int64_t started_ms = 0;  // CLOCK_REALTIME
  std::int64_t ended_ms = 0;
  int exit_code = -1;
  std::vector<std::string> log_tail;  // the last lines of its output
  nlohmann::json result;              // classify --json's answer, the training report's summary, or null
};

class JobRunner {
 public:
  // exe: the cellsight binary (/proc/self/exe); config_path and models_dir are passed to every command.
  JobRunner(std::string exe, std::string config_path, std::string models_dir);
  ~JobRunner();  // cancels a running job and waits for it
  JobRunner(const JobRunner&) = delete;
  JobRunner& operator=(const JobRunner&) = delete;

  // Starts `cellsight --config C --models M <args>`; an error when a job is running. on_done runs on the runner's
  // thread when the job has ended (e.g. to reload the models after a retrain).
  [[nodiscard]] Expected<std::uint64_t> start(JobKind kind, std::vector<std::string> args, std::string title,
                                              std::function<void(const JobView&)> on_done = {});
  [[nodiscard]] JobView view() const;  // the running job, or the last one
  void cancel();                       // SIGTERM to the running job (its saves are atomic: nothing half-written)

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

[[nodiscard]] const char* to_string(JobKind kind);

}  // namespace cellsight::hmi
