// Tests of runtime/plc_mapping: decision -> result block words, loop state -> STATUS bits, part -> WARNING_CODE.
// The truth is the README's register table, worked out by hand in the comments (addresses 200-234, 32-bit values high
// word first, 0x80000000 = invalid pose value, 0xFFFF = sigma not available), not the code under test.
#include <array>
#include <catch2/catch.hpp>
#include <cstdint>
#include <limits>
#include <numbers>
#include <utility>

#include "drivers/modbus/link_core.hpp"
#include "drivers/modbus/register_map.hpp"
#include "runtime/plc_mapping.hpp"

namespace {

using namespace cellsight;
using algo::PoseAxis;
using drivers::ResultCode;
using drivers::StatusFlag;
using drivers::WarningCode;
using runtime::LoopState;

using Block = std::array<std::uint16_t, drivers::modbus_map::kResultBlockCount>;

// The 35 words the PLC reads at 200-234 for `decision` published as RESULT_SEQ `seq`.
Block words_of(const algo::Decision& decision, std::uint32_t acq_id, std::uint64_t timestamp_us, double cycle_ms,
               std::uint32_t seq) {
  Block block{};
  drivers::encode_result_block(runtime::to_plc_result(decision, acq_id, timestamp_us, cycle_ms), seq, block);
  return block;
}

algo::Decision accepted(algo::DecisionSource source, int part_id, double p, double x_m, double y_m, double theta_rad) {
  algo::Decision d;
  d.source = source;
  d.part_id = part_id;
  d.class_index = 0;
  d.probability = p;
  d.pose.x_m = x_m;
  d.pose.y_m = y_m;
  d.pose.theta_rad = theta_rad;
  d.pose_valid = true;
  return d;
}

void set_sigma(algo::Decision& d, PoseAxis axis, double sigma) {
  d.pose_sigma[static_cast<std::size_t>(axis)] = sigma;
}

constexpr std::uint16_t kInvalidHi = 0x8000;  // 0x80000000, high word first
constexpr std::uint16_t kInvalidLo = 0x0000;
constexpr std::uint16_t kNoSigma = 0xFFFF;
// Word indices (address - 200) of the README's table.
constexpr std::size_t kZ = 12, kRx = 14, kRy = 16;
constexpr std::size_t kSigmaX = 27, kSigmaY = 28, kSigmaZ = 29, kSigmaRx = 30, kSigmaRy = 31, kSigmaRz = 32;

bool invalid_s32(const Block& words, std::size_t at) {
  return words[at] == kInvalidHi && words[at + 1] == kInvalidLo;
}

TEST_CASE("plc mapping: an SVM decision with the full pose gives the documented result block, word by word",
          "[plc_mapping]") {
  // Given part id 3 at p 0.875, x 12.345678 mm, y -4.5 mm, z -32.1 mm, rx 0.01 rad, ry -0.002 rad, theta 0.05 rad,
  // sigmas 0.4 mm, 12.6 um, 2.1 mm, 3 mrad, 1.5 mrad, 0.7 mrad; acquisition 42, published as seq 7
  algo::Decision d = accepted(algo::DecisionSource::kSvm, 3, 0.875, 0.012345678, -0.0045, 0.05);
  d.z_m = -0.0321;
  d.rx_rad = 0.01;
  d.ry_rad = -0.002;
  d.pose_sigma = {0.0004, 0.0000126, 0.0021, 0.003, 0.0015, 0.0007};
  // When mapped and encoded
  const Block words = words_of(d, 42, 123456789, 17.4, 7);
  // Then, by hand: x 12345.678 um -> 12346 = 0x0000'303A; y -4500 um = 0xFFFF'EE6C; z -32100 um = 0xFFFF'829C;
  // rx 0.01 rad = 0.5729578 deg -> 573 mdeg = 0x0000'023D; ry -0.002 rad = -0.1145916 deg -> -115 mdeg =
  // 0xFFFF'FF8D; theta 0.05 rad = 2.864789 deg -> 2865 mdeg = 0x0000'0B31; timestamp 123456789 us =
  // 0x0000'0000'075B'CD15. Sigmas: 400 um; 12.6 -> 13 um; 2100 um; 3 mrad = 171.887 -> 172 mdeg;
  // 1.5 mrad = 85.944 -> 86 mdeg; 0.7 mrad = 40.107 -> 40 mdeg.
  const Block expected = {
      0x0000, 0x0007,                  // 200-201 RESULT_SEQ
      0x0000, 0x002A,                  // 202-203 ACQ_ID 42
      0,                               // 204 RESULT_CODE ok
      3,                               // 205 PART_ID
      875,                             // 206 CONFIDENCE per mille
      1,                               // 207 SOURCE svm
      0x0000, 0x303A,                  // 208-209 X um
      0xFFFF, 0xEE6C,                  // 210-211 Y um
      0xFFFF, 0x829C,                  // 212-213 Z um
      0x0000, 0x023D,                  // 214-215 RX mdeg
      0xFFFF, 0xFF8D,                  // 216-217 RY mdeg
      0x0000, 0x0B31,                  // 218-219 RZ mdeg
      0x0000, 0x0000, 0x075B, 0xCD15,  // 220-223 TIMESTAMP
      17,                              // 224 CYCLE_MS (17.4 rounded)
      0x0000, 0x0007,                  // 225-226 RESULT_SEQ copy (the end of a version-1 read)
      400,                             // 227 SIGMA_X_UM
      13,                              // 228 SIGMA_Y_UM
      2100,                            // 229 SIGMA_Z_UM
      172,                             // 230 SIGMA_RX_MDEG
      86,                              // 231 SIGMA_RY_MDEG
      40,                              // 232 SIGMA_RZ_MDEG
      0x0000, 0x0007,                  // 233-234 RESULT_SEQ copy 2
  };
  CHECK(words == expected);
}

TEST_CASE("plc mapping: an axis the geometry does not fix goes out as 0x80000000 with sigma 0xFFFF, the result ok",
          "[plc_mapping]") {
  // Given a planar pose with its sigmas and z, rx, ry NaN (a part too narrow to fix them), as the recogniser says
  algo::Decision d = accepted(algo::DecisionSource::kPm, 5, 0.9, 0.001, 0.002, 0.003);
  set_sigma(d, PoseAxis::kX, 0.0002);
  set_sigma(d, PoseAxis::kY, 0.0003);
  set_sigma(d, PoseAxis::kRz, 0.001);  // 57.296 mdeg
  SECTION("all three out-of-plane axes missing") {
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 0);  // still ok: the robot can correct x, y and theta
    CHECK(invalid_s32(words, kZ));
    CHECK(invalid_s32(words, kRx));
    CHECK(invalid_s32(words, kRy));
    CHECK(words[kSigmaX] == 200);
    CHECK(words[kSigmaY] == 300);
    CHECK(words[kSigmaZ] == kNoSigma);
    CHECK(words[kSigmaRx] == kNoSigma);
    CHECK(words[kSigmaRy] == kNoSigma);
    CHECK(words[kSigmaRz] == 57);
  }
  SECTION("z fixed, tilt and swing not: each axis on its own") {
    d.z_m = 0.0005;
    set_sigma(d, PoseAxis::kZ, 0.0011);
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[kZ] == 0x0000);
    CHECK(words[kZ + 1] == 500);
    CHECK(words[kSigmaZ] == 1100);
    CHECK(invalid_s32(words, kRx));
    CHECK(invalid_s32(words, kRy));
    CHECK(words[kSigmaRx] == kNoSigma);
  }
  SECTION("a sigma without its value is not published (the value decides, not the estimate)") {
    set_sigma(d, PoseAxis::kRx, 0.002);  // rx itself stays NaN
    d.ry_rad = 1e5;                      // 5.7e9 millidegrees: beyond s32
    set_sigma(d, PoseAxis::kRy, 0.002);
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 0);
    CHECK(invalid_s32(words, kRy));
    CHECK(words[kSigmaRx] == kNoSigma);
    CHECK(words[kSigmaRy] == kNoSigma);
  }
  SECTION("a value whose sigma was not estimated") {
    d.z_m = 0.0;
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[kZ] == 0x0000);  // 0 is a measurement here, not a placeholder
    CHECK(words[kZ + 1] == 0x0000);
    CHECK(words[kSigmaZ] == kNoSigma);
  }
}

