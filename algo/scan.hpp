// One part's points in the carrier frame, in a buffer of fixed capacity (allocated once, reused every pass).
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace cellsight::algo {

struct ScanPoint {
  float x, y, z;        // carrier frame, metres
  std::uint16_t frame;  // profile index within the pass
  std::uint16_t row;    // image row it came from
};

// A point with all three coordinates finite (dropouts and invalid triangulations are NaN).
[[nodiscard]] inline bool finite_point(const ScanPoint& p) {
  return std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z);
}

class ScanBuffer {
 public:
  ScanBuffer() = default;
  // Start-up only: allocates.
  explicit ScanBuffer(std::size_t capacity) { points_.resize(capacity); }

  void clear() {
    size_ = 0;
    dropped_ = 0;
  }
  // False (and counted) when full: the pass keeps what fits instead of allocating.
  bool push(const ScanPoint& p) {
    if (size_ == points_.size()) {
      ++dropped_;
      return false;
    }
    points_[size_++] = p;
    return true;
  }
  // Drops the points pushed after the buffer held `size` points.
  void truncate(std::size_t size) {
    if (size < size_) size_ = size;
  }
  // Keeps the points for which keep(p) is true, in order; returns how many were removed.
  template <class Keep>
  std::size_t filter(Keep keep) {
    std::size_t out = 0;
    for (std::size_t i = 0; i < size_; ++i) {
      if (keep(points_[i])) points_[out++] = points_[i];
    }
    const std::size_t removed = size_ - out;
    size_ = out;
    return removed;
  }

  [[nodiscard]] std::span<const ScanPoint> points() const { return {points_.data(), size_}; }
  [[nodiscard]] std::size_t size() const { return size_; }
  [[nodiscard]] std::size_t capacity() const { return points_.size(); }
  [[nodiscard]] std::size_t dropped() const { return dropped_; }

 private:
  std::vector<ScanPoint> points_;
  std::size_t size_ = 0;
  std::size_t dropped_ = 0;
};

}  // namespace cellsight::algo
