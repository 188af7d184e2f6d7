// A schedule of injected faults for the simulated cell's passes (`cellsight run --sim --sim-faults SPEC`): what the
// soak test makes the simulated devices suffer. Never used with real devices.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "base/result.hpp"
#include "drivers/sim/sim_devices.hpp"

namespace cellsight::sim {

enum class FaultKind : std::uint8_t {
  kCameraStall,    // no frames for longer than camera.timeout_ms mid-pass: the pass is aborted (ERROR_CODE 2)
  kCameraHiccup,   // no frames for a moment shorter than camera.timeout_ms: the pass goes on
  kEncoderGlitch,  // the encoder cannot be read for a moment mid-pass: the pass is aborted (ERROR_CODE 4)
  kChatter,        // the photo-eye bounces at both edges of the part, within gpio.debounce_us
};

[[nodiscard]] std::string_view to_string(FaultKind kind);

// What the defaults of each kind follow.
struct FaultDefaults {
  int camera_timeout_ms = 1000;  // camera.timeout_ms
  int debounce_us = 2000;        // gpio.debounce_us
};

struct FaultRule {
  FaultKind kind = FaultKind::kCameraStall;
  std::uint64_t every = 1;  // passes k with k % every == every - 1 (0-based, in the order the conveyor brings them)
  int value = 0;            // milliseconds of the stall / glitch; bounce pairs of chatter
};

class FaultPlan {
 public:
  FaultPlan() = default;
  // SPEC: comma-separated KIND@EVERY[/VALUE], KIND one of camera_stall, camera_hiccup, encoder_glitch, chatter;
  // VALUE the duration in ms (stall default 2 x camera.timeout_ms, hiccup camera.timeout_ms / 4, glitch 300) or,
  // for chatter, the bounce pairs per edge (default 3, spread over half the debounce window). Empty: no faults.
  [[nodiscard]] static Expected<FaultPlan> parse(std::string_view spec, const FaultDefaults& defaults);

  // The faults of pass k (0-based) of a pass of frame_count frames; at most one kind per pass (the first rule
  // listed that matches). The frame a stall or glitch starts at moves from pass to pass, first and last included.
  [[nodiscard]] PassFaults for_pass(std::uint64_t k, int frame_count) const;
  // Its kind's name, or empty.
  [[nodiscard]] std::string_view kind_of(std::uint64_t k) const;
  [[nodiscard]] bool empty() const { return rules_.empty(); }
  [[nodiscard]] const std::vector<FaultRule>& rules() const { return rules_; }

 private:
  [[nodiscard]] const FaultRule* rule_of(std::uint64_t k) const;
  std::vector<FaultRule> rules_;
  int debounce_us_ = 0;
};

}  // namespace cellsight::sim
