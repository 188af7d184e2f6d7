// The recognition thread of the production loop and its hand-off: a single-slot mailbox of atomics, so the
// SCHED_FIFO loop thread never waits on a lock that this normal-priority thread could hold (no priority inversion).
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <span>
#include <string_view>
#include <thread>

#include "algo/decision.hpp"
#include "algo/scan.hpp"
#include "base/result.hpp"
#include "runtime/loop_types.hpp"
#include "runtime/recogniser.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::runtime {

enum class WorkerJob : std::uint8_t { kRecognise, kLoad };

// What the worker hands back for one job.
struct WorkerAnswer {
  WorkerJob job = WorkerJob::kRecognise;
  algo::Decision decision;  // kRecognise
  bool load_ok = false;     // kLoad: a recogniser is now in place
  std::chrono::steady_clock::time_point posted_at{};
  std::chrono::steady_clock::time_point finished_at{};
};

// One job at a time. The slot has two owners in turn, told apart by two sequence words: the poster (the loop
// thread) writes the job and then publishes posted_seq_; the worker reads it, works, writes the answer and then
// publishes done_seq_ = posted_seq_. Each side touches the slot only while it owns it, and each wait is a futex on
// a word (futex.hpp), never a mutex.
class RecognitionWorker {
 public:
  using Clock = std::chrono::steady_clock;

  RecognitionWorker() = default;
  ~RecognitionWorker();  // stop()
  RecognitionWorker(const RecognitionWorker&) = delete;
  RecognitionWorker& operator=(const RecognitionWorker&) = delete;

  // Before start().
  void set_recogniser(std::unique_ptr<Recogniser> recogniser);
  void set_loader(RecogniserLoader loader);
  // Keep scans in `keeper` (borrowed, may be null): every pass posted with tag.teach, and when keep_unknown the
  // passes that come out unknown or timed out. The copy is made before the answer is published.
  void set_keeper(ScanKeeper* keeper, bool keep_unknown);
  // Every recognised pass, thinned, for the live page's depth image (borrowed, may be null).
  void set_preview(ScanKeeper* preview) { preview_ = preview; }

  [[nodiscard]] Status start();
  // Lets a running job finish, then ends the thread. Any thread except the worker itself.
  void stop();

  // ---- the poster's side (one thread: the loop) ----
  // No job in the slot: the last answer is in answer() and a new job may be posted.
  [[nodiscard]] bool idle() const;
  // Recognise `points` (which stay untouched until the answer is back) before `deadline`. False when busy.
  [[nodiscard]] bool post_recognise(std::span<const algo::ScanPoint> points, Clock::time_point deadline,
                                    const KeepTag& tag = {});
  // Load the recogniser with the loader (model database). False when busy or without a loader.
  [[nodiscard]] bool post_load();
  // Sleeps until the worker is idle or `until`; true when idle. Wakes as soon as the answer is published.
  [[nodiscard]] bool wait_idle(Clock::time_point until);
  // The poster, while idle(): puts `recogniser` in place and hands back the one it replaces (destroy it elsewhere:
  // a model database takes long to unmap). The worker reads it only after the next post.
  void swap_recogniser(std::unique_ptr<Recogniser>& recogniser);
  // The last job's answer; read only while idle().
  [[nodiscard]] const WorkerAnswer& answer() const { return answer_; }
  [[nodiscard]] bool has_loader() const { return static_cast<bool>(loader_); }
  // The recogniser's name of a class; empty without a recogniser, and empty while a job runs (a load job replaces
  // the recogniser). The loop asks when it publishes an answer, so the worker is idle then.
  [[nodiscard]] std::string_view class_name(int class_index) const;

  // ---- any thread ----
  [[nodiscard]] bool has_recogniser() const { return has_recogniser_.load(std::memory_order_acquire); }

 private:
  void run();
  void post(WorkerJob job);
  void keep(const algo::Decision& decision);

  std::unique_ptr<Recogniser> recogniser_;  // the worker's while a job runs; replaced only by kLoad
  RecogniserLoader loader_;
  ScanKeeper* keeper_ = nullptr;
  ScanKeeper* preview_ = nullptr;
  bool keep_unknown_ = false;
  KeptScanInfo kept_info_;  // filled by keep() (worker thread), copied into the keeper's slot
  std::thread thread_;

  // The slot. Job half: written by the poster before posted_seq_ (release), read by the worker after (acquire).
  WorkerJob job_ = WorkerJob::kRecognise;
  std::span<const algo::ScanPoint> points_;
  KeepTag tag_;
  Clock::time_point deadline_{};
  Clock::time_point posted_at_{};
  // Answer half: written by the worker before done_seq_ (release), read by the poster after (acquire).
  WorkerAnswer answer_;

  std::atomic<std::uint32_t> posted_seq_{0};
  std::atomic<std::uint32_t> done_seq_{0};  // == posted_seq_: idle; the poster's futex word
  std::atomic<std::uint32_t> bell_{0};      // rung on every post and on stop: the worker's futex word
  std::atomic<bool> exit_{false};
  std::atomic<bool> has_recogniser_{false};
};

}  // namespace cellsight::runtime
