// The production loop (DESIGN.md "Data flow", "Handshake"): an explicit state machine idle -> scanning ->
// recognising -> publishing, plus fault, that scans each passing part, recognises it under the hard deadline and
// hands the result to the PLC. Memory is fixed after start(): nothing in the loop allocates.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string_view>
#include <thread>

#include "algo/decision.hpp"
#include "algo/result.hpp"
#include "algo/scan_builder.hpp"
#include "app/config.hpp"
#include "app/recogniser.hpp"
#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/modbus/plc_link.hpp"

namespace cellsight::app {

class ServiceNotifier;

enum class LoopState : std::uint8_t {
  kIdle = 0,     // waiting for a trigger (part-present rising edge or SW_TRIGGER)
  kScanning,     // frames of one pass go into the scan builder until part-present falls
  kRecognising,  // the recognition thread works on the scan; the deadline runs
  kPublishing,   // the decision becomes a PLC result (transient: one step)
  kFault,        // a device, the recogniser or the model database failed; ERROR_CODE says which
  kStopped,      // the loop thread has ended
};

[[nodiscard]] constexpr const char* to_string(LoopState state) {
  switch (state) {
    case LoopState::kIdle:
      return "idle";
    case LoopState::kScanning:
      return "scanning";
    case LoopState::kRecognising:
      return "recognising";
    case LoopState::kPublishing:
      return "publishing";
    case LoopState::kFault:
      return "fault";
    case LoopState::kStopped:
      return "stopped";
  }
  return "invalid";
}

struct LoopConfig {
  // Part-present falling edge -> result handed to the PLC link; on overrun the result is "timeout", never a guess.
  int deadline_ms = 3000;
  // No frame for this long while a part is in front of the camera: the scan is aborted (ERROR_CODE camera timeout).
  int frame_timeout_ms = 1000;
  int max_frames = 4000;  // a pass longer than this means a blocked photo-eye: aborted (ERROR_CODE I/O fault)
  std::int32_t start_exposure_us = 1500;
  // Longest single wait of the loop thread (frame, edge, recognition); bounds how late it sees a falling edge, a
  // command or a stop request, and how often it calls PlcLink::heartbeat().
  int poll_slice_ms = 10;
  int retry_interval_ms = 500;   // fault: how often a lost device is reopened and probed
  int models_retry_ms = 10'000;  // fault "model database invalid": how often loading is retried on its own
  // A recogniser still busy this long after the deadline is hung: ERROR_CODE internal, the systemd watchdog is no
  // longer petted (the service gets restarted), until it returns.
  int hung_grace_ms = 2000;
  int max_consecutive_timeouts = 3;  // this many timeout results in a row -> ERROR_CODE repeated timeouts
  double cycle_slow_ms = 1500.0;     // WARNING_CODE cycle slow above this (still inside the deadline)
  // DESIGN.md handshake: triggers start passes only while the PLC holds CONTROL.TRIGGER_ENABLE.
  bool require_trigger_enable = true;
  // The simulated cell: its conveyor moves only when the loop asks the devices for edges or frames, so it waits
  // while the loop is not ready. A real conveyor does not: the loop then keeps reading edges and frames (drained,
  // counted as missed triggers while busy).
  bool conveyor_waits_for_ready = false;
  // Do not take a new part while the link's result queue is full (a line paced by its PLC); otherwise the result
  // is rejected and RESULT_OVERRUN tells the PLC.
  bool hold_when_queue_full = false;
  std::size_t result_queue_capacity = 8;  // the link's, for hold_when_queue_full
  // Edge timestamps are CLOCK_MONOTONIC (real GPIO): the cycle time starts at the edge, not when it was seen.
  bool edge_timestamps_monotonic = false;
  int realtime_priority = 0;           // SCHED_FIFO priority of the loop thread; 0 = normal scheduling
  bool lock_memory = false;            // mlockall(MCL_CURRENT | MCL_FUTURE) at start()
  std::uint64_t max_parts = 0;         // stop taking parts after this many results; 0 = no limit
  std::uint16_t active_models_id = 1;  // ACTIVE_MODELS; SELECT_MODELS with another id is refused
};

// The loop settings that come from the configuration (runtime.*, camera.*, rig geometry, modbus.*).
[[nodiscard]] LoopConfig loop_config(const Config& config);

// What a trigger came from.
enum class TriggerSource : std::uint8_t { kPartPresent, kSoftware };

// One finished part, for the observer and the one log line per part.
struct PartRecord {
  std::uint32_t acq_id = 0;
  TriggerSource trigger = TriggerSource::kPartPresent;
  drivers::PlcResult result;
  algo::Decision decision;  // what the recogniser returned (source kTimeout when the loop enforced the deadline)
  drivers::PublishStatus publish = drivers::PublishStatus::kQueued;
  std::uint32_t seq = 0;  // RESULT_SEQ given by the link (0 when rejected)
  int frames = 0;
  std::size_t points = 0;
  double cycle_ms = 0.0;            // cycle start -> publish() returned
  double recognise_ms = 0.0;        // recognition thread, job posted -> decision back (or the deadline)
  std::int64_t cycle_start_ns = 0;  // steady clock: part-present falling edge (or when it was seen)
  std::int64_t published_ns = 0;    // steady clock: publish() returned
  std::string_view class_name;      // recogniser's name of the class, empty when none
  bool aborted = false;             // the scan was aborted (device fault): the result is "bad scan"
};

// Counters, each a snapshot of a monotonic count unless said otherwise.
struct LoopStats {
  LoopState state = LoopState::kIdle;                          // now
  drivers::ErrorCode error = drivers::ErrorCode::kNone;        // now
  drivers::WarningCode warning = drivers::WarningCode::kNone;  // now
  std::uint64_t iterations = 0;
  std::uint64_t triggers = 0;          // passes started (= last ACQ_ID)
  std::uint64_t results = 0;           // results handed to publish()
  std::uint64_t results_rejected = 0;  // publish() refused (queue full)
  std::uint64_t timeouts = 0;          // results with code timeout
  std::uint64_t aborted_scans = 0;
  std::uint64_t missed_triggers = 0;
  std::uint64_t faults = 0;          // transitions into kFault
  std::uint64_t recoveries = 0;      // transitions out of kFault
  std::uint64_t late_decisions = 0;  // decisions that came back after the deadline (discarded)
  double last_cycle_ms = 0.0;
  double max_cycle_ms = 0.0;
  bool realtime_applied = false;  // SCHED_FIFO as configured (false also when not asked for)
  bool memory_locked = false;
};

// Callbacks from the loop thread (never the recognition thread). They run inside the loop: keep them short and free
// of allocation (tests count).
class LoopObserver {
 public:
  virtual ~LoopObserver() = default;
  virtual void on_state(LoopState /*from*/, LoopState /*to*/, drivers::ErrorCode /*error*/) {}
  virtual void on_pass_started(std::uint32_t /*acq_id*/, TriggerSource /*trigger*/) {}
  virtual void on_frame(std::uint32_t /*acq_id*/, int /*frame_index*/) {}
  virtual void on_part_done(const PartRecord& /*record*/) {}
};

// Loads the recogniser when the loop starts without one or after "model database invalid" (CLEAR_ERROR,
// SELECT_MODELS or every models_retry_ms). Runs on the recognition thread; may allocate (fault path only).
using RecogniserLoader = std::function<Expected<std::unique_ptr<Recogniser>>()>;

// Decision -> result block (DESIGN.md register map). Pure; exposed for tests.
//  svm/pm -> ok (SOURCE svm / perfect match), part id, confidence = probability in per mille, pose X, Y in um and
//           RZ = theta in millidegrees, Z/RX/RY 0 (the planar pose does not move them); an accepted decision
//           without a usable pose -> "pose out of range" (part id kept, pose invalid).
//  unknown -> "unknown part" (confidence of the best class, part id 0); timeout, bad scan, no part -> their codes;
//  every field without a value carries the invalid marker 0x80000000.
[[nodiscard]] drivers::PlcResult to_plc_result(const algo::Decision& decision, std::uint32_t acq_id,
                                               std::uint64_t timestamp_us, double cycle_ms);

// Threads: start() creates the loop thread (acquisition at frame rate, state machine, every PlcLink call) and the
// recognition thread. Everything they use is allocated in the constructor and start().
class ProductionLoop {
 public:
  // Start-up: allocates the scan builder (sized from scan_params). The devices must be open; the link started.
  ProductionLoop(const LoopConfig& config, drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder,
                 const algo::ScanBuilderParams& scan_params, const algo::SensorCalibration& calibration,
                 drivers::PlcLink& link);
  ~ProductionLoop();  // request_stop() + join()
  ProductionLoop(const ProductionLoop&) = delete;
  ProductionLoop& operator=(const ProductionLoop&) = delete;

