// Decision and loop state -> the PLC's registers and flags.
#include "runtime/plc_mapping.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "drivers/modbus/register_map.hpp"

namespace cellsight::runtime {

namespace {
constexpr double kPermille = 1000.0;
constexpr double kDegPerRad = 180.0 / std::numbers::pi;
constexpr double kMaxCycleMs = 65535.0;  // CYCLE_MS is a u16
using drivers::modbus_map::kInvalidS32;

std::uint16_t permille(double p) {
  if (!std::isfinite(p)) return 0;
  return static_cast<std::uint16_t>(std::lround(std::clamp(p, 0.0, 1.0) * kPermille));
}

// svm / perfect match: a class, and a pose the robot can use or "pose out of range".
void map_accepted(const algo::Decision& decision, drivers::PlcResult& r) {
  using drivers::ResultCode;
  using drivers::ResultSource;
  r.source = decision.source == algo::DecisionSource::kSvm ? ResultSource::kSvm : ResultSource::kPerfectMatch;
  r.part_id = static_cast<std::uint16_t>(std::clamp(decision.part_id, 0, 0xFFFF));
  r.confidence_permille = permille(decision.probability);
  const std::int32_t x_um = drivers::to_plc_micrometres(decision.pose.x_m);
  const std::int32_t y_um = drivers::to_plc_micrometres(decision.pose.y_m);
  const std::int32_t rz_mdeg = drivers::to_plc_millidegrees(decision.pose.theta_rad * kDegPerRad);
  if (!decision.pose_valid || x_um == kInvalidS32 || y_um == kInvalidS32 || rz_mdeg == kInvalidS32) {
    r.code = ResultCode::kPoseOutOfRange;  // a class without a usable pose is no instruction for the robot
    return;
  }
  r.code = ResultCode::kOk;
  r.x_um = x_um;
  r.y_um = y_um;
  r.z_um = 0;  // DESIGN.md: Z 0 until estimated; the planar pose has no RX, RY either
  r.rx_mdeg = 0;
  r.ry_mdeg = 0;
  r.rz_mdeg = rz_mdeg;
}

}  // namespace

drivers::PlcResult to_plc_result(const algo::Decision& decision, std::uint32_t acq_id, std::uint64_t timestamp_us,
                                 double cycle_ms) {
  using drivers::ResultCode;
  drivers::PlcResult r;
  r.acq_id = acq_id;
  r.timestamp_us = timestamp_us;
  r.cycle_ms = static_cast<std::uint16_t>(
      std::lround(std::clamp(std::isfinite(cycle_ms) ? cycle_ms : kMaxCycleMs, 0.0, kMaxCycleMs)));
  switch (decision.source) {
    case algo::DecisionSource::kSvm:
    case algo::DecisionSource::kPm: map_accepted(decision, r); return r;
    case algo::DecisionSource::kUnknown:
      r.code = ResultCode::kUnknownPart;
      r.confidence_permille = permille(decision.probability);
      return r;
    case algo::DecisionSource::kTimeout: r.code = ResultCode::kTimeout; return r;
    case algo::DecisionSource::kBadScan: r.code = ResultCode::kBadScan; return r;
    case algo::DecisionSource::kNoPart: r.code = ResultCode::kNoPart; return r;
  }
  r.code = ResultCode::kBadScan;
  return r;
}

bool trigger_allowed(const TriggerGate& gate) {
  if (gate.state != LoopState::kIdle) return false;
  if (!gate.has_recogniser || gate.finished) return false;
  if (gate.require_trigger_enable && !gate.trigger_enable) return false;
  return !(gate.hold_when_queue_full && gate.queue_full);
}

std::uint16_t loop_status_flags(LoopState state, bool trigger_allowed, bool timeout_published) {
  const bool in_pass = state == LoopState::kScanning || (state == LoopState::kRecognising && !timeout_published);
  const bool busy = state == LoopState::kScanning || state == LoopState::kRecognising;
  std::uint16_t flags = 0;
  const auto put = [&flags](drivers::StatusFlag flag, bool on) {
    if (on) flags = static_cast<std::uint16_t>(flags | static_cast<std::uint16_t>(flag));
  };
  put(drivers::StatusFlag::kReady, state != LoopState::kFault && state != LoopState::kStopped);
  put(drivers::StatusFlag::kTriggerReady, trigger_allowed);
  put(drivers::StatusFlag::kTriggerAck, in_pass);
  put(drivers::StatusFlag::kBusy, busy);
  return flags;
}

drivers::WarningCode part_warning(const PartWarningInputs& part) {
  if (part.missed_since_result > 0) return drivers::WarningCode::kMissedTrigger;
  if (part.exposure_at_limit && !part.aborted) return drivers::WarningCode::kExposureAtLimit;
  if (!part.aborted && part.cycle_ms > part.cycle_slow_ms) return drivers::WarningCode::kCycleSlow;
  return drivers::WarningCode::kNone;
}

}  // namespace cellsight::runtime
