// Register image and result handshake of the PLC link (DESIGN.md "Modbus register map", "Handshake").
#include "drivers/modbus/link_core.hpp"

#include <algorithm>

#include "drivers/log.hpp"

namespace cellsight::drivers {
namespace {

namespace map = modbus_map;

constexpr const char* kComponent = "plc-link";
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr std::uint16_t kCommandAnswerBits = map::kStatusCmdDone | map::kStatusCmdFailed;
constexpr std::uint16_t kProductionFlagBits =
    map::kStatusReady | map::kStatusTriggerReady | map::kStatusTriggerAck | map::kStatusBusy | map::kStatusTeachMode;
constexpr int kWordBits = 16;
constexpr std::uint32_t kWordMask = 0xFFFF;
constexpr int kMailboxCountShift = 48;
constexpr int kMailboxCommandShift = 32;
constexpr std::uint64_t kMailboxArgMask = 0xFFFF'FFFF;
constexpr int kCountersShift = 32;

void put_u32(std::uint16_t* at, std::uint32_t value) {
  at[0] = static_cast<std::uint16_t>(value >> kWordBits);  // high word first (DESIGN.md)
  at[1] = static_cast<std::uint16_t>(value & kWordMask);
}

void put_s32(std::uint16_t* at, std::int32_t value) {
  put_u32(at, static_cast<std::uint32_t>(value));
}

void put_u64(std::uint16_t* at, std::uint64_t value) {
  put_u32(at, static_cast<std::uint32_t>(value >> 32));
  put_u32(at + 2, static_cast<std::uint32_t>(value & 0xFFFF'FFFFu));
}

CommandCode to_command(std::uint16_t raw) {
  switch (static_cast<CommandCode>(raw)) {
    case CommandCode::kSelectModels:
    case CommandCode::kEnterTeach:
    case CommandCode::kLeaveTeach:
    case CommandCode::kResetCounters: return static_cast<CommandCode>(raw);
    case CommandCode::kNone: break;
  }
  return CommandCode::kNone;
}

}  // namespace

void encode_result_block(const PlcResult& result, std::uint32_t seq,
                         std::span<std::uint16_t, map::kResultBlockCount> block) {
  // Index by absolute register address so the code reads like the map.
  auto at = [&block](std::uint16_t address) { return block.data() + (address - map::kResultBlockFirst); };
  put_u32(at(map::kResultSeq), seq);
  put_u32(at(map::kAcqId), result.acq_id);
  *at(map::kResultCode) = static_cast<std::uint16_t>(result.code);
  *at(map::kPartId) = result.part_id;
  *at(map::kConfidence) = result.confidence_permille;
  *at(map::kSource) = static_cast<std::uint16_t>(result.source);
  put_s32(at(map::kPoseX), result.x_um);
  put_s32(at(map::kPoseY), result.y_um);
  put_s32(at(map::kPoseZ), result.z_um);
  put_s32(at(map::kPoseRx), result.rx_mdeg);
  put_s32(at(map::kPoseRy), result.ry_mdeg);
  put_s32(at(map::kPoseRz), result.rz_mdeg);
  put_u64(at(map::kTimestamp), result.timestamp_us);
  *at(map::kCycleMs) = result.cycle_ms;
  *at(map::kSigmaX) = result.sigma_x_um;
  *at(map::kSigmaY) = result.sigma_y_um;
  *at(map::kSigmaZ) = result.sigma_z_um;
  *at(map::kSigmaRx) = result.sigma_rx_mdeg;
  *at(map::kSigmaRy) = result.sigma_ry_mdeg;
  *at(map::kSigmaRz) = result.sigma_rz_mdeg;
  // The copies last: a PLC trusts what it read only when its copy agrees with 200-201 (a version-1 PLC reads up to
  // the first, a version-2 PLC checks both).
  put_u32(at(map::kResultSeqCopy), seq);
  put_u32(at(map::kResultSeqCopy2), seq);
}

LinkCore::LinkCore(const PlcLinkConfig& config)
    : config_(config),
      capacity_(std::max<std::size_t>(config.result_queue_capacity, 1)),
      slots_(std::make_unique<Slot[]>(capacity_)) {}

// ---------------------------------------------------------------- production side

PublishStatus LinkCore::publish(const PlcResult& result) {
  if (publishing_.test_and_set(std::memory_order_acquire)) return PublishStatus::kConcurrent;
  const std::uint64_t head = head_.load(std::memory_order_relaxed);
  const std::uint64_t tail = tail_.load(std::memory_order_acquire);
  if (head - tail >= capacity_) {
    // Reject the newest rather than drop the oldest: queued results belong to parts already further down the
    // conveyor, which the PLC expects in order; the caller learns of the loss at once from the return value.
    overrun_.store(true, std::memory_order_release);
    rejected_.fetch_add(1, std::memory_order_relaxed);
    publishing_.clear(std::memory_order_release);
    return PublishStatus::kQueueFull;
  }
  seq_ = seq_ + 1 == 0 ? 1 : seq_ + 1;  // 0 means "no result yet" on the wire, so the wrap skips it
  Slot& slot = slots_[head % capacity_];
  slot.result = result;
  slot.seq = seq_;
  head_.store(head + 1, std::memory_order_release);
  published_.fetch_add(1, std::memory_order_relaxed);
  last_seq_.store(seq_, std::memory_order_relaxed);
  publishing_.clear(std::memory_order_release);
  return PublishStatus::kQueued;
}

void LinkCore::set_flag(StatusFlag flag, bool on) {
  const auto bit = static_cast<std::uint16_t>(static_cast<std::uint16_t>(flag) & kProductionFlagBits);
  if (on) {
    flags_.fetch_or(bit, std::memory_order_release);
  } else {
    flags_.fetch_and(static_cast<std::uint16_t>(~bit), std::memory_order_release);
  }
}

void LinkCore::set_error(ErrorCode code) {
  error_.store(static_cast<std::uint16_t>(code), std::memory_order_release);
}

void LinkCore::set_warning(WarningCode code) {
  warning_.store(static_cast<std::uint16_t>(code), std::memory_order_release);
}

void LinkCore::set_active_models(std::uint16_t database_id) {
  active_models_.store(database_id, std::memory_order_release);
}

void LinkCore::set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers) {
  trigger_counters_.store((std::uint64_t{trigger_count} << kCountersShift) | missed_triggers,
                          std::memory_order_release);
}

void LinkCore::complete_command(bool ok) {
  const std::uint16_t answer = ok ? map::kStatusCmdDone : map::kStatusCmdFailed;
  std::uint16_t old_flags = flags_.load(std::memory_order_relaxed);
  while (!flags_.compare_exchange_weak(old_flags,
                                       static_cast<std::uint16_t>((old_flags & ~kCommandAnswerBits) | answer),
                                       std::memory_order_release, std::memory_order_relaxed)) {
  }
}

PlcCommands LinkCore::take_commands() {
  PlcCommands commands;
  commands.trigger_enable = trigger_enable_.load(std::memory_order_acquire);
  const std::uint32_t sw = sw_trigger_edges_.load(std::memory_order_acquire);
  commands.sw_triggers = sw - sw_trigger_seen_;
  sw_trigger_seen_ = sw;
  const std::uint32_t clears = clear_error_edges_.load(std::memory_order_acquire);
  commands.clear_errors = clears - clear_error_seen_;
  clear_error_seen_ = clears;
  const std::uint64_t mailbox = exec_mailbox_.load(std::memory_order_acquire);
  const auto exec_count = static_cast<std::uint16_t>(mailbox >> kMailboxCountShift);
  if (exec_count != exec_seen_) {
    exec_seen_ = exec_count;
    commands.exec_command = true;
    commands.command_raw = static_cast<std::uint16_t>(mailbox >> kMailboxCommandShift);
    commands.command = to_command(commands.command_raw);
    commands.command_arg = static_cast<std::uint32_t>(mailbox & kMailboxArgMask);
  }
  commands.plc_heartbeat_lost = plc_hb_lost_.load(std::memory_order_acquire);
  return commands;
}

void LinkCore::heartbeat(std::int64_t now_ns) {
  last_loop_kick_ns_.store(now_ns, std::memory_order_release);
}

LinkStats LinkCore::stats() const {
  LinkStats stats;
  stats.results_published = published_.load(std::memory_order_relaxed);
  stats.results_rejected = rejected_.load(std::memory_order_relaxed);
  stats.results_presented = presented_.load(std::memory_order_relaxed);
  stats.results_acked = acked_.load(std::memory_order_relaxed);
  const std::uint64_t tail = tail_.load(std::memory_order_acquire);
  const std::uint64_t head = head_.load(std::memory_order_acquire);
  stats.queue_depth = static_cast<std::uint32_t>(head >= tail ? head - tail : 0);
  stats.last_seq = last_seq_.load(std::memory_order_relaxed);
  stats.heartbeat_losses = heartbeat_losses_.load(std::memory_order_relaxed);
  stats.loop_stalls = loop_stalls_.load(std::memory_order_relaxed);
  return stats;
}

// ---------------------------------------------------------------- network side

void LinkCore::reset(std::int64_t now_ns) {
  regs_.fill(0);
  PlcResult empty;  // pose fields carry the invalid marker until a result arrives
  encode_result_block(
      empty, 0,
      std::span<std::uint16_t, map::kResultBlockCount>(regs_.data() + map::kResultBlockFirst, map::kResultBlockCount));
  state_ = BlockState::kIdle;
  presented_at_ns_ = now_ns;
  prev_control_ = 0;
  prev_plc_heartbeat_ = 0;
  last_plc_heartbeat_change_ns_ = now_ns;
  heartbeat_tick_ns_ = now_ns;
  hb_lost_ = false;
  loop_silent_ = false;
  last_loop_kick_ns_.store(now_ns, std::memory_order_release);  // grace period until the loop's first call
  service(now_ns);
}

void LinkCore::update_heartbeat(std::int64_t now_ns) {
  const std::int64_t period_ns = map::kHeartbeatPeriodMs * kNsPerMs;
  if (now_ns < heartbeat_tick_ns_) return;
  const std::int64_t periods = (now_ns - heartbeat_tick_ns_) / period_ns;
  if (periods == 0) return;
  heartbeat_tick_ns_ += periods * period_ns;
  const bool watched = config_.loop_watchdog_ms > 0;
  const bool silent =
      watched && now_ns - last_loop_kick_ns_.load(std::memory_order_acquire) > config_.loop_watchdog_ms * kNsPerMs;
  if (silent && !loop_silent_) {
    loop_stalls_.fetch_add(1, std::memory_order_relaxed);
    CS_LOG_WARN(kComponent, "production loop silent for more than %d ms: HEARTBEAT frozen", config_.loop_watchdog_ms);
  }
  loop_silent_ = silent;
  if (!silent) {
    // uint16 arithmetic wraps at 65536 as documented.
    regs_[map::kHeartbeat] = static_cast<std::uint16_t>(regs_[map::kHeartbeat] + static_cast<std::uint64_t>(periods));
  }
}

bool LinkCore::present_next(std::int64_t now_ns) {
  const std::uint64_t tail = tail_.load(std::memory_order_relaxed);
  if (tail == head_.load(std::memory_order_acquire)) return false;
  const Slot& slot = slots_[tail % capacity_];
  encode_result_block(
      slot.result, slot.seq,
      std::span<std::uint16_t, map::kResultBlockCount>(regs_.data() + map::kResultBlockFirst, map::kResultBlockCount));
  tail_.store(tail + 1, std::memory_order_release);  // the slot may be reused only after it was copied out
  presented_.fetch_add(1, std::memory_order_relaxed);
  state_ = BlockState::kPresented;
  presented_at_ns_ = now_ns;
  return true;
}

void LinkCore::service(std::int64_t now_ns) {
  update_heartbeat(now_ns);

  if (config_.plc_heartbeat_timeout_ms > 0) {
    const bool lost = now_ns - last_plc_heartbeat_change_ns_ > config_.plc_heartbeat_timeout_ms * kNsPerMs;
    if (lost && !hb_lost_) {
      heartbeat_losses_.fetch_add(1, std::memory_order_relaxed);
      CS_LOG_WARN(kComponent, "PLC heartbeat unchanged for more than %d ms: PLC_HB_LOST, result withheld",
                  config_.plc_heartbeat_timeout_ms);
    } else if (!lost && hb_lost_) {
      CS_LOG_INFO(kComponent, "PLC heartbeat back");
    }
    hb_lost_ = lost;
  } else {
    hb_lost_ = false;
  }
  plc_hb_lost_.store(hb_lost_, std::memory_order_release);

  const std::uint16_t error = error_.load(std::memory_order_acquire);
  const bool withheld = error != 0 || hb_lost_;  // a suspect link or a fault: nothing may look fresh
  const bool ack = (regs_[map::kControl] & map::kControlResultAck) != 0;

  if (config_.ack_mode == AckMode::kHandshake) {
    if (state_ == BlockState::kPresented && ack) {
      state_ = BlockState::kAcked;
      acked_.fetch_add(1, std::memory_order_relaxed);
    }
    if (state_ == BlockState::kAcked && !ack) state_ = BlockState::kIdle;
    if (state_ == BlockState::kIdle && !ack && !withheld) (void)present_next(now_ns);
  } else {
    const bool held_long_enough = now_ns - presented_at_ns_ >= config_.poll_hold_ms * kNsPerMs;
    if (!withheld && (state_ != BlockState::kPresented || held_long_enough)) (void)present_next(now_ns);
  }

  const bool valid = state_ == BlockState::kPresented && !withheld;
  const std::uint16_t warning = warning_.load(std::memory_order_acquire);
  std::uint16_t status = flags_.load(std::memory_order_acquire);
  if (error != 0) status |= map::kStatusError;
  if (warning != 0) status |= map::kStatusWarning;
  if (valid) status |= map::kStatusResultValid;
  if (overrun_.load(std::memory_order_acquire)) status |= map::kStatusResultOverrun;
  if (hb_lost_) status |= map::kStatusPlcHbLost;
  regs_[map::kStatus] = status;
  regs_[map::kErrorCode] = error;
  regs_[map::kWarningCode] = warning;
  regs_[map::kActiveModels] = active_models_.load(std::memory_order_acquire);
  const std::uint64_t counters = trigger_counters_.load(std::memory_order_acquire);
  put_u32(regs_.data() + map::kTriggerCount, static_cast<std::uint32_t>(counters >> kCountersShift));
  put_u32(regs_.data() + map::kMissedTriggers, static_cast<std::uint32_t>(counters & 0xFFFF'FFFFu));
  const std::uint64_t depth = head_.load(std::memory_order_acquire) - tail_.load(std::memory_order_relaxed);
  regs_[map::kResultQueueDepth] = static_cast<std::uint16_t>(std::min<std::uint64_t>(depth, kWordMask));
  regs_[map::kMapVersionRegister] = map::kMapVersion;
}

void LinkCore::clear_command_answer() {
  flags_.fetch_and(static_cast<std::uint16_t>(~kCommandAnswerBits), std::memory_order_release);
}

void LinkCore::on_plc_write(std::int64_t now_ns) {
  const std::uint16_t control = regs_[map::kControl];
  const auto rising = static_cast<std::uint16_t>(control & ~prev_control_);
  const auto falling = static_cast<std::uint16_t>(prev_control_ & ~control);
  prev_control_ = control;

  trigger_enable_.store((control & map::kControlTriggerEnable) != 0, std::memory_order_release);
  if ((rising & map::kControlSwTrigger) != 0) sw_trigger_edges_.fetch_add(1, std::memory_order_release);
  if ((rising & map::kControlClearError) != 0) {
    overrun_.store(false, std::memory_order_release);  // the PLC has seen the overrun; the latch is the link's own
    clear_error_edges_.fetch_add(1, std::memory_order_release);
  }
  if ((rising & map::kControlExecCmd) != 0) {
    clear_command_answer();  // a new command: the previous answer no longer applies
    const std::uint64_t count = (exec_mailbox_.load(std::memory_order_relaxed) >> kMailboxCountShift) + 1;
    const std::uint64_t arg = (std::uint64_t{regs_[map::kCommandArg]} << kWordBits) | regs_[map::kCommandArg + 1];
    exec_mailbox_.store(
        (count << kMailboxCountShift) | (std::uint64_t{regs_[map::kCommand]} << kMailboxCommandShift) | arg,
        std::memory_order_release);
  }
  if ((falling & map::kControlExecCmd) != 0) clear_command_answer();

  if (regs_[map::kPlcHeartbeat] != prev_plc_heartbeat_) {
    prev_plc_heartbeat_ = regs_[map::kPlcHeartbeat];
    last_plc_heartbeat_change_ns_ = now_ns;
  }
}

}  // namespace cellsight::drivers
