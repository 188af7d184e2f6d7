// The production loop's vocabulary: its states, settings, per-part record, counters and observer. Shared by the loop,
// the PLC mapping and the wiring, so that none of them has to include the others.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string_view>

#include "algo/decision.hpp"
#include "base/result.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "runtime/recogniser.hpp"

namespace cellsight::runtime {

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
    case LoopState::kIdle: return "idle";
    case LoopState::kScanning: return "scanning";
    case LoopState::kRecognising: return "recognising";
    case LoopState::kPublishing: return "publishing";
    case LoopState::kFault: return "fault";
    case LoopState::kStopped: return "stopped";
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
  // Lines the loop thread may queue before the log writer thread catches up; more are dropped and counted.
  std::size_t log_queue_lines = 256;
};

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
  std::uint64_t faults = 0;             // transitions into kFault
  std::uint64_t recoveries = 0;         // transitions out of kFault
  std::uint64_t late_decisions = 0;     // decisions that came back after the deadline (discarded)
  std::uint64_t log_lines_dropped = 0;  // the loop's log queue was full (the writer thread fell behind)
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

}  // namespace cellsight::runtime