  // Before start(). Without a recogniser the loop starts in fault "model database invalid" and uses the loader.
  void set_recogniser(std::unique_ptr<Recogniser> recogniser);
  void set_recogniser_loader(RecogniserLoader loader);
  void set_observer(LoopObserver* observer);   // borrowed; must outlive the loop threads
  void set_service(ServiceNotifier* service);  // borrowed; WATCHDOG=1 while healthy

  [[nodiscard]] Status start();
  // Any thread (not a signal handler: use an atomic flag there and call this from a normal thread).
  void request_stop();
  void join();

  [[nodiscard]] LoopState state() const { return state_.load(std::memory_order_acquire); }
  [[nodiscard]] LoopStats stats() const;
  // max_parts results have been published (the loop takes no more parts but keeps serving the PLC).
  [[nodiscard]] bool finished() const { return finished_.load(std::memory_order_acquire); }
  // The loop thread iterated recently and the recogniser is not hung: what the systemd watchdog is told.
  [[nodiscard]] bool healthy() const;
  // Blocks until finished(), a stop request or the timeout; true when finished.
  [[nodiscard]] bool wait_finished(std::chrono::milliseconds timeout);

 private:
  using Clock = std::chrono::steady_clock;
  enum class Job : std::uint8_t { kNone, kRecognise, kLoad, kExit };