TEST_CASE("plc mapping: sigmas are rounded, saturate at 65534 and are 0xFFFF when not finite or negative",
          "[plc_mapping]") {
  algo::Decision d = accepted(algo::DecisionSource::kSvm, 1, 0.9, 0.0, 0.0, 0.0);
  d.z_m = 0.0;
  d.rx_rad = 0.0;
  d.ry_rad = 0.0;
  const auto sigma_words = [&d](double linear_m, double angular_rad) {
    d.pose_sigma = {linear_m, linear_m, linear_m, angular_rad, angular_rad, angular_rad};
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[kSigmaY] == words[kSigmaX]);  // each register follows its own axis: same input, same word
    CHECK(words[kSigmaZ] == words[kSigmaX]);
    CHECK(words[kSigmaRy] == words[kSigmaRx]);
    CHECK(words[kSigmaRz] == words[kSigmaRx]);
    return std::pair{words[kSigmaX], words[kSigmaRx]};
  };
  // 0.4 um -> 0; 0.0004 deg = 0.4 mdeg -> 0 (a sigma below the wire's resolution is 0, still "available")
  CHECK(sigma_words(0.0000004, 0.0004 * std::numbers::pi / 180.0) == std::pair<std::uint16_t, std::uint16_t>{0, 0});
  // 1.6 um -> 2; 1.4 mdeg -> 1
  CHECK(sigma_words(0.0000016, 0.0014 * std::numbers::pi / 180.0) == std::pair<std::uint16_t, std::uint16_t>{2, 1});
  // 65534.4 um -> 65534; 65.5344 deg -> 65534 mdeg
  CHECK(sigma_words(0.0655344, 65.5344 * std::numbers::pi / 180.0) ==
        std::pair<std::uint16_t, std::uint16_t>{65534, 65534});
  // 65534.6 um rounds to 65535, which would read "not available": saturates at 65534 instead; 1 m, 1.2 rad too
  CHECK(sigma_words(0.0655346, 65.5346 * std::numbers::pi / 180.0) ==
        std::pair<std::uint16_t, std::uint16_t>{65534, 65534});
  CHECK(sigma_words(1.0, 1.2) == std::pair<std::uint16_t, std::uint16_t>{65534, 65534});
  // Not estimated, infinite, negative: not available
  CHECK(sigma_words(std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()) ==
        std::pair{kNoSigma, kNoSigma});
  CHECK(sigma_words(std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity()) ==
        std::pair{kNoSigma, kNoSigma});
  CHECK(sigma_words(-0.0001, -0.001) == std::pair{kNoSigma, kNoSigma});
}

