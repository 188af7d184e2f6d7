// ScanKeeper: a single-producer / single-consumer ring of large slots (the points are copied in place, so the
// records are not moved through base::SpscRing, which copies whole records).
#include "runtime/scan_keeper.hpp"

#include <algorithm>
#include <cstring>

namespace cellsight::runtime {

ScanKeeper::ScanKeeper(std::size_t slots, std::size_t max_points)
    : max_points_(max_points), slots_(std::max<std::size_t>(slots, 1)) {
  for (Slot& slot : slots_) slot.points.resize(max_points_);
}

ScanKeeper::Slot* ScanKeeper::claim() {
  const std::uint64_t head = head_.load(std::memory_order_relaxed);
  if (head - tail_.load(std::memory_order_acquire) >= slots_.size()) {
    dropped_.fetch_add(1, std::memory_order_relaxed);
    return nullptr;
  }
  return &slots_[head % slots_.size()];
}

void ScanKeeper::publish(Slot& slot, const KeptScanInfo& info, std::size_t points) {
  slot.info = info;
  slot.info.points = points;
  head_.store(head_.load(std::memory_order_relaxed) + 1, std::memory_order_release);
}

bool ScanKeeper::keep(std::span<const algo::ScanPoint> points, const KeptScanInfo& info) {
  Slot* slot = claim();
  if (slot == nullptr) return false;
  const std::size_t n = std::min(points.size(), max_points_);
  if (n < points.size()) truncated_.fetch_add(1, std::memory_order_relaxed);
  if (n > 0) std::memcpy(slot->points.data(), points.data(), n * sizeof(algo::ScanPoint));
  publish(*slot, info, n);
  return true;
}

bool ScanKeeper::keep_thinned(std::span<const algo::ScanPoint> points, const KeptScanInfo& info) {
  Slot* slot = claim();
  if (slot == nullptr) return false;
  const std::size_t stride =
      max_points_ == 0 ? 1 : std::max<std::size_t>(1, (points.size() + max_points_ - 1) / max_points_);
  std::size_t n = 0;
  for (std::size_t i = 0; i < points.size() && n < max_points_; i += stride) slot->points[n++] = points[i];
  publish(*slot, info, n);
  return true;
}

bool ScanKeeper::peek(const KeptScanInfo*& info, std::span<const algo::ScanPoint>& points) const {
  const std::uint64_t tail = tail_.load(std::memory_order_relaxed);
  if (tail == head_.load(std::memory_order_acquire)) return false;
  const Slot& slot = slots_[tail % slots_.size()];
  info = &slot.info;
  points = std::span<const algo::ScanPoint>(slot.points.data(), slot.info.points);
  return true;
}

void ScanKeeper::release() {
  const std::uint64_t tail = tail_.load(std::memory_order_relaxed);
  if (tail != head_.load(std::memory_order_acquire)) tail_.store(tail + 1, std::memory_order_release);
}

void ScanKeeper::put_name(std::array<char, KeptScanInfo::kNameBytes>& field, std::string_view name) {
  const std::size_t n = std::min(name.size(), field.size() - 1);
  if (n > 0) std::memcpy(field.data(), name.data(), n);  // an empty view may have no data pointer at all
  field[n] = '\0';
}

}  // namespace cellsight::runtime
