// What the PLC sees of the loop (DESIGN.md register map and handshake), as pure functions: a decision -> the result
// block, the loop's state -> its STATUS bits, a finished part -> WARNING_CODE. No I/O, no state: tested alone
// (tests/test_plc_mapping.cpp) against words computed by hand from the README's register table.
#pragma once

#include <cstdint>

#include "algo/decision.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "runtime/loop_types.hpp"

namespace cellsight::runtime {

// Decision -> result block.
//  svm/pm -> ok (SOURCE svm / perfect match), part id, confidence = probability in per mille, pose X, Y, Z in um
//           and RX, RY, RZ = theta in millidegrees, each axis's 1-sigma in the sigma registers. Z, RX, RY the
//           geometry did not fix (NaN) go out as 0x80000000 and the result stays ok; an accepted decision whose
//           X, Y or theta is missing or unrepresentable -> "pose out of range" (part id kept, pose invalid).
//  unknown -> "unknown part" (confidence of the best class, part id 0); timeout, bad scan, no part -> their codes;
//  every pose field without a value carries the invalid marker 0x80000000, every sigma without one 0xFFFF, and a
//  sigma is published only where its axis's value is.
[[nodiscard]] drivers::PlcResult to_plc_result(const algo::Decision& decision, std::uint32_t acq_id,
                                               std::uint64_t timestamp_us, double cycle_ms);

// When a trigger may start a pass (TRIGGER_READY).
struct TriggerGate {
  LoopState state = LoopState::kIdle;
  bool has_recogniser = false;
  bool finished = false;               // max_parts reached
  bool require_trigger_enable = true;  // LoopConfig
  bool trigger_enable = false;         // CONTROL.TRIGGER_ENABLE as last read
  bool hold_when_queue_full = false;   // LoopConfig
  bool queue_full = false;             // the link's result queue
};
[[nodiscard]] bool trigger_allowed(const TriggerGate& gate);

// The STATUS bits the loop owns (READY, TRIGGER_READY, TRIGGER_ACK, BUSY, TEACH_MODE) as a StatusFlag mask.
//  READY: not in fault and not stopped. BUSY: scanning or recognising. TRIGGER_ACK: a pass is in progress, i.e.
//  scanning, or recognising before "timeout" went out (after it the PLC has its answer for that part).
//  TEACH_MODE: a part is being taught (ENTER_TEACH until LEAVE_TEACH).
[[nodiscard]] std::uint16_t loop_status_flags(LoopState state, bool trigger_allowed, bool timeout_published,
                                              bool teaching = false);
// The bits loop_status_flags() decides, for a caller that sends only the changed ones.
inline constexpr drivers::StatusFlag kLoopStatusFlags[] = {
    drivers::StatusFlag::kReady, drivers::StatusFlag::kTriggerReady, drivers::StatusFlag::kTriggerAck,
    drivers::StatusFlag::kBusy, drivers::StatusFlag::kTeachMode};

// WARNING_CODE after a published part: a trigger missed since the last result first, then (for a part that was
// scanned to its end) exposure pinned at a limit, then a cycle slower than cycle_slow_ms; otherwise none.
struct PartWarningInputs {
  std::uint32_t missed_since_result = 0;
  bool exposure_at_limit = false;
  bool aborted = false;
  double cycle_ms = 0.0;
  double cycle_slow_ms = 0.0;
};
[[nodiscard]] drivers::WarningCode part_warning(const PartWarningInputs& part);

}  // namespace cellsight::runtime