TEST_CASE("plc mapping: a Perfect Match decision with negative pose values", "[plc_mapping]") {
  // Given -250 mm, +300 mm, -0.5 rad (= -28.64789 deg) from Perfect Match
  const algo::Decision d = accepted(algo::DecisionSource::kPm, 0x1234, 1.0, -0.25, 0.3, -0.5);
  const Block words = words_of(d, 0x00010002, 0x0123456789ABCDEF, 2999.6, 0x00030004);
  // Then: -250000 um = 0xFFFC'2F70, 300000 um = 0x0004'93E0, -28648 mdeg = 0xFFFF'9018, p 1.0 -> 1000 per mille
  CHECK(words[0] == 0x0003);
  CHECK(words[1] == 0x0004);
  CHECK(words[2] == 0x0001);
  CHECK(words[3] == 0x0002);
  CHECK(words[4] == 0);
  CHECK(words[5] == 0x1234);
  CHECK(words[6] == 1000);
  CHECK(words[7] == 2);  // SOURCE perfect match
  CHECK(words[8] == 0xFFFC);
  CHECK(words[9] == 0x2F70);
  CHECK(words[10] == 0x0004);
  CHECK(words[11] == 0x93E0);
  CHECK(words[18] == 0xFFFF);
  CHECK(words[19] == 0x9018);
  CHECK(words[20] == 0x0123);
  CHECK(words[21] == 0x4567);
  CHECK(words[22] == 0x89AB);
  CHECK(words[23] == 0xCDEF);
  CHECK(words[24] == 3000);
}

