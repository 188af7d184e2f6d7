// The production loop's fault state: wait for a hung recogniser, reload the model database, or reopen and probe the
// device that failed, until the fault clears by itself or on CLEAR_ERROR.
#include "runtime/loop_internal.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::runtime {

void ProductionLoop::step_fault(Clock::time_point now) {
  const bool forced = clear_requested_;
  clear_requested_ = false;
  if (fault_cause_ == ErrorCode::kInternal) {
    fault_wait_recogniser();
    return;
  }
  if (fault_cause_ == ErrorCode::kModelDatabaseInvalid) {
    fault_reload_models(now, forced);
    return;
  }
  // Device faults: reopen what failed every retry interval (or at once on CLEAR_ERROR), then probe it.
  if (forced || now >= next_retry_) {
    next_retry_ = now + std::chrono::milliseconds(config_.retry_interval_ms);
    const bool reopened = fault_reopen_devices();
    if (forced && reopened) {
      recover("CLEAR_ERROR from the PLC");
      return;
    }
  }
  if (fault_probe()) return;
  idle_wait(now);
}

// Only the recogniser's return ends this fault; the systemd watchdog is not petted meanwhile.
void ProductionLoop::fault_wait_recogniser() {
  if (!worker_.wait_idle(Clock::now() + std::chrono::milliseconds(config_.poll_slice_ms))) return;
  late_decisions_.fetch_add(1, std::memory_order_relaxed);
  timeout_published_ = false;
  recogniser_hung_.store(false, std::memory_order_release);
  recover("the recogniser returned");
}

void ProductionLoop::fault_reload_models(Clock::time_point now, bool forced) {
  if (load_in_flight_) {
    if (!worker_.wait_idle(Clock::now() + std::chrono::milliseconds(config_.poll_slice_ms))) return;
    load_in_flight_ = false;
    if (worker_.answer().load_ok) {
      recover("model database loaded");
    } else {
      next_retry_ = Clock::now() + std::chrono::milliseconds(config_.models_retry_ms);
    }
    return;
  }
  if (worker_.has_loader() && (forced || models_reload_requested_ || now >= next_retry_)) {
    models_reload_requested_ = false;
    CS_QLOG_INFO(log_, kComponent, "loading the model database");
    load_in_flight_ = worker_.post_load();
    return;
  }
  idle_wait(now);
}

// Reopens the devices the fault concerns; true when every reopen worked.
bool ProductionLoop::fault_reopen_devices() {
  bool reopened = true;
  if (acquirer_.camera_failed()) {
    camera_.stop();
    if (auto ok = camera_.start(); ok) {
      acquirer_.clear_camera_failed();
      CS_QLOG_INFO(log_, kComponent, "camera reopened");
    } else {
      reopened = false;
      CS_QLOG_ERROR(log_, kComponent, "camera reopen failed: %s", ok.error().message.c_str());
    }
  }
  if (fault_cause_ == ErrorCode::kIoFault) {
    io_.close();
    if (auto ok = io_.open(); !ok) {
      reopened = false;
      CS_QLOG_ERROR(log_, kComponent, "digital I/O reopen failed: %s", ok.error().message.c_str());
    }
  }
  if (fault_cause_ == ErrorCode::kEncoderFault) {
    encoder_.close();
    if (auto ok = encoder_.open(); !ok) {
      reopened = false;
      CS_QLOG_ERROR(log_, kComponent, "encoder reopen failed: %s", ok.error().message.c_str());
    }
  }
  return reopened;
}

// Probes the failed device; true when it works again (the loop has recovered).
bool ProductionLoop::fault_probe() {
  switch (fault_cause_) {
    case ErrorCode::kCameraTimeout:
    case ErrorCode::kCameraFault: {
      if (acquirer_.camera_failed()) return false;  // reopened first
      if (acquirer_.probe(config_.poll_slice_ms) == DeviceStatus::kOk) {
        recover("frames are back");
        return true;
      }
      // The conveyor does not stop for a broken camera: parts passing now are missed, and their frames (when the
      // camera comes back) are the probe.
      drivers::EdgeEvent edge;
      if (io_.wait_edge(edge, 0) == DeviceStatus::kOk && edge.edge == drivers::Edge::kRising) {
        count_missed_trigger("part arrived during a camera fault");
      }
      return false;
    }
    case ErrorCode::kIoFault: {
      bool present = true;
      if (io_.read(drivers::Input::kPartPresent, present) == DeviceStatus::kOk && !present) {
        recover("part-present readable and clear");
        return true;
      }
      return false;
    }
    case ErrorCode::kEncoderFault: {
      std::int64_t counts = 0;
      if (encoder_.read_counts(counts) == DeviceStatus::kOk) {
        recover("encoder readable");
        return true;
      }
      return false;
    }
    default: return false;
  }
}

}  // namespace cellsight::runtime
