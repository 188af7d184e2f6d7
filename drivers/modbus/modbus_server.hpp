// PLC link over Modbus TCP (libmodbus): one network thread serves several PLC clients from the register image.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "drivers/modbus/plc_link.hpp"

namespace cellsight::drivers {

struct ModbusServerConfig {
  std::string bind_address = "0.0.0.0";  // dotted IPv4; 0.0.0.0 = every interface
  std::uint16_t port = 502;              // 0 = an ephemeral port (tests); see bound_port()
  // When every slot is taken, a newcomer evicts the client that has gone longest without a complete request, so idle
  // connections cannot lock a (reconnecting) PLC out. A client in the middle of a request is never evicted; when all
  // are, the newcomer is closed at once (each of them finishes or is dropped within byte_timeout_ms).
  std::int32_t max_clients = 4;
  // A request that has started arriving must be complete within this time, else the client is dropped: a slow or
  // stuck client never holds the others up (the server never waits for bytes, it only stops waiting for them).
  std::int32_t byte_timeout_ms = 100;
  std::int32_t idle_timeout_ms = 60'000;  // a client silent this long is dropped (frees its slot); 0 = never
  PlcLinkConfig link;
};

// Real backend of PlcLink. Every request is screened (request_screen.hpp) before libmodbus's modbus_reply sees it;
// only FC03/FC04/FC06/FC16 on the mapped blocks are served. The libmodbus context and the register image belong to
// the network thread alone; the production side reaches them only through LinkCore's lock-free hand-over.
class ModbusServer final : public PlcLink {
 public:
  explicit ModbusServer(const ModbusServerConfig& config);
  ~ModbusServer() override;  // stops

  // Binds, listens and starts the network thread. Fails with a message naming the cause (port in use, port 502
  // without CAP_NET_BIND_SERVICE, bad address).
  Status start() override;
  void stop() override;
  // The TCP port actually bound (differs from the config when it asked for 0); 0 before start().
  [[nodiscard]] std::uint16_t bound_port() const;

  PublishStatus publish(const PlcResult& result) override;
  void set_flag(StatusFlag flag, bool on) override;
  void set_error(ErrorCode code) override;
  void set_warning(WarningCode code) override;
  void set_active_models(std::uint16_t database_id) override;
  void set_trigger_counters(std::uint32_t trigger_count, std::uint32_t missed_triggers) override;
  void complete_command(bool ok) override;
  PlcCommands take_commands() override;
  void heartbeat() override;
  [[nodiscard]] LinkStats stats() const override;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;  // keeps libmodbus and socket headers out of this interface
};

}  // namespace cellsight::drivers