TEST_CASE("plc mapping: results without a pose carry the invalid marker in every pose and sigma register",
          "[plc_mapping]") {
  const auto pose_invalid = [](const Block& words) {
    for (std::size_t i = 8; i < 20; i += 2) {
      if (!invalid_s32(words, i)) return false;
    }
    for (std::size_t i = kSigmaX; i <= kSigmaRz; ++i) {
      if (words[i] != kNoSigma) return false;
    }
    return true;
  };
  SECTION("unknown part: code 2, no part id, source none, the best class's confidence") {
    algo::Decision d;
    d.source = algo::DecisionSource::kUnknown;
    d.probability = 0.4126;
    d.z_m = 0.01;  // the best class's pose, had anyone filled it in, is no instruction
    d.pose_sigma = {0.001, 0.001, 0.001, 0.001, 0.001, 0.001};
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 2);
    CHECK(words[5] == 0);
    CHECK(words[6] == 413);
    CHECK(words[7] == 0);
    CHECK(pose_invalid(words));
  }
  SECTION("a class without a usable pose: code 4 'pose out of range', part id kept, pose invalid") {
    algo::Decision d = accepted(algo::DecisionSource::kSvm, 9, 0.9, 0.01, 0.01, 0.01);
    d.z_m = 0.01;  // whatever else the decision carries goes nowhere
    d.pose_sigma = {0.001, 0.001, 0.001, 0.001, 0.001, 0.001};
    d.pose_valid = false;
    Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 4);
    CHECK(words[5] == 9);
    CHECK(pose_invalid(words));
    // A pose beyond s32 micrometres (2147 m) is not representable either.
    d.pose_valid = true;
    d.pose.x_m = 3000.0;
    words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 4);
    CHECK(pose_invalid(words));
    // Nor is a pose with theta missing.
    d.pose.x_m = 0.01;
    d.pose.theta_rad = std::numeric_limits<double>::quiet_NaN();
    words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 4);
    CHECK(pose_invalid(words));
  }
  SECTION("timeout 6, bad scan 5, no part 1: no part id, no confidence") {
    for (const auto& [source, code] :
         {std::pair{algo::DecisionSource::kTimeout, 6}, std::pair{algo::DecisionSource::kBadScan, 5},
          std::pair{algo::DecisionSource::kNoPart, 1}}) {
      algo::Decision d;
      d.source = source;
      d.part_id = 7;
      d.probability = 0.9;
      d.pose_sigma = {0.001, 0.001, 0.001, 0.001, 0.001, 0.001};
      const Block words = words_of(d, 1, 0, 1.0, 1);
      CHECK(words[4] == code);
      CHECK(words[5] == 0);
      CHECK(words[6] == 0);
      CHECK(pose_invalid(words));
    }
  }
  SECTION("CYCLE_MS saturates at 65535 and is never negative") {
    algo::Decision d;
    d.source = algo::DecisionSource::kTimeout;
    CHECK(words_of(d, 1, 0, 1e9, 1)[24] == 0xFFFF);
    CHECK(words_of(d, 1, 0, -5.0, 1)[24] == 0);
    CHECK(words_of(d, 1, 0, std::numeric_limits<double>::quiet_NaN(), 1)[24] == 0xFFFF);
  }
}

