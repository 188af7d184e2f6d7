// Simulated PLC link: LinkCore plus the request checks of the Modbus server, without sockets.
#include "drivers/modbus/sim_plc_link.hpp"

#include <algorithm>
#include <limits>

#include "drivers/modbus/request_screen.hpp"

namespace cellsight::drivers {

namespace map = modbus_map;

SimPlcLink::SimPlcLink(const PlcLinkConfig& config) : core_(config) {}

Status SimPlcLink::start() {
  core_.reset(now_ns());
  started_ = true;
  return {};
}

void SimPlcLink::stop() {
  started_ = false;
}

void SimPlcLink::advance_to(std::int64_t now_ns) {
  const std::int64_t now = std::max(now_ns, now_ns_.load(std::memory_order_relaxed));
  now_ns_.store(now, std::memory_order_release);
  if (started_) core_.service(now);
}

std::uint8_t SimPlcLink::plc_read(std::uint16_t address, std::span<std::uint16_t> out, bool input_registers) {
  if (!started_) return kLinkDown;
  const std::uint8_t function = input_registers ? map::kFcReadInputRegisters : map::kFcReadHoldingRegisters;
  const auto quantity =
      static_cast<std::uint16_t>(std::min<std::size_t>(out.size(), std::numeric_limits<std::uint16_t>::max()));
  const std::uint8_t code = screen_access(function, address, quantity);
  if (code != 0) return code;
  core_.service(now_ns());  // as the server does before every reply
  std::copy_n(core_.registers() + address, quantity, out.begin());
  return 0;
}

std::uint8_t SimPlcLink::plc_write(std::uint16_t address, std::span<const std::uint16_t> values) {
  if (!started_) return kLinkDown;
  const std::uint8_t function = values.size() == 1 ? map::kFcWriteSingleRegister : map::kFcWriteMultipleRegisters;
  const auto quantity =
      static_cast<std::uint16_t>(std::min<std::size_t>(values.size(), std::numeric_limits<std::uint16_t>::max()));
  const std::uint8_t code = screen_access(function, address, quantity);
  if (code != 0) return code;
  core_.service(now_ns());
  std::copy_n(values.begin(), quantity, core_.registers() + address);
  core_.on_plc_write(now_ns());
  core_.service(now_ns());
  return 0;
}

}  // namespace cellsight::drivers
