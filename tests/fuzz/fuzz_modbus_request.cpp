// libFuzzer target: Modbus TCP request screening on arbitrary bytes, checked against an independent oracle and
// replayed through libmodbus's modbus_reply whenever the screen lets a frame through. Build and run: README "Fuzzing".
#include <fcntl.h>
#include <modbus/modbus.h>
#include <sys/socket.h>
#include <unistd.h>

#include <array>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>
#include <span>

#include "drivers/modbus/register_map.hpp"
#include "drivers/modbus/request_screen.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight::drivers;
using cellsight::fuzz::violated;

std::uint16_t be16(const std::uint8_t* p) {
  return static_cast<std::uint16_t>((p[0] << 8) | p[1]);
}

// The map written out register by register from DESIGN.md, independent of register_map.hpp and the screen.
bool readable_holding(std::uint32_t a) {
  return a <= 9 || (a >= 100 && a <= 119) || (a >= 200 && a <= 234);
}
bool readable_input(std::uint32_t a) {
  return (a >= 100 && a <= 119) || (a >= 200 && a <= 234);
}
bool writable(std::uint32_t a) {
  return a <= 9;
}

// libmodbus replies into one end of a socket pair; the fuzzer reads the other end and checks the reply's shape.
struct ReplyPath {
  ReplyPath() {
    if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, fds) != 0) violated("socketpair");
    (void)fcntl(fds[1], F_SETFL, O_NONBLOCK);
    ctx = modbus_new_tcp("127.0.0.1", 1502);  // never connects: only the reply path is used
    if (ctx == nullptr) violated("modbus_new_tcp");
    (void)modbus_set_socket(ctx, fds[0]);
    mapping.nb_registers = modbus_map::kRegisterSpan;
    mapping.tab_registers = registers.data();
    mapping.nb_input_registers = modbus_map::kRegisterSpan;
    mapping.tab_input_registers = registers.data();
  }
  int fds[2] = {-1, -1};
  modbus_t* ctx = nullptr;
  modbus_mapping_t mapping{};
  std::array<std::uint16_t, modbus_map::kRegisterSpan> registers{};
};

void check_served(const std::uint8_t* frame, const ScreenResult& r, ReplyPath& path) {
  const std::uint8_t function = frame[7];
  const std::uint16_t address = be16(frame + 8);
  const std::size_t mbap_length = be16(frame + 4);
  CS_FUZZ_EXPECT(r.frame_bytes == 6 + mbap_length);
  std::uint32_t quantity = 0;
  bool (*allowed)(std::uint32_t) = nullptr;
  std::size_t reply_bytes = 0;
  switch (function) {
    case 3:
    case 4:
      quantity = be16(frame + 10);
      CS_FUZZ_EXPECT(r.frame_bytes == 12 && quantity >= 1 && quantity <= 125);
      allowed = function == 3 ? readable_holding : readable_input;
      reply_bytes = 9 + 2 * quantity;
      break;
    case 6:
      quantity = 1;
      CS_FUZZ_EXPECT(r.frame_bytes == 12);
      allowed = writable;
      reply_bytes = 12;
      break;
    case 16:
      quantity = be16(frame + 10);
      // What modbus_reply will read (byte count, then 2 * quantity data bytes) lies inside the frame.
      CS_FUZZ_EXPECT(quantity >= 1 && quantity <= 123 && frame[12] == 2 * quantity &&
                     r.frame_bytes == 13 + 2 * quantity);
      allowed = writable;
      reply_bytes = 12;
      break;
    default: violated("the screen serves only FC 03, 04, 06 and 16");
  }
  for (std::uint32_t a = address; a < address + quantity; ++a) CS_FUZZ_EXPECT(allowed(a));
  CS_FUZZ_EXPECT(r.address == address && r.quantity == quantity && r.function == function);

  // Then libmodbus answers it normally (no exception, the expected length) from an exact-size copy.
  const int sent = modbus_reply(path.ctx, frame, static_cast<int>(r.frame_bytes), &path.mapping);
  CS_FUZZ_EXPECT(sent == static_cast<int>(reply_bytes));
  std::array<std::uint8_t, 300> reply{};
  const ssize_t got = read(path.fds[1], reply.data(), reply.size());
  CS_FUZZ_EXPECT(got == static_cast<ssize_t>(reply_bytes));
  CS_FUZZ_EXPECT(reply[0] == frame[0] && reply[1] == frame[1] && reply[7] == function);
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static ReplyPath path;
  // An exact-size heap copy: any read past the input is an ASan report, not a silent over-read.
  std::unique_ptr<std::uint8_t[]> copy(new std::uint8_t[size == 0 ? 1 : size]);
  if (size > 0) std::memcpy(copy.get(), data, size);

  // Walk the bytes like the server walks a client's stream: frame after frame until one is incomplete or fatal.
  std::size_t offset = 0;
  while (offset < size) {
    const std::span<const std::uint8_t> rest(copy.get() + offset, size - offset);
    const ScreenResult r = screen_request(rest);
    if (r.verdict == ScreenVerdict::kIncomplete) {
      // Only when the header is clean and the frame it announces is longer than what is there.
      if (rest.size() >= 4) CS_FUZZ_EXPECT(be16(rest.data() + 2) == 0);
      if (rest.size() >= 6) {
        const std::size_t length = be16(rest.data() + 4);
        CS_FUZZ_EXPECT(length >= kMinMbapLength && length <= kMaxMbapLength && 6 + length > rest.size());
      }
      break;
    }
    if (r.verdict == ScreenVerdict::kClose) {
      CS_FUZZ_EXPECT(rest.size() >= 4);
      const bool bad_protocol = be16(rest.data() + 2) != 0;
      const bool bad_length =
          rest.size() >= 6 && (be16(rest.data() + 4) < kMinMbapLength || be16(rest.data() + 4) > kMaxMbapLength);
      CS_FUZZ_EXPECT(bad_protocol || bad_length);
      break;
    }
    CS_FUZZ_EXPECT(r.frame_bytes >= kMbapHeaderBytes + 1 && r.frame_bytes <= kMaxAduBytes &&
                   r.frame_bytes <= rest.size());
    if (r.verdict == ScreenVerdict::kException) {
      CS_FUZZ_EXPECT(r.exception_code >= 1 && r.exception_code <= 3);
      std::array<std::uint8_t, kExceptionReplyBytes> reply{};
      build_exception_reply(rest.first(r.frame_bytes), r.exception_code, reply);
      CS_FUZZ_EXPECT(reply[7] == (rest[7] | 0x80) && reply[8] == r.exception_code && reply[5] == 3);
    } else {
      // Exact-size copy of this frame alone, so modbus_reply cannot wander into the next one unnoticed.
      std::unique_ptr<std::uint8_t[]> frame(new std::uint8_t[r.frame_bytes]);
      std::memcpy(frame.get(), rest.data(), r.frame_bytes);
      check_served(frame.get(), r, path);
    }
    offset += r.frame_bytes;
  }
  return 0;
}