TEST_CASE(
    "plc mapping: STATUS bits of each loop state (README: b0 READY, b1 TRIGGER_READY, b2 TRIGGER_ACK, b3 BUSY, "
    "b11 TEACH_MODE)",
    "[plc_mapping]") {
  using runtime::loop_status_flags;
  CHECK(loop_status_flags(LoopState::kIdle, true, false) == 0x0003);          // READY | TRIGGER_READY
  CHECK(loop_status_flags(LoopState::kIdle, false, false) == 0x0001);         // READY
  CHECK(loop_status_flags(LoopState::kScanning, false, false) == 0x000D);     // READY | TRIGGER_ACK | BUSY
  CHECK(loop_status_flags(LoopState::kRecognising, false, false) == 0x000D);  // the pass is still the PLC's
  CHECK(loop_status_flags(LoopState::kRecognising, false, true) == 0x0009);   // "timeout" is out: no TRIGGER_ACK
  CHECK(loop_status_flags(LoopState::kPublishing, false, false) == 0x0001);
  CHECK(loop_status_flags(LoopState::kFault, false, false) == 0x0000);
  CHECK(loop_status_flags(LoopState::kStopped, false, false) == 0x0000);
  CHECK(loop_status_flags(LoopState::kIdle, true, false, true) == 0x0803);  // teaching: TEACH_MODE as well
  CHECK(loop_status_flags(LoopState::kScanning, false, false, true) == 0x080D);
  std::uint16_t all = 0;
  for (const StatusFlag flag : runtime::kLoopStatusFlags)
    all = static_cast<std::uint16_t>(all | static_cast<std::uint16_t>(flag));
  CHECK(all == 0x080F);  // exactly the five bits the loop owns (b0-b3, b11 TEACH_MODE)
}

TEST_CASE("plc mapping: a trigger is allowed only when idle, loaded, enabled and (when asked) the queue has room",
          "[plc_mapping]") {
  runtime::TriggerGate gate;
  gate.state = LoopState::kIdle;
  gate.has_recogniser = true;
  gate.require_trigger_enable = true;
  gate.trigger_enable = true;
  CHECK(runtime::trigger_allowed(gate));
  auto with = [&gate](auto change) {
    runtime::TriggerGate g = gate;
    change(g);
    return runtime::trigger_allowed(g);
  };
  CHECK_FALSE(with([](auto& g) { g.state = LoopState::kScanning; }));
  CHECK_FALSE(with([](auto& g) { g.state = LoopState::kFault; }));
  CHECK_FALSE(with([](auto& g) { g.has_recogniser = false; }));
  CHECK_FALSE(with([](auto& g) { g.finished = true; }));
  CHECK_FALSE(with([](auto& g) { g.trigger_enable = false; }));
  CHECK(with([](auto& g) {
    g.trigger_enable = false;
    g.require_trigger_enable = false;
  }));
  CHECK(with([](auto& g) { g.queue_full = true; }));  // a full queue holds triggers only when told to
  CHECK_FALSE(with([](auto& g) {
    g.queue_full = true;
    g.hold_when_queue_full = true;
  }));
}

TEST_CASE("plc mapping: WARNING_CODE after a part: missed trigger, then exposure at limit, then cycle slow",
          "[plc_mapping]") {
  runtime::PartWarningInputs part;
  part.cycle_slow_ms = 100.0;
  part.cycle_ms = 50.0;
  CHECK(runtime::part_warning(part) == WarningCode::kNone);
  part.cycle_ms = 150.0;
  CHECK(runtime::part_warning(part) == WarningCode::kCycleSlow);
  part.exposure_at_limit = true;
  CHECK(runtime::part_warning(part) == WarningCode::kExposureAtLimit);
  part.missed_since_result = 2;
  CHECK(runtime::part_warning(part) == WarningCode::kMissedTrigger);
  // An aborted scan says nothing about exposure or cycle time; a missed trigger still counts.
  part.aborted = true;
  CHECK(runtime::part_warning(part) == WarningCode::kMissedTrigger);
  part.missed_since_result = 0;
  CHECK(runtime::part_warning(part) == WarningCode::kNone);
}

}  // namespace
