// Register image and result handshake shared by both PLC link backends, with a lock-free production-side hand-over.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>

#include "drivers/modbus/plc_link.hpp"
#include "drivers/modbus/register_map.hpp"

namespace cellsight::drivers {

// Writes one result into the 35 registers of the result block (200-234), high word first, sequence copies last.
void encode_result_block(const PlcResult& result, std::uint32_t seq,
                         std::span<std::uint16_t, modbus_map::kResultBlockCount> block);

// Two sides, two threads:
// - production side (publish, setters, take_commands, heartbeat): wait-free, no allocation, never touches the
//   register image; results go through a single-producer/single-consumer ring sized at construction, the rest
//   through atomics.
// - network side (reset, service, on_plc_write, registers): one thread only, the one that serves Modbus requests.
//   It owns the register image and is the only reader of the ring, so a request always sees a whole result block.
class LinkCore {
 public:
  explicit LinkCore(const PlcLinkConfig& config);  // allocates the ring: start-up only
  LinkCore(const LinkCore&) = delete;
  LinkCore& operator=(const LinkCore&) = delete;

  // ---- production side ----
  [[nodiscard]] PublishStatus publish(const PlcResult& result);
  void set_flag(StatusFlag flag, bool on);
  void set_error(ErrorCode code);
  void set_warning(WarningCode code);
  void set_active_models(std::uint16_t database_id);
  void set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers);
  void complete_command(bool ok);
  [[nodiscard]] PlcCommands take_commands();
  void heartbeat(std::int64_t now_ns);
  [[nodiscard]] LinkStats stats() const;  // the link's counters; a backend adds its transport counters

  // ---- network side ----
  // Clears the register image and starts the clocks (heartbeat, PLC watchdog, loop watchdog) at now_ns.
  void reset(std::int64_t now_ns);
  // Heartbeat, watchdogs, status registers and the handshake. Call before answering every request and at least
  // every heartbeat period.
  void service(std::int64_t now_ns);
  // A write request landed in the command block: detect CONTROL edges and PLC_HEARTBEAT changes.
  void on_plc_write(std::int64_t now_ns);
  [[nodiscard]] std::uint16_t* registers() { return regs_.data(); }
  [[nodiscard]] const std::uint16_t* registers() const { return regs_.data(); }

 private:
  struct Slot {
    PlcResult result;
    std::uint32_t seq = 0;
  };
  enum class BlockState : std::uint8_t { kIdle, kPresented, kAcked };

  [[nodiscard]] bool present_next(std::int64_t now_ns);
  void update_heartbeat(std::int64_t now_ns);
  void clear_command_answer();

  // Members are ordered by size (8, 4, 2, 1 bytes) to keep the object compact; the comments say who writes what.
  const PlcLinkConfig config_;
  const std::size_t capacity_;
  std::unique_ptr<Slot[]> slots_;
  // Ring indices: monotonic counts; head_ written only by publish(), tail_ only by the network side.
  std::atomic<std::uint64_t> head_{0};
  std::atomic<std::uint64_t> tail_{0};
  // Production -> network.
  std::atomic<std::uint64_t> trigger_counters_{0};  // trigger count << 32 | missed: one store keeps them paired
  std::atomic<std::int64_t> last_loop_kick_ns_{0};
  // Network -> production.
  std::atomic<std::uint64_t> exec_mailbox_{0};  // edge count (16) | command (16) | argument (32), one atomic word
  // Counters (each written by one side, read anywhere).
  std::atomic<std::uint64_t> published_{0};
  std::atomic<std::uint64_t> rejected_{0};
  std::atomic<std::uint64_t> presented_{0};
  std::atomic<std::uint64_t> acked_{0};
  std::atomic<std::uint64_t> heartbeat_losses_{0};
  std::atomic<std::uint64_t> loop_stalls_{0};
  // Network side only.
  std::int64_t presented_at_ns_ = 0;
  std::int64_t last_plc_heartbeat_change_ns_ = 0;
  std::int64_t heartbeat_tick_ns_ = 0;

  std::atomic<std::uint32_t> sw_trigger_edges_{0};   // network -> production
  std::atomic<std::uint32_t> clear_error_edges_{0};  // network -> production
  std::atomic<std::uint32_t> last_seq_{0};           // production side, read anywhere
  std::uint32_t seq_ = 0;                            // production side only
  std::uint32_t sw_trigger_seen_ = 0;                // production side: what take_commands() already reported
  std::uint32_t clear_error_seen_ = 0;

  std::atomic<std::uint16_t> flags_{0};  // production -> network: StatusFlag bits plus CMD_DONE/CMD_FAILED
  std::atomic<std::uint16_t> error_{0};
  std::atomic<std::uint16_t> warning_{0};
  std::atomic<std::uint16_t> active_models_{0};
  std::uint16_t exec_seen_ = 0;                                  // production side only
  std::array<std::uint16_t, modbus_map::kRegisterSpan> regs_{};  // network side only: the register image
  std::uint16_t prev_control_ = 0;                               // network side only
  std::uint16_t prev_plc_heartbeat_ = 0;

  std::atomic_flag publishing_ = ATOMIC_FLAG_INIT;  // detects a second producer instead of corrupting the ring
  std::atomic<bool> overrun_{false};                // production sets, network clears on CLEAR_ERROR
  std::atomic<bool> trigger_enable_{false};         // network -> production
  std::atomic<bool> plc_hb_lost_{false};            // network -> production
  BlockState state_ = BlockState::kIdle;            // network side only
  bool hb_lost_ = false;
  bool loop_silent_ = false;
};

}  // namespace cellsight::drivers
