// Screening of Modbus TCP requests: framing from the MBAP header, then function, quantity and address checks.
#include "drivers/modbus/request_screen.hpp"

#include "drivers/modbus/register_map.hpp"

namespace cellsight::drivers {
namespace {

namespace map = modbus_map;

constexpr std::size_t kProtocolIdOffset = 2;
constexpr std::size_t kLengthOffset = 4;
constexpr std::size_t kUnitOffset = 6;
constexpr std::size_t kLengthPrefixBytes = 6;  // bytes before the ones the MBAP length counts
// PDU sizes: function + address + quantity (or value); FC16 adds byte count and data.
constexpr std::size_t kFixedPduBytes = 5;
constexpr std::size_t kWriteMultipleHeaderBytes = 6;

constexpr std::uint16_t be16(const std::uint8_t* p) {
  return static_cast<std::uint16_t>((static_cast<unsigned>(p[0]) << 8) | p[1]);
}

constexpr bool inside(std::uint16_t address, std::uint16_t quantity, std::uint16_t first, std::uint16_t count) {
  // 32-bit arithmetic: address 65535 + quantity 125 must not wrap into the map.
  const std::uint32_t end = std::uint32_t{address} + quantity;
  return address >= first && end <= std::uint32_t{first} + count;
}

constexpr bool in_command_block(std::uint16_t address, std::uint16_t quantity) {
  return inside(address, quantity, map::kCommandBlockFirst, map::kCommandBlockCount);
}
constexpr bool in_read_only_block(std::uint16_t address, std::uint16_t quantity) {
  return inside(address, quantity, map::kStatusBlockFirst, map::kStatusBlockCount) ||
         inside(address, quantity, map::kResultBlockFirst, map::kResultBlockCount);
}

ScreenResult exception(ScreenResult result, std::uint8_t code) {
  result.verdict = ScreenVerdict::kException;
  result.exception_code = code;
  return result;
}

ScreenResult close(CloseReason reason) {
  ScreenResult result;
  result.verdict = ScreenVerdict::kClose;
  result.close_reason = reason;
  return result;
}

}  // namespace

std::uint8_t screen_access(std::uint8_t function, std::uint16_t address, std::uint16_t quantity) {
  switch (function) {
    case map::kFcReadHoldingRegisters:
      if (quantity < 1 || quantity > map::kMaxReadQuantity) return map::kExceptionIllegalDataValue;
      if (!in_command_block(address, quantity) && !in_read_only_block(address, quantity)) {
        return map::kExceptionIllegalDataAddress;
      }
      return 0;
    case map::kFcReadInputRegisters:
      if (quantity < 1 || quantity > map::kMaxReadQuantity) return map::kExceptionIllegalDataValue;
      if (!in_read_only_block(address, quantity)) return map::kExceptionIllegalDataAddress;
      return 0;
    case map::kFcWriteSingleRegister:
      if (quantity != 1) return map::kExceptionIllegalDataValue;
      if (!in_command_block(address, 1)) return map::kExceptionIllegalDataAddress;
      return 0;
    case map::kFcWriteMultipleRegisters:
      if (quantity < 1 || quantity > map::kMaxWriteQuantity) return map::kExceptionIllegalDataValue;
      if (!in_command_block(address, quantity)) return map::kExceptionIllegalDataAddress;
      return 0;
    default: return map::kExceptionIllegalFunction;
  }
}

ScreenResult screen_request(std::span<const std::uint8_t> bytes) {
  // Judge the header as soon as its fields arrive: a wrong protocol id or length is refused without waiting for
  // bytes that may never come.
  if (bytes.size() >= kProtocolIdOffset + 2 && be16(bytes.data() + kProtocolIdOffset) != 0) {
    return close(CloseReason::kProtocolId);
  }
  if (bytes.size() < kLengthOffset + 2) return ScreenResult{};
  const std::size_t mbap_length = be16(bytes.data() + kLengthOffset);
  if (mbap_length < kMinMbapLength) return close(CloseReason::kLengthTooShort);
  if (mbap_length > kMaxMbapLength) return close(CloseReason::kLengthTooLong);
  const std::size_t frame_bytes = kLengthPrefixBytes + mbap_length;
  if (bytes.size() < frame_bytes) return ScreenResult{};

  ScreenResult result;
  result.frame_bytes = frame_bytes;
  const std::uint8_t* pdu = bytes.data() + kUnitOffset + 1;
  const std::size_t pdu_bytes = mbap_length - 1;
  result.function = pdu[0];

  switch (result.function) {
    case map::kFcReadHoldingRegisters:
    case map::kFcReadInputRegisters:
    case map::kFcWriteSingleRegister: {
      // "Implied length incorrect" is exception 03 (Modbus Application Protocol 7, code 03).
      if (pdu_bytes != kFixedPduBytes) return exception(result, map::kExceptionIllegalDataValue);
      result.address = be16(pdu + 1);
      result.quantity = result.function == map::kFcWriteSingleRegister ? std::uint16_t{1} : be16(pdu + 3);
      break;
    }
    case map::kFcWriteMultipleRegisters: {
      if (pdu_bytes < kWriteMultipleHeaderBytes) return exception(result, map::kExceptionIllegalDataValue);
      result.address = be16(pdu + 1);
      result.quantity = be16(pdu + 3);
      const std::size_t byte_count = pdu[5];
      // libmodbus copies quantity * 2 bytes without looking at the frame length: all three must agree.
      if (pdu_bytes != kWriteMultipleHeaderBytes + byte_count || byte_count != std::size_t{2} * result.quantity) {
        return exception(result, map::kExceptionIllegalDataValue);
      }
      break;
    }
    default: return exception(result, map::kExceptionIllegalFunction);
  }

  const std::uint8_t code = screen_access(result.function, result.address, result.quantity);
  if (code != 0) return exception(result, code);
  result.verdict = ScreenVerdict::kServe;
  return result;
}

void build_exception_reply(std::span<const std::uint8_t> request, std::uint8_t exception_code,
                           std::span<std::uint8_t, kExceptionReplyBytes> out) {
  constexpr std::uint8_t kExceptionFlag = 0x80;
  constexpr std::uint8_t kReplyMbapLength = 3;   // unit id, function, exception code
  out[0] = request.size() > 0 ? request[0] : 0;  // transaction id echoed
  out[1] = request.size() > 1 ? request[1] : 0;
  out[2] = 0;  // protocol id
  out[3] = 0;
  out[4] = 0;
  out[5] = kReplyMbapLength;
  out[6] = request.size() > kUnitOffset ? request[kUnitOffset] : 0;
  out[7] =
      static_cast<std::uint8_t>((request.size() > kUnitOffset + 1 ? request[kUnitOffset + 1] : 0) | kExceptionFlag);
  out[8] = exception_code;
}

}  // namespace cellsight::drivers
