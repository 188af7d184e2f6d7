// Screening of Modbus TCP requests before libmodbus sees them: MBAP framing, function code, quantity, address.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

namespace cellsight::drivers {

// Debian's libmodbus 3.1.6 modbus_reply trusts the request: FC16 copies as many bytes as the quantity says, bad
// quantities make it sleep and flush the socket, and it serves every function code it knows. So every frame goes
// through screen_request first; only kServe frames reach modbus_reply, and those are exactly what it handles safely.

inline constexpr std::size_t kMbapHeaderBytes = 7;  // transaction id, protocol id, length, unit id
inline constexpr std::size_t kMaxAduBytes = 260;    // MBAP 7 + PDU 253
inline constexpr std::size_t kMaxMbapLength = 254;  // unit id + PDU
inline constexpr std::size_t kMinMbapLength = 2;    // unit id + function code
inline constexpr std::size_t kExceptionReplyBytes = 9;

enum class ScreenVerdict : std::uint8_t {
  kIncomplete,  // the frame is not all there yet; read more (the byte timeout bounds the wait)
  kServe,       // hand the first frame_bytes to modbus_reply
  kException,   // answer exception_code for the first frame_bytes, keep the connection
  kClose,       // not Modbus TCP framing; the stream cannot be resynchronised, drop the connection
};

enum class CloseReason : std::uint8_t { kNone, kProtocolId, kLengthTooShort, kLengthTooLong };

struct ScreenResult {
  ScreenVerdict verdict = ScreenVerdict::kIncomplete;
  CloseReason close_reason = CloseReason::kNone;
  std::size_t frame_bytes = 0;  // the whole ADU (MBAP + PDU); set for kServe and kException
  std::uint8_t function = 0;
  std::uint8_t exception_code = 0;  // set for kException
  std::uint16_t address = 0;        // set once the PDU is long enough to carry it
  std::uint16_t quantity = 0;       // registers read or written (1 for FC06)
};

// Access check on an already parsed request: 0 when it may be served, else the Modbus exception code.
// Order as in the Modbus Application Protocol: function (01), quantity (03), then address range (02).
[[nodiscard]] std::uint8_t screen_access(std::uint8_t function, std::uint16_t address, std::uint16_t quantity);

// Looks at the front of a client's receive buffer. Pure: no I/O, no allocation; safe on any bytes (fuzzed).
[[nodiscard]] ScreenResult screen_request(std::span<const std::uint8_t> bytes);

// True for FC06/FC16 (the request changes registers).
[[nodiscard]] constexpr bool is_write_function(std::uint8_t function) {
  return function == 0x06 || function == 0x10;
}

// The exception ADU answering the request at the front of `request` (at least kMbapHeaderBytes + 1 bytes).
void build_exception_reply(std::span<const std::uint8_t> request, std::uint8_t exception_code,
                           std::span<std::uint8_t, kExceptionReplyBytes> out);

}  // namespace cellsight::drivers
