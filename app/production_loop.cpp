// The production loop's state machine, its two threads and the decision -> PLC result mapping.
#include "app/production_loop.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <time.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <numbers>
#include <system_error>

#include "app/service_notify.hpp"
#include "drivers/log.hpp"

namespace cellsight::app {

using drivers::DeviceStatus;
using drivers::ErrorCode;
using drivers::WarningCode;
using drivers::modbus_map::kInvalidS32;

namespace {

constexpr const char* kComponent = "loop";
constexpr std::int64_t kNsPerUs = 1000;
constexpr double kNsPerMs = 1e6;
constexpr double kPermille = 1000.0;
constexpr double kDegPerRad = 180.0 / std::numbers::pi;
constexpr double kMaxCycleMs = 65535.0;  // CYCLE_MS is a u16
constexpr int kMaxDrainedFramesPerStep = 8;
// A loop thread silent for longer than this is not healthy (the systemd watchdog is then not petted).
constexpr std::int64_t kHealthyIterationNs = 1'000'000'000;
// An edge stamped more than this before it was seen is not trusted as the cycle start (another clock, a stale edge).
constexpr auto kEdgeTimestampWindow = std::chrono::seconds(1);
// Stack the loop thread touches at start so its page faults happen before the first part (with mlockall).
constexpr std::size_t kStackPrefaultBytes = 64 * 1024;
// Headroom over the nominal frames of one pass before the photo-eye counts as blocked.
constexpr double kMaxFramesFactor = 1.5;
constexpr int kMaxFramesMargin = 16;

std::int64_t to_ns(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count();
}

double ms_between(std::chrono::steady_clock::time_point from, std::chrono::steady_clock::time_point to) {
  return static_cast<double>(std::chrono::duration_cast<std::chrono::nanoseconds>(to - from).count()) / kNsPerMs;
}

std::uint64_t monotonic_us() {
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<std::uint64_t>(now.tv_sec) * 1'000'000u + static_cast<std::uint64_t>(now.tv_nsec / kNsPerUs);
}

[[gnu::noinline]] void prefault_stack() {
  volatile char stack[kStackPrefaultBytes];
  for (std::size_t i = 0; i < sizeof stack; i += 4096) stack[i] = 0;
}

algo::Decision decision_of(algo::DecisionSource source) {
  algo::Decision d;
  d.source = source;
  return d;
}

const char* trigger_name(TriggerSource trigger) {
  return trigger == TriggerSource::kSoftware ? "SW_TRIGGER" : "part-present";
}

}  // namespace

LoopConfig loop_config(const Config& config) {
  LoopConfig c;
  c.deadline_ms = config.runtime.deadline_ms;
  c.frame_timeout_ms = config.camera.timeout_ms;
  const auto& conveyor = config.rig.conveyor;
  const double frames_per_pass =
      config.rig.carrier.length_m * 1e3 * conveyor.counts_per_mm / std::max(1, conveyor.trigger_every_counts);
  c.max_frames = static_cast<int>(std::ceil(frames_per_pass * kMaxFramesFactor)) + kMaxFramesMargin;
  c.start_exposure_us = static_cast<std::int32_t>(std::lround(config.camera.exposure_us));
  c.cycle_slow_ms = config.runtime.deadline_ms / 2.0;
  c.realtime_priority = config.runtime.realtime_priority;
  c.lock_memory = config.runtime.lock_memory;
  c.result_queue_capacity = static_cast<std::size_t>(std::max(1, config.modbus.result_queue_depth));
  c.edge_timestamps_monotonic = config.gpio.backend != "sim";
  return c;
}

drivers::PlcResult to_plc_result(const algo::Decision& decision, std::uint32_t acq_id, std::uint64_t timestamp_us,
                                 double cycle_ms) {
  using drivers::ResultCode;
  using drivers::ResultSource;
  drivers::PlcResult r;
  r.acq_id = acq_id;
  r.timestamp_us = timestamp_us;
  r.cycle_ms = static_cast<std::uint16_t>(
      std::lround(std::clamp(std::isfinite(cycle_ms) ? cycle_ms : kMaxCycleMs, 0.0, kMaxCycleMs)));
  const auto permille = [](double p) {
    if (!std::isfinite(p)) return std::uint16_t{0};
    return static_cast<std::uint16_t>(std::lround(std::clamp(p, 0.0, 1.0) * kPermille));
  };
  switch (decision.source) {
    case algo::DecisionSource::kSvm:
    case algo::DecisionSource::kPm: {
      r.source = decision.source == algo::DecisionSource::kSvm ? ResultSource::kSvm : ResultSource::kPerfectMatch;
      r.part_id = static_cast<std::uint16_t>(std::clamp(decision.part_id, 0, 0xFFFF));
      r.confidence_permille = permille(decision.probability);
      const std::int32_t x_um = drivers::to_plc_micrometres(decision.pose.x_m);
      const std::int32_t y_um = drivers::to_plc_micrometres(decision.pose.y_m);
      const std::int32_t rz_mdeg = drivers::to_plc_millidegrees(decision.pose.theta_rad * kDegPerRad);
      if (!decision.pose_valid || x_um == kInvalidS32 || y_um == kInvalidS32 || rz_mdeg == kInvalidS32) {
        r.code = ResultCode::kPoseOutOfRange;  // a class without a usable pose is no instruction for the robot
        return r;
      }
      r.code = ResultCode::kOk;
      r.x_um = x_um;
      r.y_um = y_um;
      r.z_um = 0;  // DESIGN.md: Z 0 until estimated; the planar pose has no RX, RY either
      r.rx_mdeg = 0;
      r.ry_mdeg = 0;
      r.rz_mdeg = rz_mdeg;
      return r;
    }
    case algo::DecisionSource::kUnknown:
      r.code = ResultCode::kUnknownPart;
      r.confidence_permille = permille(decision.probability);
      return r;
    case algo::DecisionSource::kTimeout:
      r.code = ResultCode::kTimeout;
      return r;
    case algo::DecisionSource::kBadScan:
      r.code = ResultCode::kBadScan;
      return r;
    case algo::DecisionSource::kNoPart:
      r.code = ResultCode::kNoPart;
      return r;
  }
  r.code = ResultCode::kBadScan;
  return r;
}

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
      exposure_min_us_(scan_params.exposure.exposure_min_us),
      exposure_max_us_(scan_params.exposure.exposure_max_us) {}

ProductionLoop::~ProductionLoop() {
  request_stop();
  join();
}

void ProductionLoop::set_recogniser(std::unique_ptr<Recogniser> recogniser) {
  recogniser_ = std::move(recogniser);
  has_recogniser_.store(recogniser_ != nullptr, std::memory_order_release);
}

void ProductionLoop::set_recogniser_loader(RecogniserLoader loader) {
  loader_ = std::move(loader);
}
void ProductionLoop::set_observer(LoopObserver* observer) {
  observer_ = observer;
}
void ProductionLoop::set_service(ServiceNotifier* service) {
  service_ = service;
}

Status ProductionLoop::start() {
  if (loop_thread_.joinable()) return make_error("production loop: start() called twice");
  if (config_.deadline_ms <= 0 || config_.frame_timeout_ms <= 0 || config_.poll_slice_ms <= 0 ||
      config_.max_frames <= 0) {
    return make_error("production loop: runtime.deadline_ms, camera.timeout_ms and the frame limits must be > 0");
  }
  if (config_.lock_memory) {
    if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
      memory_locked_.store(true);
      CS_LOG_INFO(kComponent, "memory locked (mlockall)");
    } else {
      const int err = errno;
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
  if (!has_recogniser_.load(std::memory_order_acquire)) {
    enter_fault(ErrorCode::kModelDatabaseInvalid, "no recogniser (model database not loaded)");
  }
  try {
    worker_thread_ = std::thread([this] { worker_thread(); });
    loop_thread_ = std::thread([this] { loop_thread(); });
  } catch (const std::system_error& error) {
    request_stop();
    join();
    return make_error(std::string("production loop: cannot start its threads: ") + error.what());
  }
  return {};
}

void ProductionLoop::request_stop() {
  stop_.store(true, std::memory_order_release);
  { std::lock_guard lock(finished_mutex_); }
  finished_cv_.notify_all();
}

void ProductionLoop::join() {
  if (loop_thread_.joinable()) loop_thread_.join();
  {
    std::lock_guard lock(worker_mutex_);
    worker_exit_ = true;
  }
  job_cv_.notify_all();
  if (worker_thread_.joinable()) worker_thread_.join();
}

bool ProductionLoop::wait_finished(std::chrono::milliseconds timeout) {
  std::unique_lock lock(finished_mutex_);
  finished_cv_.wait_for(lock, timeout, [this] { return finished_.load() || stop_.load(); });
  return finished_.load();
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
  s.last_cycle_ms = last_cycle_ms_.load(std::memory_order_relaxed);
  s.max_cycle_ms = max_cycle_ms_.load(std::memory_order_relaxed);
  s.realtime_applied = realtime_applied_.load(std::memory_order_relaxed);
  s.memory_locked = memory_locked_.load(std::memory_order_relaxed);
  return s;
}

// =================================================================================================== threads

void ProductionLoop::loop_thread() {
  if (config_.realtime_priority > 0) {
    sched_param param{};
    param.sched_priority = config_.realtime_priority;
    const int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
    if (rc == 0) {
      realtime_applied_.store(true);
      CS_LOG_INFO(kComponent, "loop thread runs SCHED_FIFO priority %d", config_.realtime_priority);
    } else {
      CS_LOG_WARN(kComponent,
                  "runtime.realtime_priority %d: pthread_setschedparam failed: %s (the unit needs "
                  "CPUSchedulingPolicy/LimitRTPRIO or CAP_SYS_NICE); running with normal scheduling",
                  config_.realtime_priority, std::strerror(rc));
    }
  }
  prefault_stack();
  while (!stop_.load(std::memory_order_acquire)) step(Clock::now());
  (void)io_.set(drivers::Output::kLaserEnable, false);
  link_.set_flag(drivers::StatusFlag::kReady, false);
  link_.set_flag(drivers::StatusFlag::kTriggerReady, false);
  link_.set_flag(drivers::StatusFlag::kBusy, false);
  link_.set_flag(drivers::StatusFlag::kTriggerAck, false);
  enter(LoopState::kStopped);
}

void ProductionLoop::worker_thread() {
  for (;;) {
    std::unique_lock lock(worker_mutex_);
    job_cv_.wait(lock, [this] { return job_ != Job::kNone || worker_exit_; });
    if (job_ == Job::kNone) return;  // exit requested with nothing to do
    const Job job = job_;
    const Clock::time_point deadline = job_deadline_;
    lock.unlock();

    algo::Decision decision;
    bool load_ok = false;
    if (job == Job::kRecognise) {
      if (recogniser_ != nullptr) {
        decision = recogniser_->recognise(builder_.scan().points(), deadline);
      } else {
        decision.source = algo::DecisionSource::kUnknown;
      }
    } else if (job == Job::kLoad && loader_) {
      auto loaded = loader_();
      if (loaded) {
        recogniser_ = std::move(*loaded);
        load_ok = recogniser_ != nullptr;
        has_recogniser_.store(load_ok, std::memory_order_release);
      } else {
        CS_LOG_ERROR(kComponent, "model database: %s", loaded.error().message.c_str());
      }
    }
    const Clock::time_point finished_at = Clock::now();

    lock.lock();
    job_decision_ = decision;
    job_finished_at_ = finished_at;
    load_ok_ = load_ok;
    job_finished_ = true;
    job_ = Job::kNone;
    lock.unlock();
    done_cv_.notify_all();
  }
}

void ProductionLoop::post_job(Job job) {
  {
    std::lock_guard lock(worker_mutex_);
    job_ = job;
    job_finished_ = false;
    job_deadline_ = deadline_;
    job_posted_at_ = Clock::now();
  }
  job_cv_.notify_one();
}

// =================================================================================================== one step

void ProductionLoop::step(Clock::time_point now) {
  iterations_.fetch_add(1, std::memory_order_relaxed);
  last_iteration_ns_.store(to_ns(now), std::memory_order_release);
  link_.heartbeat();
  if (service_ != nullptr && healthy()) service_->pet_watchdog(to_ns(now));
  handle_commands(link_.take_commands(), now);
  switch (state_.load(std::memory_order_relaxed)) {
    case LoopState::kIdle:
      step_idle(now);
      break;
    case LoopState::kScanning:
      step_scanning(now);
      break;
    case LoopState::kRecognising:
      step_recognising(now);
      break;
    case LoopState::kFault:
      step_fault(now);
      break;
    case LoopState::kPublishing:  // transient inside publish(); never seen here
    case LoopState::kStopped:
      enter(LoopState::kIdle);
      break;
  }
  update_flags();
}

void ProductionLoop::handle_commands(const drivers::PlcCommands& commands, Clock::time_point /*now*/) {
  trigger_enable_ = commands.trigger_enable;
  const LoopState state = state_.load(std::memory_order_relaxed);
  if (commands.sw_triggers > 0) {
    if (state == LoopState::kIdle) {
      pending_sw_triggers_ += commands.sw_triggers;
    } else if (state == LoopState::kScanning || state == LoopState::kRecognising) {
      for (std::uint32_t i = 0; i < commands.sw_triggers; ++i) count_missed_trigger("SW_TRIGGER while busy");
    } else {
      CS_LOG_WARN(kComponent, "SW_TRIGGER ignored: %s", to_string(state));
    }
  }
  if (commands.clear_errors > 0) {
    CS_LOG_INFO(kComponent, "CLEAR_ERROR from the PLC");
    if (state == LoopState::kFault) {
      clear_requested_ = true;
    } else {
      consecutive_timeouts_ = 0;
      if (error_ == ErrorCode::kRepeatedTimeouts) set_error(ErrorCode::kNone);
      set_warning(WarningCode::kNone);
    }
  }
  if (commands.exec_command) {
    using drivers::CommandCode;
    bool ok = false;
    switch (commands.command) {
      case CommandCode::kResetCounters:
        trigger_count_ = 0;
        missed_count_ = 0;
        link_.set_trigger_counters(0, 0);
        ok = true;
        break;
      case CommandCode::kSelectModels:
        // One model database per cellsight process: selecting the active one (again) retries loading it.
        ok = commands.command_arg == config_.active_models_id;
        if (ok && fault_cause_ == ErrorCode::kModelDatabaseInvalid) models_reload_requested_ = true;
        break;
      case CommandCode::kEnterTeach:
      case CommandCode::kLeaveTeach:  // teaching is `cellsight teach`, not the production loop
      case CommandCode::kNone:
        ok = false;
        break;
    }
    CS_LOG_INFO(kComponent, "command %u (arg %u) from the PLC: %s", static_cast<unsigned>(commands.command_raw),
                static_cast<unsigned>(commands.command_arg), ok ? "done" : "refused");
    link_.complete_command(ok);
  }
}

bool ProductionLoop::queue_full() const {
  return link_.stats().queue_depth >= config_.result_queue_capacity;
}

bool ProductionLoop::trigger_allowed() const {
  if (state_.load(std::memory_order_relaxed) != LoopState::kIdle) return false;
  if (!has_recogniser_.load(std::memory_order_acquire) || finished_.load(std::memory_order_relaxed)) return false;
  if (config_.require_trigger_enable && !trigger_enable_) return false;
  return !(config_.hold_when_queue_full && queue_full());
}

void ProductionLoop::update_flags() {
  const LoopState state = state_.load(std::memory_order_relaxed);
  const bool in_pass = state == LoopState::kScanning || (state == LoopState::kRecognising && !timeout_published_);
  const bool busy = state == LoopState::kScanning || state == LoopState::kRecognising;
  std::uint16_t flags = 0;
  const auto put = [&flags](drivers::StatusFlag flag, bool on) {
    if (on) flags = static_cast<std::uint16_t>(flags | static_cast<std::uint16_t>(flag));
  };
  put(drivers::StatusFlag::kReady, state != LoopState::kFault && state != LoopState::kStopped);
  put(drivers::StatusFlag::kTriggerReady, trigger_allowed());
  put(drivers::StatusFlag::kTriggerAck, in_pass);
  put(drivers::StatusFlag::kBusy, busy);
  for (const auto flag : {drivers::StatusFlag::kReady, drivers::StatusFlag::kTriggerReady,
                          drivers::StatusFlag::kTriggerAck, drivers::StatusFlag::kBusy}) {
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

// ------------------------------------------------------------------------------------------------- idle

void ProductionLoop::step_idle(Clock::time_point now) {
  if (trigger_allowed()) {
    if (pending_sw_triggers_ > 0) {
      --pending_sw_triggers_;
      start_pass(TriggerSource::kSoftware, now);
      return;
    }
  } else {
    if (pending_sw_triggers_ > 0) {
      CS_LOG_WARN(kComponent, "SW_TRIGGER ignored: not ready for a part (TRIGGER_READY is off)");
      pending_sw_triggers_ = 0;
    }
    if (config_.conveyor_waits_for_ready) {
      idle_wait(now);
      return;
    }
  }
  if (drain_frames() == kMaxDrainedFramesPerStep) return;  // frames of a part that is not scanned: keep draining
  if (state_.load(std::memory_order_relaxed) != LoopState::kIdle) return;  // the camera failed
  drivers::EdgeEvent edge;
  const DeviceStatus status = io_.wait_edge(edge, config_.poll_slice_ms);
  if (status == DeviceStatus::kTimeout) {
    idle_wait(now);  // a device that does not wait (the simulated cell) must not make this a busy loop
    return;
  }
  if (status != DeviceStatus::kOk) {
    enter_fault(ErrorCode::kIoFault, "part-present input failed");
    return;
  }
  if (edge.edge != drivers::Edge::kRising) return;  // the end of a part that was not scanned
  if (trigger_allowed()) {
    start_pass(TriggerSource::kPartPresent, edge_time(edge, Clock::now()));
  } else if (has_recogniser_.load(std::memory_order_acquire) && !finished_.load() &&
             (!config_.require_trigger_enable || trigger_enable_)) {
    count_missed_trigger("result queue full");
  } else {
    CS_LOG_DEBUG(kComponent, "part passes unscanned: triggers not enabled by the PLC");
  }
}

int ProductionLoop::drain_frames() {
  int drained = 0;
  while (drained < kMaxDrainedFramesPerStep) {
    drivers::Frame frame;
    const DeviceStatus status = camera_.grab(frame, 0);
    if (status == DeviceStatus::kOk) {
      camera_.release(frame);
      ++drained;
      continue;
    }
    if (status != DeviceStatus::kTimeout) {
      camera_needs_reopen_ = true;
      enter_fault(ErrorCode::kCameraFault, to_string(status));
    }
    break;
  }
  return drained;
}

void ProductionLoop::start_pass(TriggerSource trigger, Clock::time_point now) {
  std::int64_t start_counts = 0;
  if (encoder_.read_counts(start_counts) != DeviceStatus::kOk) {
    enter_fault(ErrorCode::kEncoderFault, "encoder unreadable at the start of a pass");
    return;
  }
  if (io_.set(drivers::Output::kLaserEnable, true) != DeviceStatus::kOk) {
    enter_fault(ErrorCode::kIoFault, "cannot switch the laser on");
    return;
  }
  if (camera_.set_exposure_us(config_.start_exposure_us) != DeviceStatus::kOk) {
    camera_needs_reopen_ = true;
    enter_fault(ErrorCode::kCameraFault, "cannot set the start exposure");
    return;
  }
  builder_.begin_pass(start_counts, config_.start_exposure_us);
  acq_id_ = acq_id_ + 1 == 0 ? 1 : acq_id_ + 1;
  ++trigger_count_;
  link_.set_trigger_counters(trigger_count_, missed_count_);
  triggers_.fetch_add(1, std::memory_order_relaxed);
  pass_trigger_ = trigger;
  frames_ = 0;
  last_frame_at_ = now;
  timeout_published_ = false;
  exposure_at_limit_ = false;
  CS_LOG_DEBUG(kComponent, "acq %u: pass started (%s)", acq_id_, trigger_name(trigger));
  if (observer_ != nullptr) observer_->on_pass_started(acq_id_, trigger);
  enter(LoopState::kScanning);
}

// ------------------------------------------------------------------------------------------------- scanning

void ProductionLoop::step_scanning(Clock::time_point now) {
  drivers::Frame frame;
  const DeviceStatus grabbed = camera_.grab(frame, config_.poll_slice_ms);
  const Clock::time_point after = Clock::now();
  if (grabbed == DeviceStatus::kOk) {
    std::int64_t counts = 0;
    if (encoder_.read_counts(counts) != DeviceStatus::kOk) {
      camera_.release(frame);
      abort_pass(ErrorCode::kEncoderFault, "encoder unreadable while a part passes");
      return;
    }
    const algo::FrameOutcome outcome =
        builder_.add_frame(frame.data, frame.width_px, frame.height_px, frame.stride_bytes, frame.exposure_us, counts);
    camera_.release(frame);
    last_frame_at_ = after;
    if (observer_ != nullptr) observer_->on_frame(acq_id_, frames_);
    ++frames_;
    if (outcome.exposure.exposure_us != frame.exposure_us &&
        camera_.set_exposure_us(outcome.exposure.exposure_us) != DeviceStatus::kOk) {
      camera_needs_reopen_ = true;
      abort_pass(ErrorCode::kCameraFault, "cannot set the exposure");
      return;
    }
    if (frames_ > config_.max_frames) {
      abort_pass(ErrorCode::kIoFault, "part-present never fell (photo-eye blocked?)");
      return;
    }
  } else if (grabbed != DeviceStatus::kTimeout) {
    camera_needs_reopen_ = true;
    abort_pass(ErrorCode::kCameraFault, to_string(grabbed));
    return;
  }

  drivers::EdgeEvent edge;
  const DeviceStatus edge_status = io_.wait_edge(edge, 0);
  if (edge_status == DeviceStatus::kOk && edge.edge == drivers::Edge::kFalling) {
    finish_scan(edge_time(edge, Clock::now()));
    return;
  }
  if (edge_status != DeviceStatus::kOk && edge_status != DeviceStatus::kTimeout) {
    abort_pass(ErrorCode::kIoFault, "part-present input failed");
    return;
  }
  if (grabbed != DeviceStatus::kTimeout) return;
  if (after - last_frame_at_ >= std::chrono::milliseconds(config_.frame_timeout_ms)) {
    bool present = true;
    const DeviceStatus read = io_.read(drivers::Input::kPartPresent, present);
    if (frames_ == 0 && pass_trigger_ == TriggerSource::kSoftware && read == DeviceStatus::kOk && !present) {
      // A SW_TRIGGER with nothing in front of the sensor: the honest answer is "no part", not a fault.
      (void)io_.set(drivers::Output::kLaserEnable, false);
      cycle_start_ = after;
      enter(LoopState::kPublishing);
      publish(decision_of(algo::DecisionSource::kNoPart), Clock::now(), false);
      enter(LoopState::kIdle);
      return;
    }
    abort_pass(ErrorCode::kCameraTimeout, "no frame while a part is in front of the camera");
    return;
  }
  idle_wait(now);
}

void ProductionLoop::finish_scan(Clock::time_point cycle_start) {
  if (io_.set(drivers::Output::kLaserEnable, false) != DeviceStatus::kOk) {
    CS_LOG_WARN(kComponent, "acq %u: cannot switch the laser off", acq_id_);
  }
  const algo::PassStats& pass = builder_.stats();
  const std::int32_t exposure = builder_.exposure_us();
  exposure_at_limit_ = (exposure <= exposure_min_us_ || exposure >= exposure_max_us_) &&
                       pass.frames_in_band * 2 < pass.frames_with_stripe;
  cycle_start_ = cycle_start;
  deadline_ = cycle_start + std::chrono::milliseconds(config_.deadline_ms);
  post_job(Job::kRecognise);
  enter(LoopState::kRecognising);
}

void ProductionLoop::abort_pass(ErrorCode cause, const char* why) {
  (void)io_.set(drivers::Output::kLaserEnable, false);
  aborted_.fetch_add(1, std::memory_order_relaxed);
  CS_LOG_ERROR(kComponent, "acq %u: scan aborted after %d frames: %s", acq_id_, frames_, why);
  // ERROR first, so the PLC never takes the aborted part's "bad scan" for a fresh result before it sees the fault.
  set_error(cause);
  const Clock::time_point now = Clock::now();
  cycle_start_ = now;
  enter(LoopState::kPublishing);
  publish(decision_of(algo::DecisionSource::kBadScan), now, true);
  enter_fault(cause, why);
}

// ------------------------------------------------------------------------------------------------- recognising

void ProductionLoop::step_recognising(Clock::time_point now) {
  bool done = false;
  algo::Decision decision;
  Clock::time_point finished_at{};
  Clock::time_point posted_at{};
  {
    std::unique_lock lock(worker_mutex_);
    Clock::time_point until = now + std::chrono::milliseconds(config_.poll_slice_ms);
    if (!timeout_published_) until = std::min(until, deadline_);
    done_cv_.wait_until(lock, until, [this] { return job_finished_; });
    if (job_finished_) {
      done = true;
      decision = job_decision_;
      finished_at = job_finished_at_;
      posted_at = job_posted_at_;
    }
  }
  if (done) {
    if (timeout_published_) {
      late_decisions_.fetch_add(1, std::memory_order_relaxed);
      CS_LOG_WARN(kComponent, "acq %u: the recogniser answered %.0f ms after the deadline; its answer is discarded",
                  acq_id_, ms_between(deadline_, finished_at));
      timeout_published_ = false;
      enter(LoopState::kIdle);
      return;
    }
    if (finished_at > deadline_ || decision.source == algo::DecisionSource::kTimeout) {
      if (decision.source != algo::DecisionSource::kTimeout) late_decisions_.fetch_add(1, std::memory_order_relaxed);
      decision = decision_of(algo::DecisionSource::kTimeout);  // never a guess
    }
    recognise_ms_ = ms_between(posted_at, finished_at);
    enter(LoopState::kPublishing);
    publish(decision, Clock::now(), false);
    enter(LoopState::kIdle);
    return;
  }
  const Clock::time_point t = Clock::now();
  if (!timeout_published_ && t >= deadline_) {
    // The PLC gets "timeout" at the deadline, whatever the recogniser does; the scan buffer stays its own until it
    // returns, so the next part waits for that.
    recognise_ms_ = ms_between(cycle_start_, t);
    enter(LoopState::kPublishing);
    publish(decision_of(algo::DecisionSource::kTimeout), t, false);
    timeout_published_ = true;
    enter(LoopState::kRecognising);
    return;
  }
  if (timeout_published_ && t >= deadline_ + std::chrono::milliseconds(config_.hung_grace_ms)) {
    recogniser_hung_.store(true, std::memory_order_release);
    enter_fault(ErrorCode::kInternal, "the recogniser does not return (hung)");
    return;
  }
  if (!config_.conveyor_waits_for_ready) poll_edges_while_busy();
}

void ProductionLoop::poll_edges_while_busy() {
  drivers::EdgeEvent edge;
  const DeviceStatus status = io_.wait_edge(edge, 0);
  if (status == DeviceStatus::kOk && edge.edge == drivers::Edge::kRising)
    count_missed_trigger("part arrived while busy");
}

// ------------------------------------------------------------------------------------------------- publishing

void ProductionLoop::publish(const algo::Decision& decision, Clock::time_point now, bool aborted) {
  const double cycle_ms = aborted ? 0.0 : ms_between(cycle_start_, now);
  PartRecord record;
  record.acq_id = acq_id_;
  record.trigger = pass_trigger_;
  record.decision = decision;
  record.result = to_plc_result(decision, acq_id_, monotonic_us(), cycle_ms);
  record.publish = link_.publish(record.result);
  const Clock::time_point published = Clock::now();
  record.seq = record.publish == drivers::PublishStatus::kQueued ? link_.stats().last_seq : 0;
  record.frames = frames_;
  record.points = builder_.scan().size();
  record.cycle_ms = aborted ? 0.0 : ms_between(cycle_start_, published);
  record.recognise_ms = recognise_ms_;
  record.cycle_start_ns = to_ns(cycle_start_);
  record.published_ns = to_ns(published);
  record.aborted = aborted;
  if (decision.class_index >= 0 && recogniser_ != nullptr)
    record.class_name = recogniser_->class_name(decision.class_index);
  recognise_ms_ = 0.0;

  results_.fetch_add(1, std::memory_order_relaxed);
  if (record.publish != drivers::PublishStatus::kQueued) {
    rejected_.fetch_add(1, std::memory_order_relaxed);
    CS_LOG_ERROR(kComponent, "acq %u: result not handed to the PLC: %s (RESULT_OVERRUN)", acq_id_,
                 drivers::to_string(record.publish));
  }
  if (!aborted) {
    last_cycle_ms_.store(record.cycle_ms, std::memory_order_relaxed);
    if (record.cycle_ms > max_cycle_ms_.load(std::memory_order_relaxed)) {
      max_cycle_ms_.store(record.cycle_ms, std::memory_order_relaxed);
    }
  }

  // Repeated timeouts are an error the PLC sees; a cycle inside the deadline clears it again.
  if (record.result.code == drivers::ResultCode::kTimeout) {
    timeouts_.fetch_add(1, std::memory_order_relaxed);
    ++consecutive_timeouts_;
    if (consecutive_timeouts_ >= config_.max_consecutive_timeouts && error_ == ErrorCode::kNone) {
      CS_LOG_ERROR(kComponent, "%d timeouts in a row: ERROR_CODE repeated timeouts", consecutive_timeouts_);
      set_error(ErrorCode::kRepeatedTimeouts);
    }
  } else if (!aborted) {
    consecutive_timeouts_ = 0;
    if (error_ == ErrorCode::kRepeatedTimeouts) set_error(ErrorCode::kNone);
  }
  WarningCode warning = WarningCode::kNone;
  if (missed_since_result_ > 0) {
    warning = WarningCode::kMissedTrigger;
  } else if (exposure_at_limit_ && !aborted) {
    warning = WarningCode::kExposureAtLimit;
  } else if (!aborted && record.cycle_ms > config_.cycle_slow_ms) {
    warning = WarningCode::kCycleSlow;
  }
  missed_since_result_ = 0;
  set_warning(warning);

  const auto& r = record.result;
  const auto name = record.class_name.empty() ? std::string_view("-") : record.class_name;
  if (r.code == drivers::ResultCode::kOk) {
    CS_LOG_INFO(kComponent,
                "acq %u %s: part %.*s (id %u) source %s p %.3f pose x %+.2f mm y %+.2f mm theta %+.3f deg "
                "cycle %.1f ms (recognition %.1f ms) frames %d points %zu seq %u",
                r.acq_id, drivers::to_string(r.code), static_cast<int>(name.size()), name.data(),
                static_cast<unsigned>(r.part_id), algo::to_string(decision.source).data(), decision.probability,
                decision.pose.x_m * 1e3, decision.pose.y_m * 1e3, decision.pose.theta_rad * kDegPerRad, record.cycle_ms,
                record.recognise_ms, record.frames, record.points, record.seq);
  } else {
    CS_LOG_INFO(kComponent,
                "acq %u %s: part %.*s (id %u) source %s p %.3f pose - cycle %.1f ms (recognition %.1f ms) "
                "frames %d points %zu seq %u",
                r.acq_id, drivers::to_string(r.code), static_cast<int>(name.size()), name.data(),
                static_cast<unsigned>(r.part_id), algo::to_string(decision.source).data(), decision.probability,
                record.cycle_ms, record.recognise_ms, record.frames, record.points, record.seq);
    if (decision.source == algo::DecisionSource::kUnknown) {
      // Why (issue 10): the most probable verified candidate's failed gate, and how deep the search went.
      const algo::CandidateOutcome* why = nullptr;
      for (int i = 0; i < decision.candidate_count && why == nullptr; ++i) {
        const algo::CandidateOutcome& c = decision.candidates[static_cast<std::size_t>(i)];
        if (c.verified) why = &c;
      }
      const std::string_view cand =
          why != nullptr && recogniser_ != nullptr ? recogniser_->class_name(why->class_index) : std::string_view("-");
      CS_LOG_INFO(kComponent, "acq %u unknown: %s; %d of %d candidates verified; first: %.*s (p %.3f) %s %.4g > %.4g",
                  r.acq_id, algo::to_string(decision.unknown_reason).data(), decision.verified_count,
                  decision.candidate_count, static_cast<int>(cand.size()), cand.data(),
                  why != nullptr ? why->probability : 0.0,
                  why != nullptr ? algo::to_string(why->rejected_by).data() : "-", why != nullptr ? why->value : 0.0,
                  why != nullptr ? why->limit : 0.0);
    }
  }
  if (observer_ != nullptr) observer_->on_part_done(record);

  if (config_.max_parts > 0 && results_.load(std::memory_order_relaxed) >= config_.max_parts &&
      !finished_.load(std::memory_order_relaxed)) {
    {
      std::lock_guard lock(finished_mutex_);
      finished_.store(true, std::memory_order_release);
    }
    finished_cv_.notify_all();
    CS_LOG_INFO(kComponent, "%llu parts done: taking no more parts",
                static_cast<unsigned long long>(config_.max_parts));
  }
}

// ------------------------------------------------------------------------------------------------- fault

void ProductionLoop::step_fault(Clock::time_point now) {
  const bool forced = clear_requested_;
  clear_requested_ = false;

  if (fault_cause_ == ErrorCode::kInternal) {
    // Only the recogniser's return ends this fault; the systemd watchdog is not petted meanwhile.
    std::unique_lock lock(worker_mutex_);
    done_cv_.wait_for(lock, std::chrono::milliseconds(config_.poll_slice_ms), [this] { return job_finished_; });
    if (!job_finished_) return;
    lock.unlock();
    late_decisions_.fetch_add(1, std::memory_order_relaxed);
    timeout_published_ = false;
    recogniser_hung_.store(false, std::memory_order_release);
    recover("the recogniser returned");
    return;
  }

  if (fault_cause_ == ErrorCode::kModelDatabaseInvalid) {
    if (load_in_flight_) {
      std::unique_lock lock(worker_mutex_);
      done_cv_.wait_for(lock, std::chrono::milliseconds(config_.poll_slice_ms), [this] { return job_finished_; });
      if (!job_finished_) return;
      const bool ok = load_ok_;
      lock.unlock();
      load_in_flight_ = false;
      if (ok) {
        recover("model database loaded");
      } else {
        next_retry_ = Clock::now() + std::chrono::milliseconds(config_.models_retry_ms);
      }
      return;
    }
    if (loader_ && (forced || models_reload_requested_ || now >= next_retry_)) {
      models_reload_requested_ = false;
      CS_LOG_INFO(kComponent, "loading the model database");
      post_job(Job::kLoad);
      load_in_flight_ = true;
      return;
    }
    idle_wait(now);
    return;
  }

  // Device faults: reopen what failed every retry interval (or at once on CLEAR_ERROR), then probe it.
  if (forced || now >= next_retry_) {
    next_retry_ = now + std::chrono::milliseconds(config_.retry_interval_ms);
    bool reopened = true;
    if (camera_needs_reopen_) {
      camera_.stop();
      if (auto ok = camera_.start(); ok) {
        camera_needs_reopen_ = false;
        CS_LOG_INFO(kComponent, "camera reopened");
      } else {
        reopened = false;
        CS_LOG_ERROR(kComponent, "camera reopen failed: %s", ok.error().message.c_str());
      }
    }
    if (fault_cause_ == ErrorCode::kIoFault) {
      io_.close();
      if (auto ok = io_.open(); !ok) {
        reopened = false;
        CS_LOG_ERROR(kComponent, "digital I/O reopen failed: %s", ok.error().message.c_str());
      }
    }
    if (fault_cause_ == ErrorCode::kEncoderFault) {
      encoder_.close();
      if (auto ok = encoder_.open(); !ok) {
        reopened = false;
        CS_LOG_ERROR(kComponent, "encoder reopen failed: %s", ok.error().message.c_str());
      }
    }
    if (forced && reopened) {
      recover("CLEAR_ERROR from the PLC");
      return;
    }
  }

  switch (fault_cause_) {
    case ErrorCode::kCameraTimeout:
    case ErrorCode::kCameraFault: {
      if (camera_needs_reopen_) break;
      drivers::Frame frame;
      const DeviceStatus grabbed = camera_.grab(frame, config_.poll_slice_ms);
      if (grabbed == DeviceStatus::kOk) {
        camera_.release(frame);
        recover("frames are back");
        return;
      }
      if (grabbed != DeviceStatus::kTimeout) camera_needs_reopen_ = true;
      // The conveyor does not stop for a broken camera: parts passing now are missed, and their frames (when the
      // camera comes back) are the probe.
      drivers::EdgeEvent edge;
      if (io_.wait_edge(edge, 0) == DeviceStatus::kOk && edge.edge == drivers::Edge::kRising) {
        count_missed_trigger("part arrived during a camera fault");
      }
      break;
    }
    case ErrorCode::kIoFault: {
      bool present = true;
      if (io_.read(drivers::Input::kPartPresent, present) == DeviceStatus::kOk && !present) {
        recover("part-present readable and clear");
        return;
      }
      break;
    }
    case ErrorCode::kEncoderFault: {
      std::int64_t counts = 0;
      if (encoder_.read_counts(counts) == DeviceStatus::kOk) {
        recover("encoder readable");
        return;
      }
      break;
    }
    default:
      break;
  }
  idle_wait(now);
}

// ------------------------------------------------------------------------------------------------- bookkeeping

void ProductionLoop::enter(LoopState next) {
  const LoopState from = state_.exchange(next, std::memory_order_acq_rel);
  if (from == next) return;
  CS_LOG_DEBUG(kComponent, "%s -> %s", to_string(from), to_string(next));
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
  CS_LOG_ERROR(kComponent, "fault: %s (%s); ERROR_CODE %u", drivers::to_string(cause), why,
               static_cast<unsigned>(cause));
  enter(LoopState::kFault);
}

void ProductionLoop::recover(const char* how) {
  recoveries_.fetch_add(1, std::memory_order_relaxed);
  CS_LOG_INFO(kComponent, "recovered from %s after %.1f s: %s", drivers::to_string(fault_cause_),
              ms_between(fault_since_, Clock::now()) / 1e3, how);
  fault_cause_ = ErrorCode::kNone;
  camera_needs_reopen_ = false;
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
  CS_LOG_WARN(kComponent, "missed trigger: %s", why);
}

}  // namespace cellsight::app
