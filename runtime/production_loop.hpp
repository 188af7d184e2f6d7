// The production loop (DESIGN.md "Data flow", "Handshake"): an explicit state machine idle -> scanning ->
// recognising -> publishing, plus fault, that scans each passing part, recognises it under the hard deadline and
// hands the result to the PLC. Memory is fixed after start(): nothing in the loop allocates.
//
// Rooms: the state machine is split per state (loop_pass.cpp idle + scanning, loop_recognise.cpp, loop_publish.cpp,
// loop_fault.cpp, loop_commands.cpp); recognition runs on RecognitionWorker (atomic mailbox); what the PLC sees is
// plc_mapping; log lines go through LogQueue to a writer thread; real-time set-up is realtime.cpp. Config -> LoopConfig
// is app/loop_wiring.cpp, above this layer.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <thread>

#include "algo/decision.hpp"
#include "algo/scan_builder.hpp"
#include "base/result.hpp"
#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "runtime/log_queue.hpp"
#include "runtime/loop_types.hpp"
#include "runtime/pass_acquirer.hpp"
#include "runtime/recogniser.hpp"
#include "runtime/recognition_worker.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::runtime {

class ServiceNotifier;

// Threads: start() creates the loop thread (acquisition at frame rate, state machine, every PlcLink call), the
// recognition thread and the log writer thread. Everything they use is allocated in the constructor and start().
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
  // Keep scans for the operator's screen (borrowed, outlives the loop threads): the passes of a part being taught,
  // and when keep_unknown those that come out unknown. Without a keeper ENTER_TEACH is refused.
  void set_keeper(ScanKeeper* keeper, bool keep_unknown);
  // Every recognised pass, thinned to the preview's max_points, for the live page's depth image (borrowed).
  void set_preview(ScanKeeper* preview) { worker_.set_preview(preview); }

  // ---- the screen's commands: the same path as the PLC's COMMAND register (one poster thread) ----
  // Taken by the loop at its next step, between passes (a teach mode change applies from the next pass on).
  // False when the previous one has not been taken yet.
  bool post_command(drivers::CommandCode command, std::uint32_t arg);
  // The last posted command's fate: pending until the loop took it, then done or refused.
  enum class CommandFate : std::uint8_t { kPending, kDone, kRefused };
  [[nodiscard]] CommandFate command_fate() const;
  // Any thread: a recogniser (e.g. built after a retrain) that the loop puts in place between passes, never in one;
  // the previous offer not taken yet comes back to be destroyed by the caller.
  std::unique_ptr<Recogniser> offer_recogniser(std::unique_ptr<Recogniser> recogniser);
  // Any thread: the recogniser the loop replaced, to be destroyed off the loop thread; null when none.
  std::unique_ptr<Recogniser> take_retired_recogniser();
  [[nodiscard]] std::uint64_t recognisers_swapped() const { return swapped_.load(std::memory_order_relaxed); }
  // A part is being taught: its PLC id, else 0 (any thread).
  [[nodiscard]] std::uint16_t teaching_part_id() const { return teaching_.load(std::memory_order_acquire); }

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

  void loop_thread();
  void apply_realtime();
  void step(Clock::time_point now);
  // loop_pass.cpp
  void step_idle(Clock::time_point now);
  void step_scanning(Clock::time_point now);
  [[nodiscard]] bool drain_frames();
  void start_pass(TriggerSource trigger, Clock::time_point now);
  void finish_scan(Clock::time_point cycle_start);
  void abort_pass(drivers::ErrorCode cause, const char* why);
  void publish_no_part(Clock::time_point at);
  void poll_edges_while_busy();
  // loop_recognise.cpp
  void step_recognising(Clock::time_point now);
  void take_answer(const WorkerAnswer& answer);
  // loop_publish.cpp
  void publish(const algo::Decision& decision, Clock::time_point now, bool aborted);
  [[nodiscard]] PartRecord make_record(const algo::Decision& decision, Clock::time_point now, bool aborted);
  void count_result(const PartRecord& record);
  void log_part(const PartRecord& record) const;
  void log_unknown(const PartRecord& record) const;
  void note_finished();
  // loop_fault.cpp
  void step_fault(Clock::time_point now);
  void fault_wait_recogniser();
  void fault_reload_models(Clock::time_point now, bool forced);
  [[nodiscard]] bool fault_reopen_devices();
  [[nodiscard]] bool fault_probe();
  // loop_commands.cpp
  void handle_commands(const drivers::PlcCommands& commands);
  void handle_sw_triggers(std::uint32_t count, LoopState state);
  void handle_clear_error(LoopState state);
  void handle_exec(const drivers::PlcCommands& commands);
  void handle_screen_command();
  void swap_offered_recogniser();
  [[nodiscard]] bool execute(drivers::CommandCode command, std::uint32_t arg);
  // production_loop.cpp: bookkeeping
  void update_flags();
  [[nodiscard]] bool trigger_allowed() const;
  [[nodiscard]] bool queue_full() const;
  void enter(LoopState next);
  void enter_fault(drivers::ErrorCode cause, const char* why);
  void recover(const char* how);
  void set_error(drivers::ErrorCode code);
  void set_warning(drivers::WarningCode code);
  void count_missed_trigger(const char* why);
  void idle_wait(Clock::time_point since);
  [[nodiscard]] Clock::time_point edge_time(const drivers::EdgeEvent& edge, Clock::time_point seen) const;
  void wake_waiters();

  const LoopConfig config_;
  drivers::Camera& camera_;
  drivers::DigitalIo& io_;
  drivers::Encoder& encoder_;
  drivers::PlcLink& link_;
  algo::ScanBuilder builder_;
  PassAcquirer acquirer_;  // every frame the loop takes goes through it (scanning, draining, the fault probe)
  const std::int32_t exposure_min_us_;
  const std::int32_t exposure_max_us_;
  RecognitionWorker worker_;
  mutable LogQueue log_;  // log_part() is const but queues lines
  LoopObserver* observer_ = nullptr;
  ServiceNotifier* service_ = nullptr;
  ScanKeeper* keeper_ = nullptr;

  // Here and in the next block the members go from the widest to the narrowest: no padding between them.
  std::thread loop_thread_;
  std::atomic<std::int64_t> last_iteration_ns_{0};
  // Rung when finished_ or stop_ change: wait_finished() sleeps on it (a futex; the loop takes no lock to ring).
  std::atomic<std::uint32_t> waiters_bell_{0};
  std::atomic<bool> stop_{false};
  std::atomic<bool> finished_{false};
  std::atomic<LoopState> state_{LoopState::kIdle};
  std::atomic<bool> recogniser_hung_{false};
  // The screen's command mailbox: the poster writes code and argument, then publishes screen_posted_; the loop
  // executes, writes the fate, then publishes screen_done_ = screen_posted_.
  std::atomic<std::uint32_t> screen_posted_{0};
  std::atomic<std::uint32_t> screen_done_{0};
  std::atomic<std::uint32_t> screen_arg_{0};
  std::atomic<std::uint16_t> screen_command_{0};
  std::atomic<bool> screen_ok_{false};
  std::atomic<std::uint16_t> teaching_{0};
  std::atomic<Recogniser*> offered_{nullptr};  // owned; offer_recogniser() -> the loop
  std::atomic<Recogniser*> retired_{nullptr};  // owned; the loop -> take_retired_recogniser()
  std::atomic<std::uint64_t> swapped_{0};

  // Loop thread only.
  Clock::time_point fault_since_{};
  Clock::time_point next_retry_{};
  Clock::time_point cycle_start_{};
  Clock::time_point deadline_{};
  double recognise_ms_ = 0.0;
  std::uint32_t pending_sw_triggers_ = 0;
  std::uint32_t acq_id_ = 0;
  std::uint32_t missed_since_result_ = 0;
  std::uint32_t trigger_count_ = 0;
  std::uint32_t missed_count_ = 0;        // MISSED_TRIGGERS (reset by RESET_COUNTERS)
  std::uint16_t teach_part_id_ = 0;       // teach mode: the PLC id being taught (0: production)
  std::uint16_t pass_teach_part_id_ = 0;  // ... as latched when the pass started (0: a production pass)
  int consecutive_timeouts_ = 0;
  drivers::ErrorCode fault_cause_ = drivers::ErrorCode::kNone;
  drivers::ErrorCode error_ = drivers::ErrorCode::kNone;  // what ERROR_CODE shows
  drivers::WarningCode warning_ = drivers::WarningCode::kNone;
  std::uint16_t flags_ = 0;  // StatusFlag bits as last sent
  TriggerSource pass_trigger_ = TriggerSource::kPartPresent;
  bool flags_sent_ = false;
  bool trigger_enable_ = false;
  bool clear_requested_ = false;
  bool models_reload_requested_ = false;
  bool load_in_flight_ = false;
  bool timeout_published_ = false;  // the deadline passed: "timeout" is out, the recogniser's answer is not wanted
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

}  // namespace cellsight::runtime
