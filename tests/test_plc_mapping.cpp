// Tests of runtime/plc_mapping: decision -> result block words, loop state -> STATUS bits, part -> WARNING_CODE.
// The truth is the README's register table, worked out by hand in the comments (addresses 200-226, 32-bit values high
// word first, 0x80000000 = invalid), not the code under test.
#include <array>
#include <catch2/catch.hpp>
#include <cstdint>
#include <limits>

#include "drivers/modbus/link_core.hpp"
#include "drivers/modbus/register_map.hpp"
#include "runtime/plc_mapping.hpp"

namespace {

using namespace cellsight;
using drivers::ResultCode;
using drivers::StatusFlag;
using drivers::WarningCode;
using runtime::LoopState;

using Block = std::array<std::uint16_t, drivers::modbus_map::kResultBlockCount>;

// The 27 words the PLC reads at 200-226 for `decision` published as RESULT_SEQ `seq`.
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

constexpr std::uint16_t kInvalidHi = 0x8000;  // 0x80000000, high word first
constexpr std::uint16_t kInvalidLo = 0x0000;

TEST_CASE("plc mapping: an SVM decision gives the documented result block, word by word", "[plc_mapping]") {
  // Given part id 3 at p 0.875, x 12.345678 mm, y -4.5 mm, theta 0.05 rad, acquisition 42, published as seq 7
  const algo::Decision d = accepted(algo::DecisionSource::kSvm, 3, 0.875, 0.012345678, -0.0045, 0.05);
  // When mapped and encoded
  const Block words = words_of(d, 42, 123456789, 17.4, 7);
  // Then, by hand: x 12345.678 um -> 12346 = 0x0000'303A; y -4500 um = 0xFFFF'EE6C; theta 0.05 rad = 2.864789 deg
  // -> 2865 mdeg = 0x0000'0B31; Z, RX, RY 0 (planar pose); timestamp 123456789 us = 0x0000'0000'075B'CD15.
  const Block expected = {
      0x0000, 0x0007,                  // 200-201 RESULT_SEQ
      0x0000, 0x002A,                  // 202-203 ACQ_ID 42
      0,                               // 204 RESULT_CODE ok
      3,                               // 205 PART_ID
      875,                             // 206 CONFIDENCE per mille
      1,                               // 207 SOURCE svm
      0x0000, 0x303A,                  // 208-209 X um
      0xFFFF, 0xEE6C,                  // 210-211 Y um
      0x0000, 0x0000,                  // 212-213 Z
      0x0000, 0x0000,                  // 214-215 RX
      0x0000, 0x0000,                  // 216-217 RY
      0x0000, 0x0B31,                  // 218-219 RZ mdeg
      0x0000, 0x0000, 0x075B, 0xCD15,  // 220-223 TIMESTAMP
      17,                              // 224 CYCLE_MS (17.4 rounded)
      0x0000, 0x0007,                  // 225-226 RESULT_SEQ copy
  };
  CHECK(words == expected);
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

TEST_CASE("plc mapping: results without a pose carry the invalid marker in every pose register", "[plc_mapping]") {
  const auto pose_invalid = [](const Block& words) {
    for (int i = 8; i < 20; i += 2) {
      if (words[static_cast<std::size_t>(i)] != kInvalidHi || words[static_cast<std::size_t>(i) + 1] != kInvalidLo)
        return false;
    }
    return true;
  };
  SECTION("unknown part: code 2, no part id, source none, the best class's confidence") {
    algo::Decision d;
    d.source = algo::DecisionSource::kUnknown;
    d.probability = 0.4126;
    const Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 2);
    CHECK(words[5] == 0);
    CHECK(words[6] == 413);
    CHECK(words[7] == 0);
    CHECK(pose_invalid(words));
  }
  SECTION("a class without a usable pose: code 4 'pose out of range', part id kept, pose invalid") {
    algo::Decision d = accepted(algo::DecisionSource::kSvm, 9, 0.9, 0.01, 0.01, 0.01);
    d.pose_valid = false;
    Block words = words_of(d, 1, 0, 1.0, 1);
    CHECK(words[4] == 4);
    CHECK(words[5] == 9);
    CHECK(pose_invalid(words));
    // A pose beyond s32 micrometres (2147 m) is not representable either.
    d = accepted(algo::DecisionSource::kSvm, 9, 0.9, 3000.0, 0.0, 0.0);
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

TEST_CASE("plc mapping: STATUS bits of each loop state (README: b0 READY, b1 TRIGGER_READY, b2 TRIGGER_ACK, b3 BUSY)",
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
  std::uint16_t all = 0;
  for (const StatusFlag flag : runtime::kLoopStatusFlags)
    all = static_cast<std::uint16_t>(all | static_cast<std::uint16_t>(flag));
  CHECK(all == 0x000F);  // exactly the four bits the loop owns
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
