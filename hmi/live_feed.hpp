// What the operator's screen shows of the production loop, handed over without ever holding the loop up: LiveFeed is
// the loop's observer (its callbacks run on the loop thread); each finished part becomes a fixed-size LiveResult in a
// single-producer ring (base::SpscRing: no lock, no allocation; a full ring drops and counts), and the loop state is
// an atomic. The HMI's own thread takes the records (take()) and keeps its history; observers chain, so the
// simulated cell's truth log still sees every call.
#pragma once

#include <atomic>
#include <cstdint>

#include "algo/decision.hpp"
#include "base/spsc_ring.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "runtime/loop_types.hpp"

namespace cellsight::hmi {

struct LiveResult {
  static constexpr std::size_t kNameBytes = 64;
  drivers::PlcResult plc;  // what the PLC was handed, in its units
  std::uint32_t seq = 0;   // RESULT_SEQ (0 when the link refused it)
  algo::DecisionSource source = algo::DecisionSource::kNoPart;
  algo::RejectReason unknown_reason = algo::RejectReason::kNone;
  runtime::TriggerSource trigger = runtime::TriggerSource::kPartPresent;
  bool aborted = false;
  std::int32_t frames = 0;
  std::int32_t verified = 0;  // candidates Perfect Match checked
  std::uint64_t points = 0;
  double cycle_ms = 0.0;
  double recognise_ms = 0.0;
  double probability = 0.0;
  std::int64_t wall_ms = 0;         // CLOCK_REALTIME when the loop finished the part (for the operator's clock)
  char part_name[kNameBytes] = {};  // the recogniser's class name, cut to fit; empty when none
};

// A change into or out of the fault state (for the Health page's fault log), with the wall-clock time.
struct FaultEvent {
  runtime::LoopState from = runtime::LoopState::kIdle;
  runtime::LoopState to = runtime::LoopState::kIdle;
  drivers::ErrorCode error = drivers::ErrorCode::kNone;
  std::int64_t wall_ms = 0;
};

class LiveFeed final : public runtime::LoopObserver {
 public:
  // capacity: records the HMI may fall behind by before the newest are dropped (counted); next: an observer that
  // gets every call as well (borrowed, may be null).
  explicit LiveFeed(std::size_t capacity, runtime::LoopObserver* next = nullptr);

  // Before the loop starts: the observer that gets every call after this one.
  void set_next(runtime::LoopObserver* next) { next_ = next; }

  // ---- loop thread ----
  void on_state(runtime::LoopState from, runtime::LoopState to, drivers::ErrorCode error) override;
  void on_pass_started(std::uint32_t acq_id, runtime::TriggerSource trigger) override;
  void on_frame(std::uint32_t acq_id, int frame_index) override;
  void on_part_done(const runtime::PartRecord& record) override;

  // ---- the HMI's thread (one consumer) ----
  bool take(LiveResult& out) { return ring_.try_pop(out); }
  bool take(FaultEvent& out) { return faults_.try_pop(out); }
  [[nodiscard]] std::uint64_t dropped() const { return ring_.dropped(); }
  [[nodiscard]] std::uint64_t passes_started() const { return passes_.load(std::memory_order_relaxed); }

 private:
  base::SpscRing<LiveResult> ring_;
  base::SpscRing<FaultEvent> faults_{64};
  runtime::LoopObserver* next_;
  std::atomic<std::uint64_t> passes_{0};
};

}  // namespace cellsight::hmi
