// The production loop's acquisition states: idle (waiting for a trigger) and scanning (one part pass through the
// PassAcquirer, one slice per step), up to handing the scan to the recognition worker.
#include "runtime/loop_internal.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::runtime {

namespace {
constexpr int kMaxDrainedFramesPerStep = 8;
}  // namespace

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
      CS_QLOG_WARN(log_, kComponent, "SW_TRIGGER ignored: not ready for a part (TRIGGER_READY is off)");
      pending_sw_triggers_ = 0;
    }
    if (config_.conveyor_waits_for_ready) {
      idle_wait(now);
      return;
    }
  }
  if (drain_frames()) return;  // frames of a part that is not scanned (keep draining), or the camera failed
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
  } else if (worker_.has_recogniser() && !finished_.load() && (!config_.require_trigger_enable || trigger_enable_)) {
    count_missed_trigger("result queue full");
  } else {
    CS_QLOG_DEBUG(log_, kComponent, "part passes unscanned: triggers not enabled by the PLC");
  }
}

// True when this step is used up: a full batch of frames was dropped, or the camera failed (fault entered).
bool ProductionLoop::drain_frames() {
  const int drained = acquirer_.drain(kMaxDrainedFramesPerStep);
  if (drained < 0) {
    enter_fault(ErrorCode::kCameraFault, to_string(acquirer_.camera_error()));
    return true;
  }
  return drained == kMaxDrainedFramesPerStep;
}

void ProductionLoop::start_pass(TriggerSource trigger, Clock::time_point now) {
  if (acquirer_.begin(trigger == TriggerSource::kSoftware, now) != PassStatus::kScanning) {
    enter_fault(error_code(acquirer_.abort()), acquirer_.abort_reason());
    return;
  }
  acq_id_ = acq_id_ + 1 == 0 ? 1 : acq_id_ + 1;
  ++trigger_count_;
  link_.set_trigger_counters(trigger_count_, missed_count_);
  triggers_.fetch_add(1, std::memory_order_relaxed);
  pass_trigger_ = trigger;
  pass_teach_part_id_ = teach_part_id_;  // latched: a mode change takes effect at the next pass, never in this one
  timeout_published_ = false;
  exposure_at_limit_ = false;
  CS_QLOG_DEBUG(log_, kComponent, "acq %u: pass started (%s)", acq_id_, loop_detail::trigger_name(trigger));
  if (observer_ != nullptr) observer_->on_pass_started(acq_id_, trigger);
  enter(LoopState::kScanning);
}

// ------------------------------------------------------------------------------------------------- scanning

void ProductionLoop::step_scanning(Clock::time_point now) {
  const PassStatus status = acquirer_.step(now);
  if (acquirer_.frame_added() && observer_ != nullptr) observer_->on_frame(acq_id_, acquirer_.frames() - 1);
  switch (status) {
    case PassStatus::kScanning: return;
    case PassStatus::kComplete: finish_scan(edge_time(acquirer_.falling_edge(), acquirer_.falling_seen())); return;
    case PassStatus::kNoPart: publish_no_part(acquirer_.last_grab_at()); return;
    case PassStatus::kAborted:
    case PassStatus::kNotStarted: abort_pass(error_code(acquirer_.abort()), acquirer_.abort_reason()); return;
  }
}

// A SW_TRIGGER with nothing in front of the sensor: the honest answer is "no part", not a fault.
void ProductionLoop::publish_no_part(Clock::time_point at) {
  (void)acquirer_.end();
  cycle_start_ = at;
  enter(LoopState::kPublishing);
  publish(decision_of(algo::DecisionSource::kNoPart), Clock::now(), false);
  enter(LoopState::kIdle);
}

void ProductionLoop::finish_scan(Clock::time_point cycle_start) {
  if (!acquirer_.end()) CS_QLOG_WARN(log_, kComponent, "acq %u: cannot switch the laser off", acq_id_);
  const algo::PassStats& pass = builder_.stats();
  const std::int32_t exposure = builder_.exposure_us();
  exposure_at_limit_ = (exposure <= exposure_min_us_ || exposure >= exposure_max_us_) &&
                       pass.frames_in_band * 2 < pass.frames_with_stripe;
  cycle_start_ = cycle_start;
  deadline_ = cycle_start + std::chrono::milliseconds(config_.deadline_ms);
  // The worker is idle here: the state machine enters scanning only after the previous answer came back.
  (void)worker_.post_recognise(builder_.scan().points(), deadline_,
                               KeepTag{acq_id_, pass_teach_part_id_ != 0, pass_teach_part_id_});
  enter(LoopState::kRecognising);
}

void ProductionLoop::abort_pass(ErrorCode cause, const char* why) {
  (void)acquirer_.end();
  aborted_.fetch_add(1, std::memory_order_relaxed);
  CS_QLOG_ERROR(log_, kComponent, "acq %u: scan aborted after %d frames: %s", acq_id_, acquirer_.frames(), why);
  // ERROR first, so the PLC never takes the aborted part's "bad scan" for a fresh result before it sees the fault.
  set_error(cause);
  const Clock::time_point now = Clock::now();
  cycle_start_ = now;
  enter(LoopState::kPublishing);
  publish(decision_of(algo::DecisionSource::kBadScan), now, true);
  enter_fault(cause, why);
}

void ProductionLoop::poll_edges_while_busy() {
  drivers::EdgeEvent edge;
  const DeviceStatus status = io_.wait_edge(edge, 0);
  if (status == DeviceStatus::kOk && edge.edge == drivers::Edge::kRising)
    count_missed_trigger("part arrived while busy");
}

}  // namespace cellsight::runtime
