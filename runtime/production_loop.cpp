// The production loop's set-up, its thread, one step of the state machine and the bookkeeping every state shares.
#include "runtime/production_loop.hpp"

#include <cstring>

#include "base/start_thread.hpp"
#include "runtime/futex.hpp"
#include "runtime/loop_internal.hpp"
#include "runtime/plc_mapping.hpp"
#include "runtime/realtime.hpp"
#include "runtime/service_notify.hpp"

namespace cellsight::runtime {

namespace {
// A loop thread silent for longer than this is not healthy (the systemd watchdog is then not petted).
constexpr std::int64_t kHealthyIterationNs = 1'000'000'000;
// An edge stamped more than this before it was seen is not trusted as the cycle start (another clock, a stale edge).
constexpr auto kEdgeTimestampWindow = std::chrono::seconds(1);
}  // namespace

// =================================================================================================== set-up

ProductionLoop::ProductionLoop(const LoopConfig& config, drivers::Camera& camera, drivers::DigitalIo& io,
                               drivers::Encoder& encoder, const algo::ScanBuilderParams& scan_params,
                               const algo::SensorCalibration& calibration, drivers::PlcLink& link)
    : config_(config),
      camera_(camera),
      io_(io),
      encoder_(encoder),
      link_(link),
      builder_(scan_params, calibration),
      acquirer_(
          camera, io, encoder, builder_,
          AcquirerParams{config.frame_timeout_ms, config.max_frames, config.start_exposure_us, config.poll_slice_ms}),
      exposure_min_us_(scan_params.exposure.exposure_min_us),
      exposure_max_us_(scan_params.exposure.exposure_max_us),
      log_(config.log_queue_lines) {}

ProductionLoop::~ProductionLoop() {
  request_stop();
  join();
  delete offered_.exchange(nullptr);  // offered or replaced recognisers nobody took
  delete retired_.exchange(nullptr);
}

void ProductionLoop::set_recogniser(std::unique_ptr<Recogniser> recogniser) {
  worker_.set_recogniser(std::move(recogniser));
}
void ProductionLoop::set_recogniser_loader(RecogniserLoader loader) {
  worker_.set_loader(std::move(loader));
}
void ProductionLoop::set_observer(LoopObserver* observer) {
  observer_ = observer;
}
void ProductionLoop::set_service(ServiceNotifier* service) {
  service_ = service;
}

void ProductionLoop::set_keeper(ScanKeeper* keeper, bool keep_unknown) {
  keeper_ = keeper;
  worker_.set_keeper(keeper, keep_unknown);
}

Status ProductionLoop::start() {
  if (loop_thread_.joinable()) return make_error("production loop: start() called twice");
  if (config_.deadline_ms <= 0 || config_.frame_timeout_ms <= 0 || config_.poll_slice_ms <= 0 ||
      config_.max_frames <= 0) {
    return make_error("production loop: runtime.deadline_ms, camera.timeout_ms and the frame limits must be > 0");
  }
  if (config_.lock_memory) {
    if (const int err = lock_all_memory(); err == 0) {
      memory_locked_.store(true);
      CS_LOG_INFO(kComponent, "memory locked (mlockall)");
    } else {
      CS_LOG_WARN(kComponent,
                  "runtime.lock_memory: mlockall failed: %s (the unit needs LimitMEMLOCK=infinity or "
                  "CAP_IPC_LOCK); running without locked memory",
                  std::strerror(err));
    }
  }
  link_.set_active_models(config_.active_models_id);
  link_.set_trigger_counters(0, 0);
  link_.set_warning(WarningCode::kNone);
  link_.set_error(ErrorCode::kNone);
  const auto now = Clock::now();
  last_iteration_ns_.store(to_ns(now));
  next_retry_ = now;
  if (!worker_.has_recogniser())
    enter_fault(ErrorCode::kModelDatabaseInvalid, "no recogniser (model database not loaded)");
  Status started = log_.start_writer();
  if (started) started = worker_.start();
  if (started) started = base::start_thread(loop_thread_, "cs-loop", [this] { loop_thread(); });
  if (!started) {
    request_stop();
    join();
    return make_error("production loop: " + started.error().message);
  }
  return {};
}

void ProductionLoop::request_stop() {
  stop_.store(true, std::memory_order_release);
  wake_waiters();
}

void ProductionLoop::join() {
  if (loop_thread_.joinable()) loop_thread_.join();
  worker_.stop();
  log_.stop_writer();  // after the loop thread: its last lines are written too
}

void ProductionLoop::wake_waiters() {
  futex_ring(waiters_bell_);
}

bool ProductionLoop::wait_finished(std::chrono::milliseconds timeout) {
  const Clock::time_point until = Clock::now() + timeout;
  for (;;) {
    const std::uint32_t bell = waiters_bell_.load(std::memory_order_acquire);
    if (finished_.load(std::memory_order_acquire) || stop_.load(std::memory_order_acquire)) break;
    const Clock::time_point now = Clock::now();
    if (now >= until) break;
    futex_wait(waiters_bell_, bell, until - now);
  }
  return finished_.load(std::memory_order_acquire);
}

bool ProductionLoop::healthy() const {
  if (recogniser_hung_.load(std::memory_order_acquire)) return false;
  const std::int64_t last = last_iteration_ns_.load(std::memory_order_acquire);
  return to_ns(Clock::now()) - last < kHealthyIterationNs;
}

LoopStats ProductionLoop::stats() const {
  LoopStats s;
  s.state = state();
  s.error = static_cast<ErrorCode>(error_now_.load(std::memory_order_relaxed));
  s.warning = static_cast<WarningCode>(warning_now_.load(std::memory_order_relaxed));
  s.iterations = iterations_.load(std::memory_order_relaxed);
  s.triggers = triggers_.load(std::memory_order_relaxed);
  s.results = results_.load(std::memory_order_relaxed);
  s.results_rejected = rejected_.load(std::memory_order_relaxed);
  s.timeouts = timeouts_.load(std::memory_order_relaxed);
  s.aborted_scans = aborted_.load(std::memory_order_relaxed);
  s.missed_triggers = missed_.load(std::memory_order_relaxed);
  s.faults = faults_.load(std::memory_order_relaxed);
  s.recoveries = recoveries_.load(std::memory_order_relaxed);
  s.late_decisions = late_decisions_.load(std::memory_order_relaxed);
  s.log_lines_dropped = log_.dropped();
  s.last_cycle_ms = last_cycle_ms_.load(std::memory_order_relaxed);
  s.max_cycle_ms = max_cycle_ms_.load(std::memory_order_relaxed);
  s.realtime_applied = realtime_applied_.load(std::memory_order_relaxed);
  s.memory_locked = memory_locked_.load(std::memory_order_relaxed);
  return s;
}

// =================================================================================================== the thread

void ProductionLoop::apply_realtime() {
  if (config_.realtime_priority <= 0) return;
  if (const int rc = set_thread_fifo(config_.realtime_priority); rc == 0) {
    realtime_applied_.store(true);
    CS_QLOG_INFO(log_, kComponent, "loop thread runs SCHED_FIFO priority %d", config_.realtime_priority);
  } else {
    CS_QLOG_WARN(log_, kComponent,
                 "runtime.realtime_priority %d: pthread_setschedparam failed: %s (the unit needs "
                 "CPUSchedulingPolicy/LimitRTPRIO or CAP_SYS_NICE); running with normal scheduling",
                 config_.realtime_priority, std::strerror(rc));
  }
}

void ProductionLoop::loop_thread() {
  apply_realtime();
  prefault_stack();
  while (!stop_.load(std::memory_order_acquire)) step(Clock::now());
  (void)io_.set(drivers::Output::kLaserEnable, false);
  link_.set_flag(drivers::StatusFlag::kReady, false);
  link_.set_flag(drivers::StatusFlag::kTriggerReady, false);
  link_.set_flag(drivers::StatusFlag::kBusy, false);
  link_.set_flag(drivers::StatusFlag::kTriggerAck, false);
  enter(LoopState::kStopped);
}

void ProductionLoop::step(Clock::time_point now) {
  iterations_.fetch_add(1, std::memory_order_relaxed);
  last_iteration_ns_.store(to_ns(now), std::memory_order_release);
  link_.heartbeat();
  if (service_ != nullptr && healthy()) service_->pet_watchdog(to_ns(now));
  handle_commands(link_.take_commands());
  switch (state_.load(std::memory_order_relaxed)) {
    case LoopState::kIdle: step_idle(now); break;
    case LoopState::kScanning: step_scanning(now); break;
    case LoopState::kRecognising: step_recognising(now); break;
    case LoopState::kFault: step_fault(now); break;
    case LoopState::kPublishing:  // transient inside publish(); never seen here
    case LoopState::kStopped: enter(LoopState::kIdle); break;
  }
  update_flags();
}

// =================================================================================================== bookkeeping

bool ProductionLoop::queue_full() const {
  return link_.stats().queue_depth >= config_.result_queue_capacity;
}

bool ProductionLoop::trigger_allowed() const {
  TriggerGate gate;
  gate.state = state_.load(std::memory_order_relaxed);
  gate.has_recogniser = worker_.has_recogniser();
  gate.finished = finished_.load(std::memory_order_relaxed);
  gate.require_trigger_enable = config_.require_trigger_enable;
  gate.trigger_enable = trigger_enable_;
  gate.hold_when_queue_full = config_.hold_when_queue_full;
  // Asked only when it matters: the link's stats are not free.
  gate.queue_full = gate.state == LoopState::kIdle && config_.hold_when_queue_full && queue_full();
  return runtime::trigger_allowed(gate);
}

void ProductionLoop::update_flags() {
  const std::uint16_t flags = loop_status_flags(state_.load(std::memory_order_relaxed), trigger_allowed(),
                                                timeout_published_, teach_part_id_ != 0);
  for (const auto flag : kLoopStatusFlags) {
    const auto bit = static_cast<std::uint16_t>(flag);
    if (!flags_sent_ || ((flags ^ flags_) & bit) != 0) link_.set_flag(flag, (flags & bit) != 0);
  }
  flags_ = flags;
  flags_sent_ = true;
}

void ProductionLoop::idle_wait(Clock::time_point since) {
  const Clock::time_point until = since + std::chrono::milliseconds(config_.poll_slice_ms);
  if (Clock::now() < until) std::this_thread::sleep_until(until);
}

ProductionLoop::Clock::time_point ProductionLoop::edge_time(const drivers::EdgeEvent& edge,
                                                            Clock::time_point seen) const {
  if (config_.edge_timestamps_monotonic) {
    const Clock::time_point stamped{std::chrono::nanoseconds(edge.timestamp_ns)};
    if (stamped <= seen && seen - stamped < kEdgeTimestampWindow) return stamped;
  }
  return seen;
}

void ProductionLoop::enter(LoopState next) {
  const LoopState from = state_.exchange(next, std::memory_order_acq_rel);
  if (from == next) return;
  CS_QLOG_DEBUG(log_, kComponent, "%s -> %s", to_string(from), to_string(next));
  if (observer_ != nullptr) observer_->on_state(from, next, error_);
}

void ProductionLoop::enter_fault(ErrorCode cause, const char* why) {
  (void)io_.set(drivers::Output::kLaserEnable, false);
  fault_cause_ = cause;
  set_error(cause);
  faults_.fetch_add(1, std::memory_order_relaxed);
  fault_since_ = Clock::now();
  next_retry_ =
      fault_since_ + std::chrono::milliseconds(cause == ErrorCode::kModelDatabaseInvalid ? config_.models_retry_ms
                                                                                         : config_.retry_interval_ms);
  CS_QLOG_ERROR(log_, kComponent, "fault: %s (%s); ERROR_CODE %u", drivers::to_string(cause), why,
                static_cast<unsigned>(cause));
  enter(LoopState::kFault);
}

void ProductionLoop::recover(const char* how) {
  recoveries_.fetch_add(1, std::memory_order_relaxed);
  CS_QLOG_INFO(log_, kComponent, "recovered from %s after %.1f s: %s", drivers::to_string(fault_cause_),
               ms_between(fault_since_, Clock::now()) / 1e3, how);
  fault_cause_ = ErrorCode::kNone;
  acquirer_.clear_camera_failed();
  clear_requested_ = false;
  consecutive_timeouts_ = 0;
  set_error(ErrorCode::kNone);
  enter(LoopState::kIdle);
}

void ProductionLoop::set_error(ErrorCode code) {
  if (code == error_) return;
  error_ = code;
  error_now_.store(static_cast<std::uint16_t>(code), std::memory_order_relaxed);
  link_.set_error(code);
}

void ProductionLoop::set_warning(WarningCode code) {
  if (code == warning_) return;
  warning_ = code;
  warning_now_.store(static_cast<std::uint16_t>(code), std::memory_order_relaxed);
  link_.set_warning(code);
}

void ProductionLoop::count_missed_trigger(const char* why) {
  missed_.fetch_add(1, std::memory_order_relaxed);
  ++missed_count_;
  ++missed_since_result_;
  link_.set_trigger_counters(trigger_count_, missed_count_);
  set_warning(WarningCode::kMissedTrigger);
  CS_QLOG_WARN(log_, kComponent, "missed trigger: %s", why);
}

}  // namespace cellsight::runtime
