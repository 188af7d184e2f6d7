// Simulated PLC link: the Modbus server's register image and handshake in memory, driven by simulated time.
#pragma once

#include <atomic>
#include <cstdint>
#include <span>

#include "drivers/modbus/link_core.hpp"
#include "drivers/modbus/plc_link.hpp"

namespace cellsight::drivers {

// For tests of the production loop without sockets. The production side is the same as ModbusServer's (same
// LinkCore); the PLC side is a set of calls that answer exactly what the server would answer on the wire, including
// exception codes (request_screen's screen_access), so a simulated PLC program carries over to a real PLC.
class SimPlcLink final : public PlcLink {
 public:
  // Returned by the plc_* calls while the link is stopped (a real PLC would see a refused connection).
  static constexpr std::uint8_t kLinkDown = 0xFF;

  explicit SimPlcLink(const PlcLinkConfig& config = {});

  Status start() override;  // clears the register image at the current simulated time
  void stop() override;

  PublishStatus publish(const PlcResult& result) override { return core_.publish(result); }
  void set_flag(StatusFlag flag, bool on) override { core_.set_flag(flag, on); }
  void set_error(ErrorCode code) override { core_.set_error(code); }
  void set_warning(WarningCode code) override { core_.set_warning(code); }
  void set_active_models(std::uint16_t database_id) override { core_.set_active_models(database_id); }
  void set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers) override {
    core_.set_trigger_counters(trigger_count, missed_triggers);
  }
  void complete_command(bool ok) override { core_.complete_command(ok); }
  PlcCommands take_commands() override { return core_.take_commands(); }
  void heartbeat() override { core_.heartbeat(now_ns_.load(std::memory_order_acquire)); }
  [[nodiscard]] LinkStats stats() const override { return core_.stats(); }

  // ---- simulated clock and PLC: call from one thread (it plays the server's network thread) ----
  // Simulated CLOCK_MONOTONIC; never goes backwards. Runs the link's periodic work (heartbeat, watchdogs, handshake).
  void advance_to(std::int64_t now_ns);
  [[nodiscard]] std::int64_t now_ns() const { return now_ns_.load(std::memory_order_acquire); }
  // FC03 (holding) or FC04 (input registers): 0 or the Modbus exception code the server would send.
  [[nodiscard]] std::uint8_t plc_read(std::uint16_t address, std::span<std::uint16_t> out,
                                      bool input_registers = false);
  // FC06 for one value, FC16 for several.
  [[nodiscard]] std::uint8_t plc_write(std::uint16_t address, std::span<const std::uint16_t> values);
  [[nodiscard]] std::uint8_t plc_write_register(std::uint16_t address, std::uint16_t value) {
    return plc_write(address, std::span<const std::uint16_t>(&value, 1));
  }

 private:
  LinkCore core_;
  std::atomic<std::int64_t> now_ns_{0};
  bool started_ = false;
};

}  // namespace cellsight::drivers