  void loop_thread();
  void worker_thread();
  void step(Clock::time_point now);
  void step_idle(Clock::time_point now);
  void step_scanning(Clock::time_point now);
  void step_recognising(Clock::time_point now);
  void step_fault(Clock::time_point now);

  void handle_commands(const drivers::PlcCommands& commands, Clock::time_point now);
  void update_flags();
  [[nodiscard]] bool trigger_allowed() const;
  [[nodiscard]] bool queue_full() const;
  void start_pass(TriggerSource trigger, Clock::time_point now);
  void finish_scan(Clock::time_point cycle_start);
  void abort_pass(drivers::ErrorCode cause, const char* why);
  void publish(const algo::Decision& decision, Clock::time_point now, bool aborted);
  void enter(LoopState next);
  void enter_fault(drivers::ErrorCode cause, const char* why);
  void recover(const char* how);
  void set_error(drivers::ErrorCode code);
  void set_warning(drivers::WarningCode code);
  void count_missed_trigger(const char* why);
  [[nodiscard]] int drain_frames();
  void poll_edges_while_busy();
  void idle_wait(Clock::time_point since);
  void post_job(Job job);
  [[nodiscard]] Clock::time_point edge_time(const drivers::EdgeEvent& edge, Clock::time_point seen) const;

  const LoopConfig config_;
  drivers::Camera& camera_;
  drivers::DigitalIo& io_;
  drivers::Encoder& encoder_;
  drivers::PlcLink& link_;
  algo::ScanBuilder builder_;
  const std::int32_t exposure_min_us_;
  const std::int32_t exposure_max_us_;
  std::unique_ptr<Recogniser> recogniser_;
  RecogniserLoader loader_;
  LoopObserver* observer_ = nullptr;
  ServiceNotifier* service_ = nullptr;

  std::thread loop_thread_;
  std::thread worker_thread_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> finished_{false};
  std::atomic<LoopState> state_{LoopState::kIdle};
  std::atomic<std::int64_t> last_iteration_ns_{0};
  std::atomic<bool> recogniser_hung_{false};
  std::atomic<bool> has_recogniser_{false};
  std::mutex finished_mutex_;
  std::condition_variable finished_cv_;

  // Loop thread <-> recognition thread: one job at a time under worker_mutex_.
  mutable std::mutex worker_mutex_;
  std::condition_variable job_cv_;
  std::condition_variable done_cv_;
  Job job_ = Job::kNone;
  bool worker_exit_ = false;
  bool job_finished_ = true;
  Clock::time_point job_deadline_{};
  Clock::time_point job_posted_at_{};
  Clock::time_point job_finished_at_{};
  algo::Decision job_decision_{};
  bool load_ok_ = false;

  // Loop thread only.
  drivers::ErrorCode fault_cause_ = drivers::ErrorCode::kNone;
  drivers::ErrorCode error_ = drivers::ErrorCode::kNone;  // what ERROR_CODE shows
  drivers::WarningCode warning_ = drivers::WarningCode::kNone;
  std::uint16_t flags_ = 0;  // StatusFlag bits as last sent
  bool flags_sent_ = false;
  bool trigger_enable_ = false;
  std::uint32_t pending_sw_triggers_ = 0;
  bool clear_requested_ = false;
  bool models_reload_requested_ = false;
  bool camera_needs_reopen_ = false;
  bool load_in_flight_ = false;
  Clock::time_point fault_since_{};
  Clock::time_point next_retry_{};
  std::uint32_t acq_id_ = 0;
  TriggerSource pass_trigger_ = TriggerSource::kPartPresent;
  int frames_ = 0;
  Clock::time_point last_frame_at_{};
  Clock::time_point cycle_start_{};
  Clock::time_point deadline_{};
  bool timeout_published_ = false;  // the deadline passed: "timeout" is out, the recogniser's answer is not wanted
  double recognise_ms_ = 0.0;
  int consecutive_timeouts_ = 0;
  std::uint32_t missed_since_result_ = 0;
  std::uint32_t trigger_count_ = 0;
  std::uint32_t missed_count_ = 0;  // MISSED_TRIGGERS (reset by RESET_COUNTERS)
  bool exposure_at_limit_ = false;

  // Counters (loop thread writes, any thread reads).
  std::atomic<std::uint64_t> iterations_{0};
  std::atomic<std::uint64_t> triggers_{0};
  std::atomic<std::uint64_t> results_{0};
  std::atomic<std::uint64_t> rejected_{0};
  std::atomic<std::uint64_t> timeouts_{0};
  std::atomic<std::uint64_t> aborted_{0};
  std::atomic<std::uint64_t> missed_{0};
  std::atomic<std::uint64_t> faults_{0};
  std::atomic<std::uint64_t> recoveries_{0};
  std::atomic<std::uint64_t> late_decisions_{0};
  std::atomic<double> last_cycle_ms_{0.0};
  std::atomic<double> max_cycle_ms_{0.0};
  std::atomic<std::uint16_t> error_now_{0};
  std::atomic<std::uint16_t> warning_now_{0};
  std::atomic<bool> realtime_applied_{false};
  std::atomic<bool> memory_locked_{false};
};

}  // namespace cellsight::app
