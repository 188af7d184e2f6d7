// Decision and loop state -> the PLC's registers and flags.
#include "runtime/plc_mapping.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
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

// An uncertainty travels only with its value: an axis published invalid has none, whatever the estimate said.
std::uint16_t sigma_register(const algo::Decision& decision, algo::PoseAxis axis, std::int32_t published) {
  if (published == kInvalidS32) return drivers::modbus_map::kInvalidSigma;
  const double sigma = decision.pose_sigma[static_cast<std::size_t>(axis)];
  const bool linear = axis == algo::PoseAxis::kX || axis == algo::PoseAxis::kY || axis == algo::PoseAxis::kZ;
  return linear ? drivers::to_plc_sigma_micrometres(sigma) : drivers::to_plc_sigma_millidegrees(sigma * kDegPerRad);
}

// svm / perfect match: a class, and a pose the robot can use or "pose out of range".
void map_accepted(const algo::Decision& decision, drivers::PlcResult& r) {
  using algo::PoseAxis;
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
  r.rz_mdeg = rz_mdeg;
  // The out-of-plane axes may be unfixed by the geometry (NaN): they go out invalid, never 0, and the planar pose
  // is still an instruction the robot can follow.
  r.z_um = drivers::to_plc_micrometres(decision.z_m);
  r.rx_mdeg = drivers::to_plc_millidegrees(decision.rx_rad * kDegPerRad);
  r.ry_mdeg = drivers::to_plc_millidegrees(decision.ry_rad * kDegPerRad);
  r.sigma_x_um = sigma_register(decision, PoseAxis::kX, r.x_um);
  r.sigma_y_um = sigma_register(decision, PoseAxis::kY, r.y_um);
  r.sigma_z_um = sigma_register(decision, PoseAxis::kZ, r.z_um);
  r.sigma_rx_mdeg = sigma_register(decision, PoseAxis::kRx, r.rx_mdeg);
  r.sigma_ry_mdeg = sigma_register(decision, PoseAxis::kRy, r.ry_mdeg);
  r.sigma_rz_mdeg = sigma_register(decision, PoseAxis::kRz, r.rz_mdeg);
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

std::uint16_t loop_status_flags(LoopState state, bool trigger_allowed, bool timeout_published, bool teaching) {
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
  put(drivers::StatusFlag::kTeachMode, teaching);
  return flags;
}

drivers::WarningCode part_warning(const PartWarningInputs& part) {
  if (part.missed_since_result > 0) return drivers::WarningCode::kMissedTrigger;
  if (part.exposure_at_limit && !part.aborted) return drivers::WarningCode::kExposureAtLimit;
  if (!part.aborted && part.cycle_ms > part.cycle_slow_ms) return drivers::WarningCode::kCycleSlow;
  return drivers::WarningCode::kNone;
}

}  // namespace cellsight::runtime
