// Memo of the simulated cell's rendered frames: a pass's frames rendered once are replayed byte for byte, so a long
// soak of the production loop runs at the speed the loop processes frames rather than the speed the CPU renders them
// (`cellsight run --sim --sim-replay K`). Sim only.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "base/result.hpp"

namespace cellsight::sim {

// Slots of `frames` frames of width x height mono8 pixels, in one shared-memory mapping (memfd) allocated up front:
// in /proc/PID/status it shows as RssShmem, apart from the process's heap (RssAnon), so a soak can still see the
// heap stay flat. A frame is keyed by what the renderer's output depends on besides the pass: exposure and laser.
class FrameMemo {
 public:
  FrameMemo() = default;
  ~FrameMemo();
  FrameMemo(const FrameMemo&) = delete;
  FrameMemo& operator=(const FrameMemo&) = delete;

  [[nodiscard]] Status allocate(std::size_t slots, int frames, int width_px, int height_px);
  [[nodiscard]] bool enabled() const { return base_ != nullptr; }
  [[nodiscard]] std::size_t slots() const { return slots_; }

  // The frame's pixels when stored with this exposure and laser state, else nullptr.
  [[nodiscard]] const std::uint8_t* find(std::size_t slot, int frame, std::int32_t exposure_us, bool laser_on) const;
  // Stores a rendered frame (rows of width bytes, `stride` apart).
  void store(std::size_t slot, int frame, std::int32_t exposure_us, bool laser_on, const std::uint8_t* pixels,
             std::size_t stride);
  [[nodiscard]] std::uint64_t hits() const { return hits_; }
  [[nodiscard]] std::uint64_t stores() const { return stores_; }

 private:
  [[nodiscard]] std::size_t index(std::size_t slot, int frame) const {
    return slot * static_cast<std::size_t>(frames_) + static_cast<std::size_t>(frame);
  }
  std::uint8_t* base_ = nullptr;
  std::size_t bytes_ = 0;
  std::size_t slots_ = 0;
  int frames_ = 0;
  int width_ = 0;
  int height_ = 0;
  std::vector<std::int64_t> keys_;  // per frame: exposure_us * 2 + laser, or -1 when empty
  mutable std::uint64_t hits_ = 0;
  std::uint64_t stores_ = 0;
};

}  // namespace cellsight::sim
