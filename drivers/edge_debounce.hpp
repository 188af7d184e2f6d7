// Bounce filter of one digital input (gpio.debounce_us) on the input's own clock: shared by the libgpiod backend and
// the simulated cell's part-present line, so a bouncing photo-eye reaches the production loop the same way from both.
#pragma once

#include <cstdint>

namespace cellsight::drivers {

// The first edge after a quiet debounce window is delivered at once; raw edges closer than the window to the last
// delivered edge are bounces. When the bounces leave the pin at the other level (a pulse shorter than the window),
// that level is delivered once the window has passed (settle()), stamped with the time the pin got there.
// Pure and allocation-free; one thread (the caller of wait_edge) owns it.
class EdgeDebounce {
 public:
  EdgeDebounce() = default;  // no window: every change is delivered
  explicit EdgeDebounce(std::int64_t debounce_ns) : debounce_ns_(debounce_ns) {}

  // The pin reads `level` now; nothing delivered yet, so the next change is delivered at once.
  void reset(bool level, std::int64_t now_ns) {
    state_ = raw_ = level;
    raw_since_ns_ = now_ns;
    have_accepted_ = false;
    accepted_ns_ = 0;
  }

  // A raw edge of the pin to `level` at `timestamp_ns`: true when it is delivered (the debounced state changes),
  // false for a bounce.
  [[nodiscard]] bool on_edge(bool level, std::int64_t timestamp_ns) {
    raw_ = level;
    raw_since_ns_ = timestamp_ns;
    if (level == state_ || (have_accepted_ && timestamp_ns - accepted_ns_ < debounce_ns_)) return false;
    deliver(level, timestamp_ns);
    return true;
  }

  // Bounces left the pin at the other level than the one delivered.
  [[nodiscard]] bool unsettled() const { return raw_ != state_; }
  // From when that level is the truth.
  [[nodiscard]] std::int64_t settle_at_ns() const { return accepted_ns_ + debounce_ns_; }
  // Delivers the level the pin rests at (when unsettled() and settle_at_ns() has come); returns its timestamp.
  std::int64_t settle() {
    deliver(raw_, raw_since_ns_);
    return raw_since_ns_;
  }

  [[nodiscard]] bool state() const { return state_; }

 private:
  void deliver(bool level, std::int64_t timestamp_ns) {
    state_ = level;
    have_accepted_ = true;
    accepted_ns_ = timestamp_ns;
  }

  std::int64_t debounce_ns_ = 0;
  bool state_ = false;             // debounced, active-high logic
  bool raw_ = false;               // level of the last raw edge
  std::int64_t raw_since_ns_ = 0;  // when the pin reached raw_
  bool have_accepted_ = false;
  std::int64_t accepted_ns_ = 0;  // time of the last delivered edge
};

}  // namespace cellsight::drivers
