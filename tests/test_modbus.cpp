// Tests of the PLC link: request screen, handshake (simulated and on a real server), real clients (pymodbus, mbpoll).
#include <arpa/inet.h>
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <catch2/catch.hpp>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "drivers/modbus/modbus_server.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "drivers/modbus/register_map.hpp"
#include "drivers/modbus/request_screen.hpp"
#include "drivers/modbus/sim_plc_link.hpp"
#include "tests/support/alloc_counter.hpp"

extern char** environ;

namespace {

using namespace cellsight::drivers;
namespace map = cellsight::drivers::modbus_map;
using Clock = std::chrono::steady_clock;
// Counts allocations made by any thread while alive (proves "no allocation").
using cellsight::test::AllocationWindow;

constexpr std::int64_t kNsPerMs = 1'000'000;

template <class Predicate>
bool wait_until(Predicate predicate, int timeout_ms) {
  const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
  while (Clock::now() < deadline) {
    if (predicate()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return predicate();
}

std::int64_t elapsed_ms(Clock::time_point since) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(Clock::now() - since).count();
}

// ------------------------------------------------------------------ independent decoding (the DESIGN.md table)
std::uint32_t u32_at(const std::uint16_t* regs, int address, int base) {
  return (std::uint32_t{regs[address - base]} << 16) | regs[address - base + 1];
}
std::int32_t s32_at(const std::uint16_t* regs, int address, int base) {
  return static_cast<std::int32_t>(u32_at(regs, address, base));
}

// The result block's length as a PLC reads it (README "Register table"): version 2 reads 200-234, a PLC written for
// version 1 reads 200-226.
constexpr int kBlockWords = 35;
constexpr int kBlockWordsV1 = 27;
constexpr std::uint16_t kMapVersion = 2;  // MAP_VERSION (register 110) of this map
using BlockWords = std::array<std::uint16_t, kBlockWords>;

struct DecodedBlock {
  std::uint32_t seq = 0;
  std::uint32_t seq_copy = 0;
  std::uint32_t seq_copy2 = 0;  // 0 in a version-1 read, which does not reach it
  PlcResult result;
};

// Addresses written out from the README's table on purpose rather than taken from register_map.hpp. A version-1 read
// (27 words) leaves the version-2 fields at PlcResult's defaults.
DecodedBlock decode_block(std::span<const std::uint16_t> words) {
  constexpr int kBase = 200;
  const std::uint16_t* regs = words.data();
  DecodedBlock block;
  block.seq = u32_at(regs, 200, kBase);
  block.result.acq_id = u32_at(regs, 202, kBase);
  block.result.code = static_cast<ResultCode>(regs[204 - kBase]);
  block.result.part_id = regs[205 - kBase];
  block.result.confidence_permille = regs[206 - kBase];
  block.result.source = static_cast<ResultSource>(regs[207 - kBase]);
  block.result.x_um = s32_at(regs, 208, kBase);
  block.result.y_um = s32_at(regs, 210, kBase);
  block.result.z_um = s32_at(regs, 212, kBase);
  block.result.rx_mdeg = s32_at(regs, 214, kBase);
  block.result.ry_mdeg = s32_at(regs, 216, kBase);
  block.result.rz_mdeg = s32_at(regs, 218, kBase);
  block.result.timestamp_us = (std::uint64_t{u32_at(regs, 220, kBase)} << 32) | u32_at(regs, 222, kBase);
  block.result.cycle_ms = regs[224 - kBase];
  block.seq_copy = u32_at(regs, 225, kBase);
  if (words.size() < kBlockWords) return block;
  block.result.sigma_x_um = regs[227 - kBase];
  block.result.sigma_y_um = regs[228 - kBase];
  block.result.sigma_z_um = regs[229 - kBase];
  block.result.sigma_rx_mdeg = regs[230 - kBase];
  block.result.sigma_ry_mdeg = regs[231 - kBase];
  block.result.sigma_rz_mdeg = regs[232 - kBase];
  block.seq_copy2 = u32_at(regs, 233, kBase);
  return block;
}

// The 35 words a PLC must see for `result`, written from the README's table (high word first).
BlockWords expected_words(const PlcResult& r, std::uint32_t seq) {
  BlockWords w{};
  auto put32 = [&w](int address, std::uint32_t v) {
    w[static_cast<std::size_t>(address - 200)] = static_cast<std::uint16_t>(v >> 16);
    w[static_cast<std::size_t>(address - 199)] = static_cast<std::uint16_t>(v & 0xFFFF);
  };
  put32(200, seq);
  put32(202, r.acq_id);
  w[4] = static_cast<std::uint16_t>(r.code);
  w[5] = r.part_id;
  w[6] = r.confidence_permille;
  w[7] = static_cast<std::uint16_t>(r.source);
  put32(208, static_cast<std::uint32_t>(r.x_um));
  put32(210, static_cast<std::uint32_t>(r.y_um));
  put32(212, static_cast<std::uint32_t>(r.z_um));
  put32(214, static_cast<std::uint32_t>(r.rx_mdeg));
  put32(216, static_cast<std::uint32_t>(r.ry_mdeg));
  put32(218, static_cast<std::uint32_t>(r.rz_mdeg));
  put32(220, static_cast<std::uint32_t>(r.timestamp_us >> 32));
  put32(222, static_cast<std::uint32_t>(r.timestamp_us & 0xFFFF'FFFFu));
  w[24] = r.cycle_ms;
  put32(225, seq);
  w[27] = r.sigma_x_um;
  w[28] = r.sigma_y_um;
  w[29] = r.sigma_z_um;
  w[30] = r.sigma_rx_mdeg;
  w[31] = r.sigma_ry_mdeg;
  w[32] = r.sigma_rz_mdeg;
  put32(233, seq);
  return w;
}

bool same_result(const PlcResult& a, const PlcResult& b) {
  return a.acq_id == b.acq_id && a.code == b.code && a.part_id == b.part_id &&
         a.confidence_permille == b.confidence_permille && a.source == b.source && a.x_um == b.x_um &&
         a.y_um == b.y_um && a.z_um == b.z_um && a.rx_mdeg == b.rx_mdeg && a.ry_mdeg == b.ry_mdeg &&
         a.rz_mdeg == b.rz_mdeg && a.timestamp_us == b.timestamp_us && a.cycle_ms == b.cycle_ms &&
         a.sigma_x_um == b.sigma_x_um && a.sigma_y_um == b.sigma_y_um && a.sigma_z_um == b.sigma_z_um &&
         a.sigma_rx_mdeg == b.sigma_rx_mdeg && a.sigma_ry_mdeg == b.sigma_ry_mdeg && a.sigma_rz_mdeg == b.sigma_rz_mdeg;
}

// Results that exercise every word: extremes first (sign, high word, 64-bit high half), then random values.
std::vector<PlcResult> make_results(std::size_t count, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<std::int32_t> s32(std::numeric_limits<std::int32_t>::min() + 1,
                                                  std::numeric_limits<std::int32_t>::max());
  std::uniform_int_distribution<std::uint32_t> u32;
  std::uniform_int_distribution<std::uint64_t> u64;
  std::uniform_int_distribution<int> u16(0, 0xFFFF);
  std::vector<PlcResult> results;
  for (std::size_t i = 0; i < count; ++i) {
    PlcResult r;
    r.acq_id = u32(rng);
    r.code = static_cast<ResultCode>(i % 7);
    r.part_id = static_cast<std::uint16_t>(u16(rng));
    r.confidence_permille = static_cast<std::uint16_t>(u16(rng) % 1001);
    r.source = static_cast<ResultSource>(i % 3);
    r.x_um = s32(rng);
    r.y_um = s32(rng);
    r.z_um = s32(rng);
    r.rx_mdeg = s32(rng);
    r.ry_mdeg = s32(rng);
    r.rz_mdeg = s32(rng);
    r.timestamp_us = u64(rng);
    r.cycle_ms = static_cast<std::uint16_t>(u16(rng));
    r.sigma_x_um = static_cast<std::uint16_t>(u16(rng));
    r.sigma_y_um = static_cast<std::uint16_t>(u16(rng));
    r.sigma_z_um = static_cast<std::uint16_t>(u16(rng));
    r.sigma_rx_mdeg = static_cast<std::uint16_t>(u16(rng));
    r.sigma_ry_mdeg = static_cast<std::uint16_t>(u16(rng));
    r.sigma_rz_mdeg = static_cast<std::uint16_t>(u16(rng));
    results.push_back(r);
  }
  if (count >= 3) {
    results[0].acq_id = 0xFFFF'FFFFu;
    results[0].x_um = std::numeric_limits<std::int32_t>::max();
    results[0].y_um = -1;
    results[0].z_um = map::kInvalidS32;  // "not estimated" travels as 0x80000000 ...
    results[0].sigma_z_um = 0xFFFF;      // ... and its sigma as "not available"
    results[0].sigma_x_um = 0xFFFE;      // the largest sigma, one below the marker
    results[0].sigma_y_um = 0;
    results[0].timestamp_us = 0xFFFF'FFFF'FFFF'FFFEull;
    results[0].cycle_ms = 0xFFFF;
    results[1].acq_id = 0x0001'0000u;
    results[1].x_um = -65536;
    results[1].y_um = 65536;
    results[1].timestamp_us = 0x0000'0001'0000'0000ull;
    results[2].acq_id = 0;
    results[2].x_um = std::numeric_limits<std::int32_t>::min() + 1;
    results[2].timestamp_us = 0;
  }
  return results;
}

// ------------------------------------------------------------------ frame builders
std::vector<std::uint8_t> pdu_read(std::uint8_t function, std::uint16_t address, std::uint16_t quantity) {
  return {function, static_cast<std::uint8_t>(address >> 8), static_cast<std::uint8_t>(address & 0xFF),
          static_cast<std::uint8_t>(quantity >> 8), static_cast<std::uint8_t>(quantity & 0xFF)};
}

std::vector<std::uint8_t> pdu_write_multiple(std::uint16_t address, const std::vector<std::uint16_t>& values,
                                             std::optional<std::uint16_t> quantity = std::nullopt,
                                             std::optional<std::uint8_t> byte_count = std::nullopt) {
  const std::uint16_t q = quantity.value_or(static_cast<std::uint16_t>(values.size()));
  std::vector<std::uint8_t> pdu = {0x10,
                                   static_cast<std::uint8_t>(address >> 8),
                                   static_cast<std::uint8_t>(address & 0xFF),
                                   static_cast<std::uint8_t>(q >> 8),
                                   static_cast<std::uint8_t>(q & 0xFF),
                                   byte_count.value_or(static_cast<std::uint8_t>(values.size() * 2))};
  for (std::uint16_t v : values) {
    pdu.push_back(static_cast<std::uint8_t>(v >> 8));
    pdu.push_back(static_cast<std::uint8_t>(v & 0xFF));
  }
  return pdu;
}

std::vector<std::uint8_t> adu(std::uint16_t transaction, std::uint8_t unit, const std::vector<std::uint8_t>& pdu,
                              std::uint16_t protocol = 0, std::optional<std::uint16_t> length = std::nullopt) {
  const std::uint16_t mbap_length = length.value_or(static_cast<std::uint16_t>(pdu.size() + 1));
  std::vector<std::uint8_t> frame = {static_cast<std::uint8_t>(transaction >> 8),
                                     static_cast<std::uint8_t>(transaction & 0xFF),
                                     static_cast<std::uint8_t>(protocol >> 8),
                                     static_cast<std::uint8_t>(protocol & 0xFF),
                                     static_cast<std::uint8_t>(mbap_length >> 8),
                                     static_cast<std::uint8_t>(mbap_length & 0xFF),
                                     unit};
  frame.insert(frame.end(), pdu.begin(), pdu.end());
  return frame;
}

// ------------------------------------------------------------------ clients
// libmodbus as a client: an implementation independent of our framing and screening.
class MbClient {
 public:
  explicit MbClient(std::uint16_t port) : ctx_(modbus_new_tcp("127.0.0.1", port)) {
    if (ctx_ == nullptr) return;
    (void)modbus_set_response_timeout(ctx_, 2, 0);
    connected_ = modbus_connect(ctx_) == 0;
  }
  ~MbClient() {
    if (ctx_ == nullptr) return;
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
  MbClient(const MbClient&) = delete;
  MbClient& operator=(const MbClient&) = delete;
  [[nodiscard]] bool connected() const { return connected_; }

  // 0 on success, the Modbus exception code, or -1 for a transport failure.
  int read(std::uint16_t address, std::uint16_t* out, int count, bool input = false) {
    const int rc = input ? modbus_read_input_registers(ctx_, address, count, out)
                         : modbus_read_registers(ctx_, address, count, out);
    return rc == count ? 0 : error_code();
  }
  int write(std::uint16_t address, std::uint16_t value) {
    return modbus_write_register(ctx_, address, value) == 1 ? 0 : error_code();
  }
  int write_many(std::uint16_t address, const std::vector<std::uint16_t>& values) {
    const int count = static_cast<int>(values.size());
    return modbus_write_registers(ctx_, address, count, values.data()) == count ? 0 : error_code();
  }
  std::uint16_t status() {
    std::uint16_t value = 0;
    REQUIRE(read(map::kStatus, &value, 1) == 0);
    return value;
  }
  DecodedBlock block() {
    BlockWords regs{};
    REQUIRE(read(200, regs.data(), kBlockWords) == 0);
    return decode_block(regs);
  }

 private:
  static int error_code() {
    const int err = errno;
    if (err > MODBUS_ENOBASE && err < MODBUS_ENOBASE + 12) return err - MODBUS_ENOBASE;
    return -1;
  }
  modbus_t* ctx_ = nullptr;
  bool connected_ = false;
};

// A plain TCP socket for frames no Modbus library would send.
class RawClient {
 public:
  explicit RawClient(std::uint16_t port) : fd_(socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0)) {
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(port);
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    connected_ = fd_ >= 0 && connect(fd_, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0;
  }
  ~RawClient() {
    if (fd_ >= 0) close(fd_);
  }
  RawClient(const RawClient&) = delete;
  RawClient& operator=(const RawClient&) = delete;
  [[nodiscard]] bool connected() const { return connected_; }

  bool send_bytes(const std::vector<std::uint8_t>& bytes) {
    return send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(bytes.size());
  }

  enum class Outcome { kData, kClosed, kTimeout };
  // Reads until `want` bytes arrived, the peer closed, or the timeout passed.
  Outcome receive(std::vector<std::uint8_t>& out, std::size_t want, int timeout_ms) {
    out.clear();
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (out.size() < want) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0) return Outcome::kTimeout;
      pollfd p{fd_, POLLIN, 0};
      if (poll(&p, 1, static_cast<int>(left)) <= 0) continue;
      std::array<std::uint8_t, 512> buffer{};
      const ssize_t got = recv(fd_, buffer.data(), std::min(buffer.size(), want - out.size()), 0);
      if (got <= 0) return Outcome::kClosed;  // 0 = orderly close, <0 = reset
      out.insert(out.end(), buffer.begin(), buffer.begin() + got);
    }
    return Outcome::kData;
  }
  // Sends a request and returns the exception code of a 9-byte exception reply (or -1 if it was not one).
  int exception_for(const std::vector<std::uint8_t>& frame) {
    if (!send_bytes(frame)) return -1;
    std::vector<std::uint8_t> reply;
    if (receive(reply, 9, 2000) != Outcome::kData) return -1;
    const bool echoed = reply[0] == frame[0] && reply[1] == frame[1] && reply[2] == 0 && reply[3] == 0 &&
                        reply[4] == 0 && reply[5] == 3 && reply[6] == frame[6] && reply[7] == (frame[7] | 0x80);
    return echoed ? reply[8] : -1;
  }
  // Closes with a TCP reset instead of an orderly FIN, as a crashed or unplugged peer would.
  void abort_connection() {
    linger hard{1, 0};
    (void)setsockopt(fd_, SOL_SOCKET, SO_LINGER, &hard, sizeof hard);
    close(fd_);
    fd_ = -1;
  }
  // True when the server closes the connection within timeout_ms (and sends nothing before).
  bool closed_within(int timeout_ms) {
    std::vector<std::uint8_t> ignored;
    return receive(ignored, 1, timeout_ms) == Outcome::kClosed;
  }

 private:
  int fd_ = -1;
  bool connected_ = false;
};

// ------------------------------------------------------------------ child processes (python3, mbpoll)
class ChildProcess {
 public:
  ChildProcess(const std::vector<std::string>& argv, const std::string& stderr_path) {
    int pipe_fds[2] = {-1, -1};
    if (pipe2(pipe_fds, O_CLOEXEC) != 0) return;
    posix_spawn_file_actions_t actions;
    posix_spawn_file_actions_init(&actions);
    posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
    posix_spawn_file_actions_adddup2(&actions, pipe_fds[1], STDOUT_FILENO);
    posix_spawn_file_actions_addopen(&actions, STDERR_FILENO, stderr_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    std::vector<char*> args;
    args.reserve(argv.size() + 1);
    for (const std::string& arg : argv) args.push_back(const_cast<char*>(arg.c_str()));
    args.push_back(nullptr);
    std::vector<std::string> env_storage = {"PYTHONDONTWRITEBYTECODE=1", "LC_ALL=C"};
    std::vector<char*> env;
    for (char** e = environ; *e != nullptr; ++e) env.push_back(*e);
    for (std::string& e : env_storage) env.push_back(e.data());
    env.push_back(nullptr);
    spawned_ = posix_spawn(&pid_, args[0], &actions, nullptr, args.data(), env.data()) == 0;
    posix_spawn_file_actions_destroy(&actions);
    close(pipe_fds[1]);
    out_fd_ = pipe_fds[0];
    stderr_path_ = stderr_path;
  }
  ~ChildProcess() {
    if (spawned_ && !reaped_) {
      kill(pid_, SIGKILL);
      int status = 0;
      waitpid(pid_, &status, 0);
    }
    if (out_fd_ >= 0) close(out_fd_);
    if (!stderr_path_.empty()) unlink(stderr_path_.c_str());  // its text went into the test's INFO already
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;
  [[nodiscard]] bool spawned() const { return spawned_; }

  // Next stdout line; false at end of output or after timeout_ms.
  bool read_line(std::string& line, int timeout_ms) {
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    for (;;) {
      const std::size_t newline = buffer_.find('\n');
      if (newline != std::string::npos) {
        line = buffer_.substr(0, newline);
        buffer_.erase(0, newline + 1);
        return true;
      }
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0 || eof_) return false;
      pollfd p{out_fd_, POLLIN, 0};
      if (poll(&p, 1, static_cast<int>(left)) <= 0) continue;
      char chunk[4096];
      const ssize_t got = read(out_fd_, chunk, sizeof chunk);
      if (got <= 0) {
        eof_ = true;
        if (!buffer_.empty()) {
          line = buffer_;
          buffer_.clear();
          return true;
        }
        return false;
      }
      buffer_.append(chunk, static_cast<std::size_t>(got));
    }
  }
  std::vector<std::string> read_all(int timeout_ms) {
    std::vector<std::string> lines;
    std::string line;
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    while (Clock::now() < deadline) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (!read_line(line, static_cast<int>(left))) break;
      lines.push_back(line);
    }
    return lines;
  }
  // Exit status, or -1 if it did not exit in time (then it is killed).
  int wait_exit(int timeout_ms) {
    const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    int status = 0;
    while (Clock::now() < deadline) {
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        reaped_ = true;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return -1;
  }
  [[nodiscard]] std::string stderr_text() const {
    std::string text;
    if (FILE* f = std::fopen(stderr_path_.c_str(), "r")) {
      char chunk[1024];
      std::size_t got = 0;
      while ((got = std::fread(chunk, 1, sizeof chunk, f)) > 0) text.append(chunk, got);
      std::fclose(f);
    }
    return text;
  }

 private:
  pid_t pid_ = -1;
  int out_fd_ = -1;
  bool spawned_ = false;
  bool reaped_ = false;
  bool eof_ = false;
  std::string buffer_;
  std::string stderr_path_;
};

std::string stderr_file(const char* tag) {
  return std::string(CELLSIGHT_BINARY_DIR) + "/test_modbus_" + tag + "_" + std::to_string(getpid()) + ".stderr";
}

std::string find_program(const char* name) {
  const char* path = std::getenv("PATH");
  std::string dirs = path != nullptr ? path : "/usr/bin:/bin";
  dirs += ":/usr/bin:/bin";
  std::size_t start = 0;
  while (start <= dirs.size()) {
    const std::size_t end = dirs.find(':', start);
    const std::string dir = dirs.substr(start, end == std::string::npos ? std::string::npos : end - start);
    std::string candidate = dir + "/" + name;
    if (!dir.empty() && access(candidate.c_str(), X_OK) == 0) return candidate;
    if (end == std::string::npos) break;
    start = end + 1;
  }
  return {};
}

// Debian's python3 (where python3-pymodbus lives), not whatever python3 comes first on PATH; CELLSIGHT_PYTHON
// overrides. Missing -> the test FAILS with a message: a skipped client test would hide a broken link.
std::string python_with_pymodbus() {
  const char* override_path = std::getenv("CELLSIGHT_PYTHON");
  std::string python = override_path != nullptr ? override_path : "/usr/bin/python3";
  if (access(python.c_str(), X_OK) != 0) {
    FAIL("python3 not found at " << python
                                 << ": install python3 and python3-pymodbus (scripts/setup.sh) or set "
                                    "CELLSIGHT_PYTHON");
  }
  ChildProcess probe({python, "-c", "import pymodbus.client, pymodbus.payload; print(pymodbus.__version__)"},
                     stderr_file("probe"));
  std::string version;
  const bool printed = probe.read_line(version, 20000);
  const int status = probe.wait_exit(20000);
  if (!printed || status != 0) {
    FAIL(python << " cannot import pymodbus (install python3-pymodbus, see scripts/setup.sh): " << probe.stderr_text());
  }
  if (version.rfind("3.", 0) != 0) FAIL("pymodbus 3.x expected, found " << version);
  return python;
}

std::string client_script() {
  return std::string(CELLSIGHT_SOURCE_DIR) + "/tests/modbus_plc_client.py";
}

// Flat JSON objects as printed by modbus_plc_client.py: string, integer and boolean values only.
using JsonLine = std::map<std::string, std::string>;

bool parse_json_line(const std::string& text, JsonLine& out) {
  out.clear();
  std::size_t i = 0;
  auto skip = [&] {
    while (i < text.size() && (text[i] == ' ' || text[i] == '\t')) ++i;
  };
  auto read_string = [&](std::string& s) {
    if (i >= text.size() || text[i] != '"') return false;
    ++i;
    s.clear();
    while (i < text.size() && text[i] != '"') {
      if (text[i] == '\\' && i + 1 < text.size()) ++i;
      s += text[i++];
    }
    if (i >= text.size()) return false;
    ++i;
    return true;
  };
  skip();
  if (i >= text.size() || text[i++] != '{') return false;
  for (;;) {
    skip();
    if (i < text.size() && text[i] == '}') return true;
    std::string key;
    std::string value;
    if (!read_string(key)) return false;
    skip();
    if (i >= text.size() || text[i++] != ':') return false;
    skip();
    if (i < text.size() && text[i] == '"') {
      if (!read_string(value)) return false;
    } else {
      while (i < text.size() && text[i] != ',' && text[i] != '}') value += text[i++];
      while (!value.empty() && value.back() == ' ') value.pop_back();
    }
    out[key] = value;
    skip();
    if (i < text.size() && text[i] == ',') {
      ++i;
      continue;
    }
    if (i < text.size() && text[i] == '}') return true;
    return false;
  }
}

std::int64_t json_i64(const JsonLine& line, const std::string& key) {
  const auto it = line.find(key);
  if (it == line.end()) FAIL("JSON line has no '" << key << "'");
  return std::strtoll(it->second.c_str(), nullptr, 10);
}
std::uint64_t json_u64(const JsonLine& line, const std::string& key) {
  const auto it = line.find(key);
  if (it == line.end()) FAIL("JSON line has no '" << key << "'");
  return std::strtoull(it->second.c_str(), nullptr, 10);
}

// The client prints a pose value of 0x80000000 and a sigma of 0xFFFF as null ("not available"): back to the markers.
bool json_null(const JsonLine& line, const std::string& key) {
  const auto it = line.find(key);
  return it != line.end() && it->second == "null";
}
std::int32_t json_pose(const JsonLine& line, const std::string& key) {
  return json_null(line, key) ? map::kInvalidS32 : static_cast<std::int32_t>(json_i64(line, key));
}
std::uint16_t json_sigma(const JsonLine& line, const std::string& key) {
  return json_null(line, key) ? std::uint16_t{0xFFFF} : static_cast<std::uint16_t>(json_i64(line, key));
}

PlcResult result_from_json(const JsonLine& line) {
  PlcResult r;
  r.acq_id = static_cast<std::uint32_t>(json_u64(line, "acq_id"));
  r.code = static_cast<ResultCode>(json_i64(line, "code"));
  r.part_id = static_cast<std::uint16_t>(json_i64(line, "part_id"));
  r.confidence_permille = static_cast<std::uint16_t>(json_i64(line, "confidence"));
  r.source = static_cast<ResultSource>(json_i64(line, "source"));
  r.x_um = json_pose(line, "x_um");
  r.y_um = json_pose(line, "y_um");
  r.z_um = json_pose(line, "z_um");
  r.rx_mdeg = json_pose(line, "rx_mdeg");
  r.ry_mdeg = json_pose(line, "ry_mdeg");
  r.rz_mdeg = json_pose(line, "rz_mdeg");
  r.timestamp_us = json_u64(line, "timestamp_us");
  r.cycle_ms = static_cast<std::uint16_t>(json_i64(line, "cycle_ms"));
  r.sigma_x_um = json_sigma(line, "sigma_x_um");
  r.sigma_y_um = json_sigma(line, "sigma_y_um");
  r.sigma_z_um = json_sigma(line, "sigma_z_um");
  r.sigma_rx_mdeg = json_sigma(line, "sigma_rx_mdeg");
  r.sigma_ry_mdeg = json_sigma(line, "sigma_ry_mdeg");
  r.sigma_rz_mdeg = json_sigma(line, "sigma_rz_mdeg");
  return r;
}

// ------------------------------------------------------------------ servers
ModbusServerConfig loopback_config() {
  ModbusServerConfig config;
  config.bind_address = "127.0.0.1";
  config.port = 0;  // ephemeral: tests run in parallel with other engineers' servers
  config.link.plc_heartbeat_timeout_ms = 0;
  config.link.loop_watchdog_ms = 0;
  return config;
}

struct RunningServer {
  explicit RunningServer(const ModbusServerConfig& config) : server(config) {
    const cellsight::Status started = server.start();
    if (!started.ok()) FAIL("server did not start: " << started.error().message);
    port = server.bound_port();
    REQUIRE(port != 0);
  }
  ModbusServer server;
  std::uint16_t port = 0;
};

// ------------------------------------------------------------------ simulated PLC helpers
struct SimPlc {
  SimPlcLink& link;
  std::uint16_t reg(std::uint16_t address) {
    std::uint16_t value = 0;
    REQUIRE(link.plc_read(address, std::span<std::uint16_t>(&value, 1)) == 0);
    return value;
  }
  std::uint16_t status() { return reg(100); }
  DecodedBlock block() {
    BlockWords regs{};
    REQUIRE(link.plc_read(200, regs) == 0);
    return decode_block(regs);
  }
  void control(std::uint16_t value) { REQUIRE(link.plc_write_register(0, value) == 0); }
  void at_ms(std::int64_t ms) { link.advance_to(ms * kNsPerMs); }
};

PlcLinkConfig sim_config() {
  PlcLinkConfig config;
  config.plc_heartbeat_timeout_ms = 0;
  config.loop_watchdog_ms = 0;
  return config;
}

// Oracle of the map, register by register, from the DESIGN.md table.
bool holding_mapped(std::uint32_t a) {
  return a <= 9 || (a >= 100 && a <= 119) || (a >= 200 && a <= 234);
}
bool input_mapped(std::uint32_t a) {
  return (a >= 100 && a <= 119) || (a >= 200 && a <= 234);
}
bool plc_writable(std::uint32_t a) {
  return a <= 9;
}

std::uint8_t oracle(std::uint8_t function, std::uint32_t address, std::uint32_t quantity) {
  bool (*mapped)(std::uint32_t) = nullptr;
  std::uint32_t max_quantity = 0;
  if (function == 3) {
    mapped = holding_mapped;
    max_quantity = 125;
  } else if (function == 4) {
    mapped = input_mapped;
    max_quantity = 125;
  } else if (function == 6) {
    mapped = plc_writable;
    max_quantity = 1;
    quantity = 1;  // FC06 carries a value, not a quantity
  } else if (function == 16) {
    mapped = plc_writable;
    max_quantity = 123;
  } else {
    return 1;
  }
  if (quantity < 1 || quantity > max_quantity) return 3;
  for (std::uint32_t a = address; a < address + quantity; ++a) {
    if (!mapped(a)) return 2;
  }
  return 0;
}

}  // namespace

// ================================================================== request screen (pure)

TEST_CASE("screen: every function, address and quantity agrees with a register-by-register oracle of the map",
          "[modbus][screen]") {
  // Given every function code a PLC might send, addresses around every block edge and at the top of the space,
  // and quantities 0..130
  const std::array<std::uint8_t, 13> functions = {1, 2, 3, 4, 5, 6, 7, 15, 16, 17, 22, 23, 43};
  std::vector<std::uint32_t> addresses;
  for (std::uint32_t a = 0; a <= 300; ++a) addresses.push_back(a);
  for (std::uint32_t a = 65400; a <= 65535; ++a) addresses.push_back(a);
  std::size_t mismatches = 0;
  std::array<std::size_t, 4> by_code{};  // how often the oracle said serve / 01 / 02 / 03
  std::array<std::uint8_t, kMaxAduBytes> frame{};
  for (std::uint8_t function : functions) {
    for (std::uint32_t address : addresses) {
      for (std::uint32_t quantity = 0; quantity <= 130; ++quantity) {
        const std::uint8_t expected = oracle(function, address, quantity);
        // When the screen sees a well-formed frame for this request
        std::size_t pdu_bytes = 5;
        frame[7] = function;
        frame[8] = static_cast<std::uint8_t>(address >> 8);
        frame[9] = static_cast<std::uint8_t>(address & 0xFF);
        frame[10] = static_cast<std::uint8_t>(quantity >> 8);
        frame[11] = static_cast<std::uint8_t>(quantity & 0xFF);
        if (function == 16) {
          // Quantities over 123 cannot be carried honestly (byte count is one byte): send them with count 0.
          const std::uint32_t data_bytes = quantity <= 123 ? 2 * quantity : 0;
          frame[12] = static_cast<std::uint8_t>(data_bytes);
          for (std::uint32_t b = 0; b < data_bytes; ++b) frame[13 + b] = static_cast<std::uint8_t>(b);
          pdu_bytes = 6 + data_bytes;
        }
        frame[0] = 0x12;
        frame[1] = 0x34;
        frame[2] = frame[3] = 0;
        frame[4] = static_cast<std::uint8_t>((pdu_bytes + 1) >> 8);
        frame[5] = static_cast<std::uint8_t>((pdu_bytes + 1) & 0xFF);
        frame[6] = 1;
        const ScreenResult result = screen_request(std::span<const std::uint8_t>(frame.data(), 7 + pdu_bytes));
        // Then serve exactly when the oracle says so, otherwise the oracle's exception; never close a valid frame
        const std::uint8_t got = result.verdict == ScreenVerdict::kServe       ? 0
                                 : result.verdict == ScreenVerdict::kException ? result.exception_code
                                                                               : 0xFF;
        const std::uint8_t direct =
            screen_access(function, static_cast<std::uint16_t>(address),
                          function == 6 ? std::uint16_t{1} : static_cast<std::uint16_t>(quantity));
        if (got != expected || direct != expected || result.frame_bytes != 7 + pdu_bytes) {
          if (++mismatches <= 5) {
            UNSCOPED_INFO("fc " << int(function) << " address " << address << " quantity " << quantity << ": oracle "
                                << int(expected) << ", screen " << int(got) << ", access " << int(direct));
          }
        }
        ++by_code[expected];
      }
    }
  }
  CHECK(mismatches == 0);
  // And the sweep really covered every outcome, not just refusals
  for (std::size_t code = 0; code < by_code.size(); ++code) {
    INFO("outcome " << code);
    CHECK(by_code[code] > 100);
  }
}

TEST_CASE("screen: MBAP framing decides between wait, serve, exception and close", "[modbus][screen]") {
  const std::vector<std::uint8_t> read_status = adu(7, 1, pdu_read(3, 100, 11));

  SECTION("a protocol id other than 0 closes as soon as it is visible") {
    const auto frame = adu(7, 1, pdu_read(3, 100, 1), 1);
    const ScreenResult result = screen_request(std::span<const std::uint8_t>(frame.data(), 4));
    CHECK(result.verdict == ScreenVerdict::kClose);
    CHECK(result.close_reason == CloseReason::kProtocolId);
  }
  SECTION("MBAP lengths below 2 or above 254 close") {
    for (std::uint16_t length : {0, 1}) {
      const auto frame = adu(7, 1, {}, 0, length);
      const ScreenResult result = screen_request(frame);
      CHECK(result.verdict == ScreenVerdict::kClose);
      CHECK(result.close_reason == CloseReason::kLengthTooShort);
    }
    for (std::uint16_t length : {255, 1000, 0xFFFF}) {
      const auto frame = adu(7, 1, pdu_read(3, 100, 1), 0, length);
      const ScreenResult result = screen_request(frame);
      CHECK(result.verdict == ScreenVerdict::kClose);
      CHECK(result.close_reason == CloseReason::kLengthTooLong);
    }
  }
  SECTION("every proper prefix of a frame waits for more, the whole frame is served") {
    for (std::size_t n = 0; n < read_status.size(); ++n) {
      CHECK(screen_request(std::span<const std::uint8_t>(read_status.data(), n)).verdict == ScreenVerdict::kIncomplete);
    }
    const ScreenResult whole = screen_request(read_status);
    CHECK(whole.verdict == ScreenVerdict::kServe);
    CHECK(whole.frame_bytes == 12);
    CHECK(whole.address == 100);
    CHECK(whole.quantity == 11);
  }
  SECTION("pipelined frames are taken one at a time") {
    std::vector<std::uint8_t> two = read_status;
    const auto write = adu(8, 1, {0x06, 0x00, 0x04, 0x12, 0x34});
    two.insert(two.end(), write.begin(), write.end());
    const ScreenResult first = screen_request(two);
    REQUIRE(first.verdict == ScreenVerdict::kServe);
    REQUIRE(first.frame_bytes == read_status.size());
    const ScreenResult second =
        screen_request(std::span<const std::uint8_t>(two.data() + first.frame_bytes, two.size() - first.frame_bytes));
    CHECK(second.verdict == ScreenVerdict::kServe);
    CHECK(second.function == 6);
    CHECK(second.address == 4);
    CHECK(second.quantity == 1);
  }
  SECTION("a PDU whose length does not fit its function is exception 03, whole frame consumed") {
    // FC03 with one byte missing / one byte extra / nothing after the function code
    for (const auto& pdu : {std::vector<std::uint8_t>{3, 0, 100, 0}, std::vector<std::uint8_t>{3, 0, 100, 0, 1, 9},
                            std::vector<std::uint8_t>{3}, std::vector<std::uint8_t>{6, 0, 0, 1}}) {
      const auto frame = adu(7, 1, pdu);
      const ScreenResult result = screen_request(frame);
      CHECK(result.verdict == ScreenVerdict::kException);
      CHECK(result.exception_code == 3);
      CHECK(result.frame_bytes == frame.size());
    }
  }
  SECTION("FC16 whose byte count, quantity and frame length disagree is exception 03") {
    // byte count says 4, quantity says 2, but only 2 data bytes follow (libmodbus would read past the frame)
    auto short_data = pdu_write_multiple(0, {0x0001}, std::uint16_t{2}, std::uint8_t{4});
    CHECK(screen_request(adu(1, 1, short_data)).exception_code == 3);
    // byte count 2 for quantity 2
    auto wrong_count = pdu_write_multiple(0, {0x0001}, std::uint16_t{2}, std::uint8_t{2});
    CHECK(screen_request(adu(1, 1, wrong_count)).exception_code == 3);
    // header cut before the byte count
    CHECK(screen_request(adu(1, 1, {0x10, 0, 0, 0, 1})).exception_code == 3);
  }
  SECTION("function codes outside 03/04/06/16, including 0x80 and up, are exception 01") {
    for (std::uint8_t function : {0x01, 0x02, 0x05, 0x07, 0x08, 0x0F, 0x11, 0x16, 0x17, 0x2B, 0x80, 0x83, 0xFF}) {
      const auto frame = adu(7, 1, {function, 0, 0, 0, 1});
      const ScreenResult result = screen_request(frame);
      CHECK(result.verdict == ScreenVerdict::kException);
      CHECK(result.exception_code == 1);
    }
    // even a bare function code with nothing after it
    CHECK(screen_request(adu(7, 1, {0x2B})).exception_code == 1);
  }
}

TEST_CASE("screen: the exception reply echoes transaction, unit and function", "[modbus][screen]") {
  const auto request = adu(0xBEEF, 0x11, {0x2B, 0x0E, 0x01, 0x00});
  std::array<std::uint8_t, kExceptionReplyBytes> reply{};
  build_exception_reply(request, 1, reply);
  const std::array<std::uint8_t, 9> expected = {0xBE, 0xEF, 0x00, 0x00, 0x00, 0x03, 0x11, 0xAB, 0x01};
  CHECK(reply == expected);
  // A function code that already has the top bit keeps it (0x83 | 0x80 == 0x83)
  build_exception_reply(adu(1, 2, {0x83}), 1, reply);
  CHECK(reply[7] == 0x83);
}

TEST_CASE("wire units: metres and degrees become s32 um and millidegrees, unrepresentable -> 0x80000000",
          "[modbus][units]") {
  CHECK(to_plc_micrometres(1.0) == 1'000'000);
  CHECK(to_plc_micrometres(-0.25) == -250'000);
  CHECK(to_plc_micrometres(0.0000015) == 2);  // rounds to nearest
  CHECK(to_plc_micrometres(-2147.483647) == -2'147'483'647);
  CHECK(to_plc_micrometres(2147.483648) == map::kInvalidS32);  // one past INT32_MAX
  CHECK(to_plc_micrometres(std::nan("")) == map::kInvalidS32);
  CHECK(to_plc_micrometres(std::numeric_limits<double>::infinity()) == map::kInvalidS32);
  CHECK(to_plc_millidegrees(45.0) == 45'000);
  CHECK(to_plc_millidegrees(-179.9996) == -180'000);
  CHECK(to_plc_millidegrees(1e300) == map::kInvalidS32);
  CHECK(static_cast<std::uint32_t>(map::kInvalidS32) == 0x80000000u);
}

TEST_CASE("wire units: sigmas become u16 um and millidegrees, rounded, saturated at 65534, else 0xFFFF",
          "[modbus][units]") {
  CHECK(to_plc_sigma_micrometres(0.0) == 0);
  CHECK(to_plc_sigma_micrometres(0.0000004) == 0);  // below the resolution: 0, still available
  CHECK(to_plc_sigma_micrometres(0.0012346) == 1235);
  CHECK(to_plc_sigma_micrometres(0.0655344) == 65534);
  CHECK(to_plc_sigma_micrometres(0.0655346) == 65534);  // rounds to 65535, which is the marker: saturates
  CHECK(to_plc_sigma_micrometres(1e300) == 65534);
  CHECK(to_plc_sigma_micrometres(-0.000001) == 0xFFFF);  // no uncertainty is negative
  CHECK(to_plc_sigma_micrometres(std::nan("")) == 0xFFFF);
  CHECK(to_plc_sigma_micrometres(std::numeric_limits<double>::infinity()) == 0xFFFF);
  CHECK(to_plc_sigma_millidegrees(0.0426) == 43);
  CHECK(to_plc_sigma_millidegrees(90.0) == 65534);
  CHECK(to_plc_sigma_millidegrees(-1.0) == 0xFFFF);
  CHECK(map::kInvalidSigma == 0xFFFF);
}

// ================================================================== handshake on the simulated link

TEST_CASE("sim link: each result is presented whole, once, in order, through the ack handshake", "[modbus][sim]") {
  // Given a link with three results queued before the PLC looks
  SimPlcLink link(sim_config());
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  const auto results = make_results(3, 11);
  CHECK(plc.status() == 0);
  CHECK(plc.block().seq == 0);  // 0 = no result yet
  for (const PlcResult& r : results) REQUIRE(link.publish(r) == PublishStatus::kQueued);

  for (std::size_t i = 0; i < results.size(); ++i) {
    plc.at_ms(static_cast<std::int64_t>(10 * (i + 1)));
    // When the PLC polls, then the block holds result i, both sequence copies agree, RESULT_VALID is set
    REQUIRE((plc.status() & map::kStatusResultValid) != 0);
    const DecodedBlock block = plc.block();
    CHECK(block.seq == i + 1);
    CHECK(block.seq_copy == block.seq);
    CHECK(block.seq_copy2 == block.seq);
    CHECK(same_result(block.result, results[i]));
    CHECK(plc.reg(109) == results.size() - i - 1);  // RESULT_QUEUE_DEPTH: waiting behind the presented one
    // When the PLC acks, then RESULT_VALID drops and the block does not change until the ack is cleared
    plc.control(map::kControlResultAck);
    CHECK((plc.status() & map::kStatusResultValid) == 0);
    plc.at_ms(static_cast<std::int64_t>(10 * (i + 1) + 5));
    CHECK(plc.block().seq == i + 1);
    CHECK((plc.status() & map::kStatusResultValid) == 0);
    plc.control(0);
  }
  // Then nothing is presented twice
  CHECK((plc.status() & map::kStatusResultValid) == 0);
  const LinkStats stats = link.stats();
  CHECK(stats.results_published == 3);
  CHECK(stats.results_presented == 3);
  CHECK(stats.results_acked == 3);
  CHECK(stats.queue_depth == 0);
}

TEST_CASE("sim link: a result that arrives while RESULT_ACK is still high waits until the PLC clears it",
          "[modbus][sim]") {
  SimPlcLink link(sim_config());
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  const auto results = make_results(3, 14);
  // Given a PLC that raises RESULT_ACK before any result exists (a stale bit after its own restart)
  plc.control(map::kControlResultAck);
  // When the first result arrives and time passes, then it is not presented: the ack cannot be meant for it
  REQUIRE(link.publish(results[0]) == PublishStatus::kQueued);
  plc.at_ms(10);
  CHECK((plc.status() & map::kStatusResultValid) == 0);
  CHECK(plc.block().seq == 0);
  plc.at_ms(20);
  CHECK(link.stats().results_presented == 0);
  CHECK(link.stats().results_acked == 0);
  // When the PLC clears the ack, then it appears, and its ack counts only after the PLC raised it for this block
  plc.control(0);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
  CHECK(plc.block().seq == 1);
  CHECK(link.stats().results_acked == 0);
  plc.control(map::kControlResultAck);
  CHECK(link.stats().results_acked == 1);

  // Given the PLC clears its ack and raises it again before the next result (a PLC that acks twice)
  plc.control(0);
  plc.control(map::kControlResultAck);
  // When the next result arrives while the ack is high, then it waits: the block still holds result 1, invalid
  REQUIRE(link.publish(results[1]) == PublishStatus::kQueued);
  for (int ms = 30; ms <= 60; ms += 10) {
    plc.at_ms(ms);
    CHECK((plc.status() & map::kStatusResultValid) == 0);
    CHECK(plc.block().seq == 1);
  }
  CHECK(link.stats().results_presented == 1);
  CHECK(link.stats().results_acked == 1);  // never counted as taken while the PLC has not seen it
  CHECK(plc.reg(109) == 1);                // RESULT_QUEUE_DEPTH: it is still waiting
  // When the ack falls, then result 2 is presented, whole, and taken by the next ack
  plc.control(0);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
  const DecodedBlock second = plc.block();
  CHECK(second.seq == 2);
  CHECK(same_result(second.result, results[1]));
  plc.control(map::kControlResultAck);
  plc.control(0);
  CHECK(link.stats().results_acked == 2);
}

TEST_CASE("sim link: a full queue rejects the newest result and latches RESULT_OVERRUN until CLEAR_ERROR",
          "[modbus][sim]") {
  PlcLinkConfig config = sim_config();
  config.result_queue_capacity = 2;
  SimPlcLink link(config);
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  const auto results = make_results(5, 12);
  // Given one result presented (not acked) and two waiting
  REQUIRE(link.publish(results[0]) == PublishStatus::kQueued);
  plc.at_ms(1);
  REQUIRE(link.publish(results[1]) == PublishStatus::kQueued);
  REQUIRE(link.publish(results[2]) == PublishStatus::kQueued);
  CHECK((plc.status() & map::kStatusResultOverrun) == 0);
  // When a fourth arrives, then it is rejected, counted and RESULT_OVERRUN is set
  CHECK(link.publish(results[3]) == PublishStatus::kQueueFull);
  CHECK(link.stats().results_rejected == 1);
  CHECK((plc.status() & map::kStatusResultOverrun) != 0);
  // And the queued ones still arrive in order, the rejected one never, without a gap in RESULT_SEQ
  std::vector<std::uint32_t> seen_acq;
  std::vector<std::uint32_t> seen_seq;
  for (int step = 0; step < 6; ++step) {
    plc.at_ms(10 + step);
    if ((plc.status() & map::kStatusResultValid) != 0) {
      const DecodedBlock block = plc.block();
      seen_acq.push_back(block.result.acq_id);
      seen_seq.push_back(block.seq);
      plc.control(map::kControlResultAck);
      plc.control(0);
    }
  }
  CHECK(seen_acq == std::vector<std::uint32_t>{results[0].acq_id, results[1].acq_id, results[2].acq_id});
  CHECK(seen_seq == std::vector<std::uint32_t>{1, 2, 3});
  // RESULT_OVERRUN stays latched after the queue drained, until the PLC pulses CLEAR_ERROR
  CHECK((plc.status() & map::kStatusResultOverrun) != 0);
  plc.control(map::kControlClearError);
  plc.control(0);
  CHECK((plc.status() & map::kStatusResultOverrun) == 0);
  CHECK(link.take_commands().clear_errors == 1);
  // And the next accepted result continues the sequence
  REQUIRE(link.publish(results[4]) == PublishStatus::kQueued);
  plc.at_ms(100);
  CHECK(plc.block().seq == 4);
  CHECK(plc.block().result.acq_id == results[4].acq_id);
}

TEST_CASE("sim link: a fault withdraws RESULT_VALID at once and clearing it presents the same result again",
          "[modbus][sim]") {
  SimPlcLink link(sim_config());
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  const auto results = make_results(2, 13);
  REQUIRE(link.publish(results[0]) == PublishStatus::kQueued);
  REQUIRE(link.publish(results[1]) == PublishStatus::kQueued);
  plc.at_ms(1);
  REQUIRE((plc.status() & map::kStatusResultValid) != 0);
  // When the production loop reports a fault, then the very next read shows ERROR with its code and no valid result
  link.set_error(ErrorCode::kCameraFault);
  std::uint16_t status = plc.status();
  CHECK((status & map::kStatusError) != 0);
  CHECK((status & map::kStatusResultValid) == 0);
  CHECK(plc.reg(102) == 1);
  // And no queued result replaces it while the fault lasts, even when the PLC acks and time passes
  plc.control(map::kControlResultAck);
  plc.control(0);
  plc.at_ms(500);
  CHECK((plc.status() & map::kStatusResultValid) == 0);
  CHECK(plc.block().seq == 1);
  // When the fault clears, then the second result (the first was acked) is presented
  link.set_error(ErrorCode::kNone);
  status = plc.status();
  CHECK((status & map::kStatusError) == 0);
  CHECK((status & map::kStatusResultValid) != 0);
  CHECK(plc.block().seq == 2);
  // And a fault on an unacked result re-presents that same result afterwards
  link.set_error(ErrorCode::kEncoderFault);
  CHECK((plc.status() & map::kStatusResultValid) == 0);
  link.set_error(ErrorCode::kNone);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
  CHECK(plc.block().seq == 2);
  CHECK(same_result(plc.block().result, results[1]));
}

TEST_CASE("sim link: a stale PLC heartbeat sets PLC_HB_LOST and withholds the result until it moves again",
          "[modbus][sim]") {
  PlcLinkConfig config = sim_config();
  config.plc_heartbeat_timeout_ms = 500;
  SimPlcLink link(config);
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  REQUIRE(link.publish(make_results(1, 14)[0]) == PublishStatus::kQueued);
  plc.at_ms(100);
  REQUIRE(link.plc_write_register(4, 1) == 0);
  REQUIRE((plc.status() & map::kStatusResultValid) != 0);
  // Writing the same value again is not a heartbeat
  plc.at_ms(400);
  REQUIRE(link.plc_write_register(4, 1) == 0);
  // When the heartbeat has not changed for exactly the timeout, then the link still trusts it
  plc.at_ms(600);
  CHECK((plc.status() & map::kStatusPlcHbLost) == 0);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
  // When it has been stale for longer, then PLC_HB_LOST is set and RESULT_VALID dropped
  plc.at_ms(601);
  std::uint16_t status = plc.status();
  CHECK((status & map::kStatusPlcHbLost) != 0);
  CHECK((status & map::kStatusResultValid) == 0);
  CHECK(link.take_commands().plc_heartbeat_lost);
  CHECK(link.stats().heartbeat_losses == 1);
  // When the PLC's heartbeat moves again, then the same result is valid again
  plc.at_ms(2000);
  REQUIRE(link.plc_write_register(4, 2) == 0);
  status = plc.status();
  CHECK((status & map::kStatusPlcHbLost) == 0);
  CHECK((status & map::kStatusResultValid) != 0);
  CHECK(plc.block().seq == 1);
  CHECK_FALSE(link.take_commands().plc_heartbeat_lost);
}

TEST_CASE("sim link: HEARTBEAT counts 100 ms periods, wraps at 65536 and freezes when the loop is silent",
          "[modbus][sim]") {
  SECTION("counting and wrap") {
    SimPlcLink link(sim_config());
    REQUIRE(link.start().ok());
    SimPlc plc{link};
    plc.at_ms(99);
    CHECK(plc.reg(101) == 0);
    plc.at_ms(100);
    CHECK(plc.reg(101) == 1);
    plc.at_ms(1050);
    CHECK(plc.reg(101) == 10);
    // 65536 periods later the 16-bit counter is back where it was
    plc.at_ms(1050 + 65536LL * 100);
    CHECK(plc.reg(101) == 10);
    plc.at_ms(1050 + 65536LL * 100 + 300);
    CHECK(plc.reg(101) == 13);
  }
  SECTION("loop watchdog") {
    PlcLinkConfig config = sim_config();
    config.loop_watchdog_ms = 300;
    SimPlcLink link(config);
    REQUIRE(link.start().ok());
    SimPlc plc{link};
    // Given a production loop that last called heartbeat() at t = 0
    link.heartbeat();
    plc.at_ms(300);
    CHECK(plc.reg(101) == 3);
    // When it stays silent, then HEARTBEAT stops moving
    plc.at_ms(400);
    const std::uint16_t frozen = plc.reg(101);
    plc.at_ms(1000);
    CHECK(plc.reg(101) == frozen);
    CHECK(link.stats().loop_stalls == 1);
    // When it calls again, then HEARTBEAT resumes from where it stopped
    link.heartbeat();
    plc.at_ms(1100);
    CHECK(plc.reg(101) == static_cast<std::uint16_t>(frozen + 1));
  }
}

TEST_CASE("sim link: CONTROL edges, commands and status reach their destinations", "[modbus][sim]") {
  SimPlcLink link(sim_config());
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  SECTION("trigger enable level and SW_TRIGGER rising edges (pulses between two polls are not lost)") {
    plc.control(map::kControlTriggerEnable);
    PlcCommands commands = link.take_commands();
    CHECK(commands.trigger_enable);
    CHECK(commands.sw_triggers == 0);
    plc.control(map::kControlTriggerEnable | map::kControlSwTrigger);
    plc.control(map::kControlTriggerEnable);
    plc.control(map::kControlTriggerEnable | map::kControlSwTrigger);
    plc.control(map::kControlTriggerEnable | map::kControlSwTrigger);  // level held: no new edge
    commands = link.take_commands();
    CHECK(commands.sw_triggers == 2);
    CHECK(link.take_commands().sw_triggers == 0);
    plc.control(0);
    CHECK_FALSE(link.take_commands().trigger_enable);
  }
  SECTION("EXEC_CMD latches COMMAND and ARG (u32 high word first); CMD_DONE until EXEC_CMD falls") {
    // COMMAND, ARG written first, EXEC raised afterwards
    REQUIRE(link.plc_write(1, std::vector<std::uint16_t>{1, 0x0001, 0x0002}) == 0);
    plc.control(map::kControlExecCmd);
    PlcCommands commands = link.take_commands();
    CHECK(commands.exec_command);
    CHECK(commands.command == CommandCode::kSelectModels);
    CHECK(commands.command_arg == 0x0001'0002u);
    CHECK_FALSE(link.take_commands().exec_command);
    link.complete_command(true);
    CHECK((plc.status() & map::kStatusCmdDone) != 0);
    CHECK((plc.status() & map::kStatusCmdFailed) == 0);
    plc.control(0);
    CHECK((plc.status() & (map::kStatusCmdDone | map::kStatusCmdFailed)) == 0);
    // Everything in one FC16: CONTROL, COMMAND, ARG
    REQUIRE(link.plc_write(0, std::vector<std::uint16_t>{map::kControlExecCmd, 2, 0xABCD, 0x0042}) == 0);
    commands = link.take_commands();
    CHECK(commands.exec_command);
    CHECK(commands.command == CommandCode::kEnterTeach);
    CHECK(commands.command_arg == 0xABCD'0042u);
    link.complete_command(false);
    CHECK((plc.status() & map::kStatusCmdFailed) != 0);
    plc.control(0);
    // An unknown command number is passed on raw, never guessed
    REQUIRE(link.plc_write(0, std::vector<std::uint16_t>{map::kControlExecCmd, 99, 0, 0}) == 0);
    commands = link.take_commands();
    CHECK(commands.command == CommandCode::kNone);
    CHECK(commands.command_raw == 99);
  }
  SECTION("status flags, codes and counters appear at their addresses") {
    link.set_flag(StatusFlag::kReady, true);
    link.set_flag(StatusFlag::kTeachMode, true);
    link.set_flag(StatusFlag::kBusy, true);
    link.set_flag(StatusFlag::kBusy, false);
    link.set_warning(WarningCode::kExposureAtLimit);
    link.set_active_models(42);
    link.set_trigger_counters(0x0001'2345u, 0xFFFF'FFFEu);
    const std::uint16_t status = plc.status();
    CHECK(status == ((1u << 0) | (1u << 7) | (1u << 11)));  // READY, WARNING, TEACH_MODE from DESIGN.md
    CHECK(plc.reg(103) == 1);
    CHECK(plc.reg(104) == 42);
    CHECK(plc.reg(105) == 0x0001);
    CHECK(plc.reg(106) == 0x2345);
    CHECK(plc.reg(107) == 0xFFFF);
    CHECK(plc.reg(108) == 0xFFFE);
    CHECK(plc.reg(110) == kMapVersion);
  }
}

TEST_CASE("sim link: in poll-only mode a result stays at least the hold time, then the next replaces it",
          "[modbus][sim]") {
  PlcLinkConfig config = sim_config();
  config.ack_mode = AckMode::kPollOnly;
  config.poll_hold_ms = 200;
  SimPlcLink link(config);
  REQUIRE(link.start().ok());
  SimPlc plc{link};
  const auto results = make_results(3, 15);
  for (const PlcResult& r : results) REQUIRE(link.publish(r) == PublishStatus::kQueued);
  plc.at_ms(0);
  CHECK(plc.block().seq == 1);
  plc.at_ms(199);
  CHECK(plc.block().seq == 1);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
  plc.at_ms(200);
  CHECK(plc.block().seq == 2);
  plc.at_ms(400);
  CHECK(plc.block().seq == 3);
  // The last one stays (and stays valid) when nothing follows
  plc.at_ms(10'000);
  CHECK(plc.block().seq == 3);
  CHECK((plc.status() & map::kStatusResultValid) != 0);
}

TEST_CASE("sim link: the PLC side answers like the server: read-only blocks refuse writes, FC04 reads them",
          "[modbus][sim]") {
  SimPlcLink link(sim_config());
  BlockWords regs{};
  CHECK(link.plc_read(200, regs) == SimPlcLink::kLinkDown);  // not started: no server
  REQUIRE(link.start().ok());
  CHECK(link.plc_write_register(100, 1) == 2);
  CHECK(link.plc_write_register(200, 1) == 2);
  CHECK(link.plc_write(8, std::vector<std::uint16_t>{1, 2, 3}) == 2);
  CHECK(link.plc_read(0, std::span<std::uint16_t>(regs.data(), 5), true) == 2);  // command block is not input
  CHECK(link.plc_read(200, regs, true) == 0);
  CHECK(link.plc_read(199, regs) == 2);
  CHECK(link.plc_read(201, regs) == 2);  // one past 234
  std::vector<std::uint16_t> too_many(126);
  CHECK(link.plc_read(100, too_many) == 3);
}

TEST_CASE("production side allocates nothing after start (simulated and real backend)", "[modbus][alloc]") {
  PlcLinkConfig config = sim_config();
  config.result_queue_capacity = 4;
  const auto results = make_results(8, 16);
  SECTION("simulated link, both sides") {
    SimPlcLink link(config);
    REQUIRE(link.start().ok());
    BlockWords block{};
    long allocations = 0;
    std::size_t accepted = 0;
    {
      AllocationWindow window;
      for (std::size_t i = 0; i < results.size(); ++i) {
        accepted += link.publish(results[i]) == PublishStatus::kQueued ? 1 : 0;
        link.set_flag(StatusFlag::kBusy, (i % 2) == 0);
        link.set_error(i == 3 ? ErrorCode::kCameraTimeout : ErrorCode::kNone);
        link.set_trigger_counters(static_cast<std::uint32_t>(i), 0);
        link.heartbeat();
        (void)link.take_commands();
        (void)link.stats();
        link.advance_to(static_cast<std::int64_t>(i) * 50 * kNsPerMs);
        (void)link.plc_read(200, block);
        (void)link.plc_write_register(0, (i % 2) == 0 ? map::kControlResultAck : std::uint16_t{0});
      }
      allocations = window.count();
    }
    CHECK(allocations == 0);
    CHECK(accepted >= 4);  // the loop really published
  }
  SECTION("Modbus server: publishing and serving requests") {
    ModbusServerConfig server_config = loopback_config();
    server_config.link = config;
    RunningServer running(server_config);
    MbClient client(running.port);
    REQUIRE(client.connected());
    BlockWords block{};
    REQUIRE(client.read(200, block.data(), kBlockWords) == 0);  // connection accepted and served once before counting
    long allocations = 0;
    int failures = 0;
    {
      AllocationWindow window;  // counts the network thread too
      for (const PlcResult& r : results) {
        if (running.server.publish(r) != PublishStatus::kQueued) ++failures;
        running.server.set_flag(StatusFlag::kBusy, true);
        running.server.heartbeat();
        (void)running.server.take_commands();
        if (client.read(200, block.data(), kBlockWords) != 0) ++failures;
        if (client.write(0, map::kControlResultAck) != 0) ++failures;
        if (client.write(0, 0) != 0) ++failures;
      }
      allocations = window.count();
    }
    CHECK(allocations == 0);
    CHECK(failures == 0);
    CHECK(running.server.stats().results_acked >= 4);
  }
}

TEST_CASE("sim link: a producer thread and a PLC thread exchange 2000 results without loss or duplicate",
          "[modbus][sim][threads]") {
  PlcLinkConfig config = sim_config();
  config.result_queue_capacity = 3;
  SimPlcLink link(config);
  REQUIRE(link.start().ok());
  constexpr std::uint32_t kCount = 2000;
  std::atomic<bool> producer_done{false};
  std::uint64_t full_retries = 0;
  std::thread producer([&] {
    for (std::uint32_t i = 1; i <= kCount; ++i) {
      PlcResult r;
      r.acq_id = i;
      r.x_um = -static_cast<std::int32_t>(i);
      r.timestamp_us = std::uint64_t{i} << 33;
      while (link.publish(r) == PublishStatus::kQueueFull) {
        ++full_retries;
        std::this_thread::yield();
      }
      link.set_trigger_counters(i, 0);
    }
    producer_done = true;
  });
  // The PLC: one thread, as the network thread would be.
  std::uint32_t expected = 1;
  int bad = 0;
  std::int64_t t_ms = 0;
  const auto started = Clock::now();
  while (expected <= kCount && elapsed_ms(started) < 30'000) {
    link.advance_to(++t_ms * kNsPerMs);
    std::array<std::uint16_t, 1> status{};
    if (link.plc_read(100, status) != 0) ++bad;
    if ((status[0] & map::kStatusResultValid) == 0) {
      std::this_thread::yield();
      continue;
    }
    BlockWords regs{};
    if (link.plc_read(200, regs) != 0) ++bad;
    const DecodedBlock block = decode_block(regs);
    if (block.seq != expected || block.seq_copy != expected || block.seq_copy2 != expected ||
        block.result.acq_id != expected || block.result.x_um != -static_cast<std::int32_t>(expected) ||
        block.result.timestamp_us != (std::uint64_t{expected} << 33)) {
      ++bad;
    }
    ++expected;
    if (link.plc_write_register(0, map::kControlResultAck) != 0) ++bad;
    if (link.plc_write_register(0, 0) != 0) ++bad;
  }
  producer.join();
  CHECK(bad == 0);
  CHECK(expected == kCount + 1);
  CHECK(producer_done.load());
  // Every retry was a rejection counted by the link (the producer gets told, nothing is silently dropped)
  CHECK(link.stats().results_rejected == full_retries);
  CHECK(link.stats().results_published == kCount);
}

// ================================================================== real server, real clients

TEST_CASE("server: a pymodbus PLC reading the whole block in one request sees every result once, exact, sigmas too",
          "[modbus][server][python]") {
  const std::string python = python_with_pymodbus();
  ModbusServerConfig config = loopback_config();
  config.link.result_queue_capacity = 8;
  config.link.plc_heartbeat_timeout_ms = 5000;  // the client writes PLC_HEARTBEAT on every poll
  RunningServer running(config);
  constexpr std::size_t kResults = 20;

  ChildProcess client({python, client_script(), "--port", std::to_string(running.port), "--count",
                       std::to_string(kResults), "--timeout", "40"},
                      stderr_file("python_ack"));
  REQUIRE(client.spawned());
  std::string line;
  JsonLine json;
  REQUIRE(client.read_line(line, 30'000));
  INFO("first line: " << line << "\nstderr: " << client.stderr_text());
  REQUIRE(parse_json_line(line, json));
  REQUIRE(json["event"] == "connected");
  CHECK(json_i64(json, "map_version") == kMapVersion);

  // Given a burst that fills the queue, then the rest as space frees up (never over capacity)
  const auto results = make_results(kResults, 21);
  for (std::size_t i = 0; i < config.link.result_queue_capacity; ++i) {
    REQUIRE(running.server.publish(results[i]) == PublishStatus::kQueued);
  }
  for (std::size_t i = config.link.result_queue_capacity; i < kResults; ++i) {
    REQUIRE(wait_until([&] { return running.server.stats().queue_depth < config.link.result_queue_capacity; }, 20'000));
    REQUIRE(running.server.publish(results[i]) == PublishStatus::kQueued);
  }

  // When the client has collected them all
  const std::vector<std::string> lines = client.read_all(40'000);
  const int exit_status = client.wait_exit(10'000);
  std::vector<JsonLine> received;
  JsonLine done;
  std::string errors;
  for (const std::string& text : lines) {
    REQUIRE(parse_json_line(text, json));
    if (json["event"] == "result") received.push_back(json);
    if (json["event"] == "done") done = json;
    if (json["event"] == "error") errors += json["what"] + "\n";
  }
  INFO("client stderr: " << client.stderr_text() << "\nclient errors: " << errors);
  CHECK(errors.empty());
  CHECK(exit_status == 0);
  // Then each one was seen exactly once, in order, with RESULT_VALID set and the values that were published
  REQUIRE(received.size() == kResults);
  for (std::size_t i = 0; i < kResults; ++i) {
    INFO("result " << i);
    CHECK(json_u64(received[i], "seq") == i + 1);
    CHECK((json_i64(received[i], "status") & map::kStatusResultValid) != 0);
    CHECK(same_result(result_from_json(received[i]), results[i]));
  }
  // And the markers reached the PLC program as "not available", never as numbers it might use
  CHECK(received[0]["z_um"] == "null");
  CHECK(received[0]["sigma_z_um"] == "null");
  CHECK(received[0]["sigma_x_um"] == "65534");
  CHECK(received[0]["sigma_y_um"] == "0");
  CHECK(json_i64(done, "torn") == 0);
  CHECK(wait_until([&] { return running.server.stats().results_acked == kResults; }, 5000));
  CHECK(running.server.stats().results_rejected == 0);
}

TEST_CASE("server: a polling pymodbus PLC reading with FC04 sees each result once", "[modbus][server][python]") {
  const std::string python = python_with_pymodbus();
  ModbusServerConfig config = loopback_config();
  config.link.ack_mode = AckMode::kPollOnly;
  config.link.poll_hold_ms = 150;
  RunningServer running(config);
  const auto results = make_results(4, 22);
  ChildProcess client({python, client_script(), "--port", std::to_string(running.port), "--count", "4", "--mode",
                       "poll", "--input", "--no-heartbeat", "--timeout", "40"},
                      stderr_file("python_poll"));
  REQUIRE(client.spawned());
  std::string line;
  JsonLine json;
  REQUIRE(client.read_line(line, 30'000));
  REQUIRE(parse_json_line(line, json));
  REQUIRE(json["event"] == "connected");
  for (const PlcResult& r : results) REQUIRE(running.server.publish(r) == PublishStatus::kQueued);
  std::vector<JsonLine> received;
  for (const std::string& text : client.read_all(40'000)) {
    REQUIRE(parse_json_line(text, json));
    if (json["event"] == "result") received.push_back(json);
    if (json["event"] == "error") FAIL_CHECK("client error: " << json["what"]);
  }
  CHECK(client.wait_exit(10'000) == 0);
  REQUIRE(received.size() == results.size());
  for (std::size_t i = 0; i < results.size(); ++i) {
    CHECK(json_u64(received[i], "seq") == i + 1);
    CHECK(same_result(result_from_json(received[i]), results[i]));
  }
}

TEST_CASE("server: mbpoll reads the result block word for word and 32-bit values high word first",
          "[modbus][server][mbpoll]") {
  const std::string mbpoll = find_program("mbpoll");
  if (mbpoll.empty()) FAIL("mbpoll not found on PATH: install it (apt-get install mbpoll; scripts/setup.sh)");
  RunningServer running(loopback_config());
  PlcResult r = make_results(3, 23)[1];
  r.acq_id = 0x0102'0304u;  // mbpoll prints 32-bit values signed; keep these two positive
  r.x_um = -1'234'567;
  r.y_um = 7'654'321;
  r.z_um = map::kInvalidS32;
  r.rx_mdeg = -1;
  r.ry_mdeg = 65536;
  r.rz_mdeg = -45'000;
  REQUIRE(running.server.publish(r) == PublishStatus::kQueued);
  MbClient observer(running.port);
  REQUIRE(observer.connected());
  REQUIRE(wait_until([&] { return (observer.status() & map::kStatusResultValid) != 0; }, 2000));

  // mbpoll -r is the 1-based reference: address + 1.
  auto run_mbpoll = [&](const std::vector<std::string>& options, const char* tag) {
    std::vector<std::string> argv = {mbpoll, "-m", "tcp", "-a", "1"};
    argv.insert(argv.end(), options.begin(), options.end());
    argv.insert(argv.end(), {"-1", "-p", std::to_string(running.port), "127.0.0.1"});
    ChildProcess process(argv, stderr_file(tag));
    REQUIRE(process.spawned());
    std::map<int, long long> values;
    for (const std::string& text : process.read_all(20'000)) {
      int reference = 0;
      long long value = 0;
      if (std::sscanf(text.c_str(), "[%d]: %lld", &reference, &value) == 2) values[reference] = value;
    }
    INFO("mbpoll stderr: " << process.stderr_text());
    REQUIRE(process.wait_exit(20'000) == 0);
    return values;
  };

  SECTION("35 holding registers, 16 bit, one request") {
    const auto values = run_mbpoll({"-r", "201", "-c", "35", "-t", "4"}, "mbpoll16");
    const auto expected = expected_words(r, 1);
    REQUIRE(values.size() == kBlockWords);
    for (int i = 0; i < kBlockWords; ++i) {
      INFO("address " << 200 + i);
      CHECK(values.at(201 + i) == expected[static_cast<std::size_t>(i)]);
    }
  }
  SECTION("pose as six 32-bit signed values, big-endian word order") {
    const auto values = run_mbpoll({"-r", "209", "-c", "6", "-t", "4:int", "-B"}, "mbpoll32");
    REQUIRE(values.size() == 6);
    CHECK(values.at(209) == r.x_um);
    CHECK(values.at(211) == r.y_um);
    CHECK(values.at(213) == static_cast<long long>(map::kInvalidS32));
    CHECK(values.at(215) == r.rx_mdeg);
    CHECK(values.at(217) == r.ry_mdeg);
    CHECK(values.at(219) == r.rz_mdeg);
  }
  SECTION("the same block as input registers (FC04)") {
    const auto values = run_mbpoll({"-r", "201", "-c", "2", "-t", "3:int", "-B"}, "mbpoll_input");
    REQUIRE(values.size() == 2);
    CHECK(values.at(201) == 1);            // RESULT_SEQ
    CHECK(values.at(203) == 0x0102'0304);  // ACQ_ID
  }
}

TEST_CASE("server: a PLC written for map version 1 reads 200-226 in one request and still gets a whole block",
          "[modbus][server]") {
  // Given a published result with every field set, the version-2 ones too
  RunningServer running(loopback_config());
  const PlcResult r = make_results(3, 28)[1];
  REQUIRE(running.server.publish(r) == PublishStatus::kQueued);
  MbClient plc(running.port);
  REQUIRE(plc.connected());
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusResultValid) != 0; }, 2000));
  const BlockWords expected = expected_words(r, 1);
  for (const bool input : {false, true}) {
    INFO((input ? "FC04" : "FC03"));
    // When a version-1 PLC reads its 27 registers
    std::array<std::uint16_t, kBlockWordsV1> words{};
    REQUIRE(plc.read(200, words.data(), kBlockWordsV1, input) == 0);
    // Then they are the version-1 block word for word, and its sequence copy at 225-226 accepts it
    CHECK(std::equal(words.begin(), words.end(), expected.begin()));
    const DecodedBlock block = decode_block(words);
    CHECK(block.seq == 1);
    CHECK(block.seq_copy == block.seq);
    CHECK(block.result.x_um == r.x_um);
    CHECK(block.result.rz_mdeg == r.rz_mdeg);
    CHECK(block.result.cycle_ms == r.cycle_ms);
  }
}

TEST_CASE("server: two clients see the same result and disconnects or reconnects keep the server serving",
          "[modbus][server]") {
  RunningServer running(loopback_config());
  const PlcResult published = make_results(1, 24)[0];
  REQUIRE(running.server.publish(published) == PublishStatus::kQueued);
  auto a = std::make_unique<MbClient>(running.port);
  MbClient b(running.port);
  REQUIRE(a->connected());
  REQUIRE(b.connected());
  REQUIRE(wait_until([&] { return (b.status() & map::kStatusResultValid) != 0; }, 2000));
  // Both see the same, correct block
  const DecodedBlock from_a = a->block();
  const DecodedBlock from_b = b.block();
  CHECK(from_a.seq == 1);
  CHECK(from_b.seq == 1);
  CHECK(same_result(from_a.result, published));
  CHECK(same_result(from_b.result, published));
  // When A goes away (orderly), B keeps being served; when A comes back, it reads the same block
  a.reset();
  CHECK(b.block().seq == 1);
  a = std::make_unique<MbClient>(running.port);
  REQUIRE(a->connected());
  CHECK(same_result(a->block().result, published));
  // When a client vanishes mid-request (reset, half a frame sent), the others are unaffected
  {
    RawClient vanishing(running.port);
    REQUIRE(vanishing.connected());
    REQUIRE(vanishing.send_bytes({0x00, 0x01, 0x00, 0x00, 0x00}));
    vanishing.abort_connection();
  }
  for (int i = 0; i < 20; ++i) {
    CHECK(b.block().seq == 1);
    CHECK(a->block().seq == 1);
  }
  CHECK(wait_until([&] { return running.server.stats().clients_connected == 2; }, 3000));
  CHECK(running.server.stats().clients_accepted >= 3);
}

TEST_CASE("server: malformed frames get exceptions or a closed connection while other clients keep being served",
          "[modbus][server][robustness]") {
  ModbusServerConfig config = loopback_config();
  config.byte_timeout_ms = 150;
  RunningServer running(config);
  REQUIRE(running.server.publish(make_results(1, 25)[0]) == PublishStatus::kQueued);
  MbClient observer(running.port);
  REQUIRE(observer.connected());
  REQUIRE(wait_until([&] { return (observer.status() & map::kStatusResultValid) != 0; }, 2000));
  const DecodedBlock before = observer.block();
  auto observer_fine = [&] {
    BlockWords regs{};
    return observer.read(200, regs.data(), kBlockWords) == 0 && decode_block(regs).seq == before.seq;
  };

  SECTION("unknown function codes: exception 01, connection still usable") {
    RawClient raw(running.port);
    REQUIRE(raw.connected());
    CHECK(raw.exception_for(adu(1, 1, {0x2B, 0x0E, 0x01, 0x00})) == 1);                   // read device identification
    CHECK(raw.exception_for(adu(2, 1, {0x08, 0x00, 0x00, 0x12, 0x34})) == 1);             // diagnostics echo
    CHECK(raw.exception_for(adu(3, 1, {0x17, 0, 100, 0, 1, 0, 0, 0, 1, 2, 0, 0})) == 1);  // read/write multiple
    CHECK(raw.exception_for(adu(4, 1, {0x05, 0, 0, 0xFF, 0})) == 1);                      // write coil
    // The same connection then gets a normal answer
    REQUIRE(raw.send_bytes(adu(5, 1, pdu_read(3, 100, 2))));
    std::vector<std::uint8_t> reply;
    REQUIRE(raw.receive(reply, 13, 2000) == RawClient::Outcome::kData);
    CHECK(reply[7] == 3);
    CHECK(reply[8] == 4);  // byte count
    CHECK(observer_fine());
  }
  SECTION("addresses outside the map and writes into the read-only blocks: exception 02, nothing written") {
    RawClient raw(running.port);
    REQUIRE(raw.connected());
    CHECK(raw.exception_for(adu(1, 1, pdu_read(3, 10, 1))) == 2);
    CHECK(raw.exception_for(adu(2, 1, pdu_read(3, 99, 2))) == 2);
    CHECK(raw.exception_for(adu(3, 1, pdu_read(3, 230, 10))) == 2);  // runs past 234
    CHECK(raw.exception_for(adu(10, 1, pdu_read(4, 200, 36))) == 2);
    CHECK(raw.exception_for(adu(4, 1, pdu_read(4, 0, 1))) == 2);
    CHECK(raw.exception_for(adu(5, 1, pdu_read(3, 65535, 125))) == 2);
    CHECK(raw.exception_for(adu(6, 1, {0x06, 0, 100, 0xFF, 0xFF})) == 2);
    CHECK(raw.exception_for(adu(7, 1, {0x06, 0, 226, 0, 0})) == 2);
    CHECK(raw.exception_for(adu(11, 1, {0x06, 0, 234, 0, 0})) == 2);
    CHECK(raw.exception_for(adu(8, 1, pdu_write_multiple(200, {0, 0}))) == 2);
    CHECK(raw.exception_for(adu(9, 1, pdu_write_multiple(8, {1, 2, 3}))) == 2);
    const DecodedBlock after = observer.block();
    CHECK(after.seq == before.seq);
    CHECK(same_result(after.result, before.result));
    CHECK(observer_fine());
  }
  SECTION("quantity 0 or above the limit, and lying byte counts: exception 03") {
    RawClient raw(running.port);
    REQUIRE(raw.connected());
    CHECK(raw.exception_for(adu(1, 1, pdu_read(3, 100, 0))) == 3);
    CHECK(raw.exception_for(adu(2, 1, pdu_read(3, 100, 126))) == 3);
    CHECK(raw.exception_for(adu(3, 1, pdu_read(4, 200, 0))) == 3);
    CHECK(raw.exception_for(adu(4, 1, pdu_write_multiple(0, {}, std::uint16_t{0}))) == 3);
    CHECK(raw.exception_for(adu(5, 1, pdu_write_multiple(0, {}, std::uint16_t{124}, std::uint8_t{0}))) == 3);
    CHECK(raw.exception_for(adu(6, 1, pdu_write_multiple(0, {1}, std::uint16_t{5}, std::uint8_t{10}))) == 3);
    CHECK(observer_fine());
    CHECK(running.server.stats().exceptions_sent >= 6);
  }
  SECTION("broken MBAP framing closes that connection only") {
    const std::vector<std::vector<std::uint8_t>> broken = {
        adu(1, 1, pdu_read(3, 100, 1), 1),       // protocol id 1
        adu(1, 1, {}, 0, 1),                     // length 1: no function code
        adu(1, 1, pdu_read(3, 100, 1), 0, 300),  // length beyond the 260-byte ADU
    };
    for (const auto& frame : broken) {
      RawClient raw(running.port);
      REQUIRE(raw.connected());
      REQUIRE(raw.send_bytes(frame));
      CHECK(raw.closed_within(1000));
      CHECK(observer_fine());
    }
  }
  SECTION("truncated MBAP and a length that promises more than arrives: closed after the byte timeout") {
    for (const auto& frame :
         {std::vector<std::uint8_t>{0x00, 0x01, 0x00, 0x00}, adu(1, 1, pdu_read(3, 100, 1), 0, 20)}) {
      RawClient raw(running.port);
      REQUIRE(raw.connected());
      const auto sent_at = Clock::now();
      REQUIRE(raw.send_bytes(frame));
      CHECK(observer_fine());  // served while the other one is still pending
      CHECK(raw.closed_within(3000));
      CHECK(elapsed_ms(sent_at) >= config.byte_timeout_ms);
      CHECK(observer_fine());
    }
  }
}

namespace {

// Sends FC03 for MAP_VERSION (110) and checks the 11-byte answer: the connection is being served.
bool served(RawClient& client, std::uint16_t transaction) {
  if (!client.send_bytes(adu(transaction, 1, pdu_read(3, 110, 1)))) return false;
  std::vector<std::uint8_t> reply;
  if (client.receive(reply, 11, 2000) != RawClient::Outcome::kData) return false;
  return reply[0] == (transaction >> 8) && reply[1] == (transaction & 0xFF) && reply[7] == 3 && reply[8] == 2 &&
         reply[9] == 0 && reply[10] == kMapVersion;
}

// Connects `count` raw clients that send nothing, one after the other, each accepted by the server before the
// next connects (so their idle times are strictly ordered: the first is the longest idle).
std::vector<std::unique_ptr<RawClient>> connect_idle(const RunningServer& running, int count) {
  std::vector<std::unique_ptr<RawClient>> idle;
  for (int i = 0; i < count; ++i) {
    const std::uint64_t accepted = running.server.stats().clients_accepted;
    idle.push_back(std::make_unique<RawClient>(running.port));
    REQUIRE(idle.back()->connected());
    REQUIRE(wait_until([&] { return running.server.stats().clients_accepted == accepted + 1; }, 2000));
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return idle;
}

}  // namespace

TEST_CASE("server: idle connections filling every slot cannot lock the PLC out: the longest idle is evicted",
          "[modbus][server][robustness]") {
  ModbusServerConfig config = loopback_config();
  config.max_clients = 4;
  config.idle_timeout_ms = 60'000;  // the idle timeout would free a slot only after a minute
  RunningServer running(config);
  // Given every slot held by a connection that never sends a request
  auto idle = connect_idle(running, config.max_clients);
  REQUIRE(running.server.stats().clients_connected == 4);

  // When the PLC (re)connects, then it is served within 1 s
  const auto connecting = Clock::now();
  MbClient plc(running.port);
  REQUIRE(plc.connected());
  std::uint16_t version = 0;
  REQUIRE(plc.read(110, &version, 1) == 0);
  CHECK(elapsed_ms(connecting) < 1000);
  CHECK(version == kMapVersion);
  // And the connection that was idle longest (the first) made room for it, the others keep their slots
  CHECK(idle[0]->closed_within(2000));
  LinkStats stats = running.server.stats();
  CHECK(stats.clients_evicted == 1);
  CHECK(stats.clients_refused == 0);
  CHECK(stats.clients_dropped == 0);  // an eviction is counted on its own
  CHECK(stats.clients_connected == 4);

  // When another newcomer arrives while the PLC keeps polling, then the next idle one goes, not the PLC
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  REQUIRE(plc.read(110, &version, 1) == 0);
  RawClient newcomer(running.port);
  REQUIRE(newcomer.connected());
  CHECK(served(newcomer, 7));
  CHECK(idle[1]->closed_within(2000));
  CHECK(plc.read(110, &version, 1) == 0);
  CHECK(served(*idle[2], 8));
  CHECK(served(*idle[3], 9));
  stats = running.server.stats();
  CHECK(stats.clients_evicted == 2);
  CHECK(stats.clients_connected == 4);
}

TEST_CASE("server: a client that polls keeps its slot however early it connected, the idle ones go first",
          "[modbus][server][robustness]") {
  ModbusServerConfig config = loopback_config();
  config.max_clients = 3;
  RunningServer running(config);
  // Given a PLC that connected first, then idle connections in every other slot, then a poll by the PLC
  MbClient plc(running.port);
  REQUIRE(plc.connected());
  std::uint16_t version = 0;
  REQUIRE(plc.read(110, &version, 1) == 0);
  auto idle = connect_idle(running, config.max_clients - 1);
  REQUIRE(plc.read(110, &version, 1) == 0);
  // When a newcomer connects, then the idle one connected first goes: the PLC's last request is the newest
  RawClient newcomer(running.port);
  REQUIRE(newcomer.connected());
  CHECK(served(newcomer, 4));
  CHECK(idle[0]->closed_within(2000));
  CHECK(plc.read(110, &version, 1) == 0);
  CHECK(served(*idle[1], 5));
  CHECK(running.server.stats().clients_evicted == 1);
}

TEST_CASE("server: a storm of new connections that send nothing does not push out a client that polls",
          "[modbus][server][robustness]") {
  // Found by the soak (tests/soak.py): a port scanner's burst of connections evicted the polling PLC, because each
  // newcomer counted as active from its connection and the PLC had been quiet for one poll period.
  ModbusServerConfig config = loopback_config();
  config.max_clients = 3;
  RunningServer running(config);
  // Given a PLC that polls, and a second client that polls too
  MbClient plc(running.port);
  MbClient hmi(running.port);
  REQUIRE(plc.connected());
  REQUIRE(hmi.connected());
  std::uint16_t version = 0;
  REQUIRE(plc.read(110, &version, 1) == 0);
  REQUIRE(hmi.read(110, &version, 1) == 0);
  // When, after their last poll, connections arrive one after another and send nothing
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  auto storm = connect_idle(running, 6);
  // Then each newcomer took the slot of the silent one before it, never a client that polls
  CHECK(running.server.stats().clients_evicted == 5);
  CHECK(plc.read(110, &version, 1) == 0);
  CHECK(hmi.read(110, &version, 1) == 0);
  CHECK(version == kMapVersion);
  for (std::size_t i = 0; i + 1 < storm.size(); ++i) CHECK(storm[i]->closed_within(2000));
  CHECK(served(*storm.back(), 11));
}

TEST_CASE("server: a client in the middle of a request is not evicted in preference to an idle one",
          "[modbus][server][robustness]") {
  ModbusServerConfig config = loopback_config();
  config.byte_timeout_ms = 5000;  // the half-sent request stays pending for the whole test
  const std::vector<std::uint8_t> request = adu(0x0102, 1, pdu_read(3, 110, 1));
  const std::vector<std::uint8_t> first_half(request.begin(), request.begin() + 5);
  const std::vector<std::uint8_t> second_half(request.begin() + 5, request.end());

  SECTION("the idle one goes, the busy one is answered when its request completes") {
    config.max_clients = 2;
    RunningServer running(config);
    // Given a client that connected first (longest without a complete request) and has half a request buffered,
    auto busy = connect_idle(running, 1);
    // (sent before the next connection: the server reads a round's data before it accepts, so the half frame is
    // buffered by the time the next client is accepted)
    REQUIRE(busy[0]->send_bytes(first_half));
    // and a client that connected later and sends nothing
    auto idle = connect_idle(running, 1);
    // When a newcomer connects
    RawClient newcomer(running.port);
    REQUIRE(newcomer.connected());
    // Then the idle one is evicted and the newcomer served
    CHECK(served(newcomer, 3));
    CHECK(idle[0]->closed_within(2000));
    // And the busy one still gets its answer once the rest of its request arrives
    REQUIRE(busy[0]->send_bytes(second_half));
    std::vector<std::uint8_t> reply;
    REQUIRE(busy[0]->receive(reply, 11, 2000) == RawClient::Outcome::kData);
    CHECK(reply[0] == 0x01);
    CHECK(reply[1] == 0x02);
    CHECK(reply[10] == kMapVersion);
    CHECK(running.server.stats().clients_evicted == 1);
    CHECK(running.server.stats().clients_refused == 0);
  }
  SECTION("when every client is in the middle of a request the newcomer is refused") {
    config.max_clients = 1;
    RunningServer running(config);
    auto busy = connect_idle(running, 1);
    REQUIRE(busy[0]->send_bytes(first_half));
    RawClient newcomer(running.port);
    REQUIRE(newcomer.connected());  // the kernel completes the handshake; the server then closes it
    REQUIRE(newcomer.send_bytes(request));
    CHECK(newcomer.closed_within(2000));
    CHECK(running.server.stats().clients_refused == 1);
    CHECK(running.server.stats().clients_evicted == 0);
    REQUIRE(busy[0]->send_bytes(second_half));
    std::vector<std::uint8_t> reply;
    REQUIRE(busy[0]->receive(reply, 11, 2000) == RawClient::Outcome::kData);
    CHECK(reply[10] == kMapVersion);
  }
}

TEST_CASE("server: HEARTBEAT advances by one per 100 ms of wall time", "[modbus][server]") {
  RunningServer running(loopback_config());
  MbClient client(running.port);
  REQUIRE(client.connected());
  std::uint16_t first = 0;
  std::uint16_t second = 0;
  const auto t0_send = Clock::now();
  REQUIRE(client.read(101, &first, 1) == 0);
  const auto t0_recv = Clock::now();
  std::this_thread::sleep_for(std::chrono::milliseconds(650));
  const auto t1_send = Clock::now();
  REQUIRE(client.read(101, &second, 1) == 0);
  const auto t1_recv = Clock::now();
  // The register was sampled somewhere inside each request's round trip: bound the count from both sides.
  const auto shortest = std::chrono::duration_cast<std::chrono::milliseconds>(t1_send - t0_recv).count();
  const auto longest = std::chrono::duration_cast<std::chrono::milliseconds>(t1_recv - t0_send).count();
  const int advanced = static_cast<std::uint16_t>(second - first);
  INFO("advanced " << advanced << " in " << shortest << ".." << longest << " ms");
  CHECK(advanced >= shortest / 100 - 1);
  CHECK(advanced <= longest / 100 + 1);
  CHECK(advanced >= 5);
}

TEST_CASE("server: a lost PLC heartbeat sets PLC_HB_LOST and drops RESULT_VALID until the heartbeat returns",
          "[modbus][server]") {
  ModbusServerConfig config = loopback_config();
  config.link.plc_heartbeat_timeout_ms = 300;
  RunningServer running(config);
  MbClient plc(running.port);
  REQUIRE(plc.connected());
  REQUIRE(plc.write(4, 1) == 0);
  REQUIRE(running.server.publish(make_results(1, 26)[0]) == PublishStatus::kQueued);
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusResultValid) != 0; }, 2000));
  // When the PLC stops moving PLC_HEARTBEAT (the server stamps the last change after this instant)
  const auto last_beat = Clock::now();
  REQUIRE(plc.write(4, 2) == 0);
  std::uint16_t status = 0;
  REQUIRE(wait_until(
      [&] {
        status = plc.status();
        return (status & map::kStatusPlcHbLost) != 0;
      },
      3000));
  // Then not before the timeout, and in the same read RESULT_VALID is gone
  CHECK(elapsed_ms(last_beat) >= config.link.plc_heartbeat_timeout_ms);
  CHECK((status & map::kStatusResultValid) == 0);
  CHECK(running.server.take_commands().plc_heartbeat_lost);
  // When it moves again, then the same result is valid again at the next read
  REQUIRE(plc.write(4, 3) == 0);
  status = plc.status();
  CHECK((status & map::kStatusPlcHbLost) == 0);
  CHECK((status & map::kStatusResultValid) != 0);
  CHECK(plc.block().seq == 1);
}

TEST_CASE("server: set_error withdraws RESULT_VALID before the next reply", "[modbus][server]") {
  RunningServer running(loopback_config());
  MbClient plc(running.port);
  REQUIRE(plc.connected());
  REQUIRE(running.server.publish(make_results(1, 27)[0]) == PublishStatus::kQueued);
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusResultValid) != 0; }, 2000));
  running.server.set_error(ErrorCode::kModelDatabaseInvalid);
  std::array<std::uint16_t, 3> regs{};
  REQUIRE(plc.read(100, regs.data(), 3) == 0);
  CHECK((regs[0] & map::kStatusResultValid) == 0);
  CHECK((regs[0] & map::kStatusError) != 0);
  CHECK(regs[2] == static_cast<std::uint16_t>(ErrorCode::kModelDatabaseInvalid));
  running.server.set_error(ErrorCode::kNone);
  CHECK((plc.status() & (map::kStatusResultValid | map::kStatusError)) == map::kStatusResultValid);
}

TEST_CASE("server: start() fails with a clear message on a taken port or a bad configuration", "[modbus][server]") {
  RunningServer first(loopback_config());
  ModbusServerConfig same_port = loopback_config();
  same_port.port = first.port;
  ModbusServer second(same_port);
  const cellsight::Status taken = second.start();
  REQUIRE_FALSE(taken.ok());
  CHECK_THAT(taken.error().message, Catch::Contains("cannot listen") && Catch::Contains("in use"));

  ModbusServerConfig bad_address = loopback_config();
  bad_address.bind_address = "300.1.2.3";
  ModbusServer third(bad_address);
  const cellsight::Status refused = third.start();
  REQUIRE_FALSE(refused.ok());
  CHECK_THAT(refused.error().message, Catch::Contains("300.1.2.3"));

  ModbusServerConfig no_clients = loopback_config();
  no_clients.max_clients = 0;
  ModbusServer fourth(no_clients);
  CHECK_FALSE(fourth.start().ok());
  // The first server is unaffected by its failed neighbours
  MbClient client(first.port);
  REQUIRE(client.connected());
  std::uint16_t version = 0;
  CHECK(client.read(110, &version, 1) == 0);
  CHECK(version == kMapVersion);
}
