// Parsing and scheduling of the simulated cell's injected faults.
#include "drivers/sim/sim_faults.hpp"

#include <algorithm>
#include <charconv>

namespace cellsight::sim {
namespace {

constexpr int kStallTimeoutFactor = 2;    // a stall lasts twice the camera timeout: the loop must give up the pass
constexpr int kHiccupTimeoutDivisor = 4;  // a hiccup a quarter of it: the loop must wait it out
constexpr int kGlitchMs = 300;
constexpr int kChatterPairs = 3;
constexpr int kMaxValue = 600'000;
// Frame of pass k where a stall or glitch starts: a stride prime to the usual 296 frames walks every frame.
constexpr std::uint64_t kFrameStride = 97;

struct KindName {
  FaultKind kind;
  std::string_view name;
};
constexpr KindName kKinds[] = {{FaultKind::kCameraStall, "camera_stall"},
                               {FaultKind::kCameraHiccup, "camera_hiccup"},
                               {FaultKind::kEncoderGlitch, "encoder_glitch"},
                               {FaultKind::kChatter, "chatter"}};

bool parse_number(std::string_view text, std::uint64_t& out) {
  if (text.empty()) return false;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), out);
  return ec == std::errc() && end == text.data() + text.size();
}

}  // namespace

std::string_view to_string(FaultKind kind) {
  for (const KindName& k : kKinds) {
    if (k.kind == kind) return k.name;
  }
  return "invalid";
}

Expected<FaultPlan> FaultPlan::parse(std::string_view spec, const FaultDefaults& defaults) {
  FaultPlan plan;
  plan.debounce_us_ = defaults.debounce_us;
  std::size_t from = 0;
  while (from < spec.size()) {
    const std::size_t comma = std::min(spec.find(',', from), spec.size());
    const std::string_view item = spec.substr(from, comma - from);
    from = comma + 1;
    if (item.empty()) continue;
    const std::string bad = "--sim-faults '" + std::string(item) + "': ";
    const std::size_t at = item.find('@');
    if (at == std::string_view::npos) return make_error(bad + "expected KIND@EVERY[/VALUE], e.g. camera_stall@50");
    const std::string_view name = item.substr(0, at);
    const auto* known =
        std::find_if(std::begin(kKinds), std::end(kKinds), [&](const KindName& k) { return k.name == name; });
    if (known == std::end(kKinds)) {
      return make_error(bad + "unknown kind; known: camera_stall, camera_hiccup, encoder_glitch, chatter");
    }
    FaultRule rule;
    rule.kind = known->kind;
    const std::string_view rest = item.substr(at + 1);
    const std::size_t slash = rest.find('/');
    if (!parse_number(rest.substr(0, slash), rule.every) || rule.every == 0) {
      return make_error(bad + "EVERY must be a whole number >= 1 (every EVERY-th pass)");
    }
    switch (rule.kind) {
      case FaultKind::kCameraStall: rule.value = kStallTimeoutFactor * defaults.camera_timeout_ms; break;
      case FaultKind::kCameraHiccup:
        rule.value = std::max(1, defaults.camera_timeout_ms / kHiccupTimeoutDivisor);
        break;
      case FaultKind::kEncoderGlitch: rule.value = kGlitchMs; break;
      case FaultKind::kChatter: rule.value = kChatterPairs; break;
    }
    if (slash != std::string_view::npos) {
      std::uint64_t value = 0;
      if (!parse_number(rest.substr(slash + 1), value) || value == 0 || value > kMaxValue) {
        return make_error(bad + "VALUE must be a whole number from 1 to " + std::to_string(kMaxValue));
      }
      rule.value = static_cast<int>(value);
    }
    plan.rules_.push_back(rule);
  }
  return plan;
}

const FaultRule* FaultPlan::rule_of(std::uint64_t k) const {
  for (const FaultRule& rule : rules_) {
    if (k % rule.every == rule.every - 1) return &rule;
  }
  return nullptr;
}

std::string_view FaultPlan::kind_of(std::uint64_t k) const {
  const FaultRule* rule = rule_of(k);
  return rule == nullptr ? std::string_view() : to_string(rule->kind);
}

PassFaults FaultPlan::for_pass(std::uint64_t k, int frame_count) const {
  PassFaults f;
  const FaultRule* rule = rule_of(k);
  if (rule == nullptr || frame_count <= 0) return f;
  const int frame = static_cast<int>((k / rule->every * kFrameStride) % static_cast<std::uint64_t>(frame_count));
  switch (rule->kind) {
    case FaultKind::kCameraStall:
    case FaultKind::kCameraHiccup:
      f.camera_stall_frame = frame;
      f.camera_stall_ms = rule->value;
      break;
    case FaultKind::kEncoderGlitch:
      f.encoder_glitch_frame = frame;
      f.encoder_glitch_ms = rule->value;
      break;
    case FaultKind::kChatter:
      f.bounce_pairs = rule->value;
      // The whole burst inside the debounce window (which is what a debounce is configured for).
      f.bounce_spacing_us = std::max(1, debounce_us_ / (2 * rule->value + 2));
      break;
  }
  return f;
}

}  // namespace cellsight::sim
