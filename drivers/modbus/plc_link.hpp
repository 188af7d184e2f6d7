// PLC link interface used by the production loop: publish results, report state, read the PLC's commands.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "base/result.hpp"
#include "drivers/modbus/register_map.hpp"

namespace cellsight::drivers {

// One recognition result as the PLC sees it (result block 200-234). Integers with units, as on the wire.
struct PlcResult {
  std::uint32_t acq_id = 0;  // the part pass that produced it
  ResultCode code = ResultCode::kNoPart;
  std::uint16_t part_id = 0;  // PLC id of the taught part (its robot program), 0 when none
  std::uint16_t confidence_permille = 0;
  ResultSource source = ResultSource::kNone;
  std::int32_t x_um = modbus_map::kInvalidS32;
  std::int32_t y_um = modbus_map::kInvalidS32;
  std::int32_t z_um = modbus_map::kInvalidS32;
  std::int32_t rx_mdeg = modbus_map::kInvalidS32;
  std::int32_t ry_mdeg = modbus_map::kInvalidS32;
  std::int32_t rz_mdeg = modbus_map::kInvalidS32;  // theta of DESIGN.md "Pose"
  std::uint64_t timestamp_us = 0;                  // CLOCK_MONOTONIC when the result was made
  std::uint16_t cycle_ms = 0;                      // part-present falling edge -> result ready, saturated
  // 1-sigma uncertainty of each pose axis; kInvalidSigma where the axis or its uncertainty is not available.
  std::uint16_t sigma_x_um = modbus_map::kInvalidSigma;
  std::uint16_t sigma_y_um = modbus_map::kInvalidSigma;
  std::uint16_t sigma_z_um = modbus_map::kInvalidSigma;
  std::uint16_t sigma_rx_mdeg = modbus_map::kInvalidSigma;
  std::uint16_t sigma_ry_mdeg = modbus_map::kInvalidSigma;
  std::uint16_t sigma_rz_mdeg = modbus_map::kInvalidSigma;
};

// Metres -> s32 micrometres on the wire; not finite or not representable -> the invalid marker, never a wrapped value.
[[nodiscard]] inline std::int32_t to_plc_micrometres(double metres) {
  constexpr double kMicrometresPerMetre = 1e6;
  const double value = std::round(metres * kMicrometresPerMetre);
  // The marker itself (INT32_MIN) is not a legal measurement, hence the symmetric range.
  constexpr double kLimit = static_cast<double>(std::numeric_limits<std::int32_t>::max());
  if (!std::isfinite(value) || value > kLimit || value < -kLimit) return modbus_map::kInvalidS32;
  return static_cast<std::int32_t>(value);
}

// Degrees -> s32 millidegrees on the wire, same rules as to_plc_micrometres.
[[nodiscard]] inline std::int32_t to_plc_millidegrees(double degrees) {
  constexpr double kMillidegreesPerDegree = 1e3;
  const double value = std::round(degrees * kMillidegreesPerDegree);
  constexpr double kLimit = static_cast<double>(std::numeric_limits<std::int32_t>::max());
  if (!std::isfinite(value) || value > kLimit || value < -kLimit) return modbus_map::kInvalidS32;
  return static_cast<std::int32_t>(value);
}

// A 1-sigma uncertainty already in wire units (um or millidegrees) -> its u16 register: rounded; a finite value above
// kMaxSigma saturates there (a large uncertainty stays large, never "not available"); not finite or negative ->
// kInvalidSigma (no uncertainty is negative: such a value is a fault of the estimate, not a small sigma).
[[nodiscard]] inline std::uint16_t to_plc_sigma(double wire_units) {
  if (!std::isfinite(wire_units) || wire_units < 0.0) return modbus_map::kInvalidSigma;
  const double value = std::round(wire_units);
  return value >= modbus_map::kMaxSigma ? modbus_map::kMaxSigma : static_cast<std::uint16_t>(value);
}

// Metres -> u16 micrometres of a sigma register (to_plc_sigma's rules).
[[nodiscard]] inline std::uint16_t to_plc_sigma_micrometres(double metres) {
  constexpr double kMicrometresPerMetre = 1e6;
  return to_plc_sigma(metres * kMicrometresPerMetre);
}

// Degrees -> u16 millidegrees of a sigma register (to_plc_sigma's rules).
[[nodiscard]] inline std::uint16_t to_plc_sigma_millidegrees(double degrees) {
  constexpr double kMillidegreesPerDegree = 1e3;
  return to_plc_sigma(degrees * kMillidegreesPerDegree);
}

// STATUS bits the production loop owns. The link owns RESULT_VALID, RESULT_OVERRUN and PLC_HB_LOST; ERROR, WARNING,
// CMD_DONE and CMD_FAILED follow set_error, set_warning and complete_command.
enum class StatusFlag : std::uint16_t {
  kReady = modbus_map::kStatusReady,
  kTriggerReady = modbus_map::kStatusTriggerReady,
  kTriggerAck = modbus_map::kStatusTriggerAck,
  kBusy = modbus_map::kStatusBusy,
  kTeachMode = modbus_map::kStatusTeachMode,
};

enum class [[nodiscard]] PublishStatus : std::uint8_t{
    kQueued = 0,  // accepted; it appears in the result block when the block is free
    kQueueFull,   // rejected: the queue holds `result_queue_capacity` unpresented results; RESULT_OVERRUN is set
    kConcurrent,  // rejected: another thread is inside publish() (a programming error: one producer only)
};

constexpr const char* to_string(PublishStatus status) {
  switch (status) {
    case PublishStatus::kQueued: return "queued";
    case PublishStatus::kQueueFull: return "queue full";
    case PublishStatus::kConcurrent: return "concurrent publish";
  }
  return "invalid";
}

// How the next result replaces the presented one.
enum class AckMode : std::uint8_t {
  kHandshake,  // RESULT_ACK set -> RESULT_VALID cleared; RESULT_ACK cleared -> next result (DESIGN.md "Handshake")
  kPollOnly,   // no ack: a presented result stays at least poll_hold_ms, then the next queued one replaces it
};

struct PlcLinkConfig {
  std::size_t result_queue_capacity = 8;  // results waiting behind the presented one
  // PLC_HEARTBEAT (register 4) unchanged for longer than this -> PLC_HB_LOST and RESULT_VALID dropped. 0 = no check
  // (for a PLC that never writes a heartbeat).
  std::int32_t plc_heartbeat_timeout_ms = 1000;
  AckMode ack_mode = AckMode::kHandshake;
  std::int32_t poll_hold_ms = 1000;  // kPollOnly only
  // HEARTBEAT (register 101) advances only while the production loop called heartbeat() within this time, so the
  // PLC sees a hung loop, not just a live network thread. 0 = advance regardless.
  std::int32_t loop_watchdog_ms = 1000;
};

// What the PLC asked for since the previous take_commands(). Edges are counted by the link, so a short pulse
// between two polls of the production loop is not lost.
struct PlcCommands {
  bool trigger_enable = false;     // CONTROL.TRIGGER_ENABLE, current level
  std::uint32_t sw_triggers = 0;   // SW_TRIGGER rising edges since the last take
  std::uint32_t clear_errors = 0;  // CLEAR_ERROR rising edges since the last take
  bool exec_command = false;       // an EXEC_CMD rising edge arrived; command/argument latched at the last one
  CommandCode command = CommandCode::kNone;
  std::uint16_t command_raw = 0;  // COMMAND as written (command is kNone for unknown values)
  std::uint32_t command_arg = 0;
  bool plc_heartbeat_lost = false;  // STATUS.PLC_HB_LOST
};

// Counters for logs and tests; every field is a snapshot of a monotonic counter unless said otherwise.
struct LinkStats {
  std::uint64_t results_published = 0;  // accepted by publish()
  std::uint64_t results_rejected = 0;   // publish() returned kQueueFull
  std::uint64_t results_presented = 0;  // written into the result block
  std::uint64_t results_acked = 0;      // RESULT_ACK seen for a presented result
  std::uint32_t queue_depth = 0;        // now: published, not yet presented
  std::uint32_t last_seq = 0;           // now: RESULT_SEQ of the newest published result
  std::uint64_t requests_served = 0;    // frames answered by modbus_reply
  std::uint64_t exceptions_sent = 0;    // frames answered with an exception
  std::uint64_t clients_accepted = 0;
  std::uint64_t clients_refused = 0;    // table full and every client in the middle of a request
  std::uint64_t clients_evicted = 0;    // closed to make room for a newcomer: the longest idle (not in clients_dropped)
  std::uint64_t clients_dropped = 0;    // closed by the server: bad framing, byte/idle timeout, send failure
  std::uint32_t clients_connected = 0;  // now
  std::uint64_t heartbeat_losses = 0;   // transitions into PLC_HB_LOST
  std::uint64_t loop_stalls = 0;        // transitions into "production loop silent" (HEARTBEAT frozen)
};

// The production loop talks to the PLC only through this. Two backends: ModbusServer (libmodbus TCP) and SimPlcLink.
//
// Threading: start()/stop() from the owning thread. publish() and take_commands() each from one thread (the
// production loop). The setters may be called from any thread. None of the calls after start() allocates or waits
// on a lock held by the network side: state travels through atomics and a single-producer ring.
class PlcLink {
 public:
  virtual ~PlcLink() = default;
  PlcLink() = default;
  PlcLink(const PlcLink&) = delete;
  PlcLink& operator=(const PlcLink&) = delete;

  virtual Status start() = 0;
  virtual void stop() = 0;

  // Queues a result; the link numbers it (RESULT_SEQ) and presents it when the result block is free.
  virtual PublishStatus publish(const PlcResult& result) = 0;
  virtual void set_flag(StatusFlag flag, bool on) = 0;
  // A fault drops RESULT_VALID at once: no result looks fresh while ERROR is set. kNone clears the fault; the result
  // that was presented (if not acknowledged) is then presented again with its sequence number unchanged.
  virtual void set_error(ErrorCode code) = 0;
  virtual void set_warning(WarningCode code) = 0;
  virtual void set_active_models(std::uint16_t database_id) = 0;
  virtual void set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers) = 0;
  // Answers the command latched by the last EXEC_CMD edge: CMD_DONE or CMD_FAILED until EXEC_CMD falls.
  virtual void complete_command(bool ok) = 0;
  virtual PlcCommands take_commands() = 0;
  // The production loop is alive; call it every iteration (see PlcLinkConfig::loop_watchdog_ms).
  virtual void heartbeat() = 0;
  [[nodiscard]] virtual LinkStats stats() const = 0;
};

}  // namespace cellsight::drivers
