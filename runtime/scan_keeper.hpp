// Scans the loop keeps for people: the passes that came out unknown (the operator's Review page) and the passes of
// a part being taught. The recognition worker copies a pass's points into a free slot after recognising it — the
// loop's scan buffer is refilled by the next pass, so the copy must happen while the worker still owns it — and a
// normal-priority consumer (the screen's writer thread) stores them on disk and frees the slot. Slots are allocated
// once, at start-up; no free slot means the scan is not kept (counted), never a wait.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

#include "algo/decision.hpp"
#include "algo/scan.hpp"

namespace cellsight::runtime {

// Why a pass is kept, told to the worker with the job (the loop knows whether it is teaching).
struct KeepTag {
  std::uint32_t acq_id = 0;
  bool teach = false;               // the loop is in teach mode: keep every pass
  std::uint16_t teach_part_id = 0;  // the PLC id being taught
};

struct KeptScanInfo {
  static constexpr std::size_t kNameBytes = 64;
  KeepTag tag;
  std::int64_t wall_ms = 0;  // CLOCK_REALTIME when it was kept
  algo::Decision decision;   // what the recogniser decided (candidates and why each was refused)
  // The class names of decision.candidates[i] (same index), and of decision.class_index at kMaxReportedCandidates.
  std::array<std::array<char, kNameBytes>, algo::kMaxReportedCandidates + 1> names{};
  std::size_t points = 0;
};

class ScanKeeper {
 public:
  // Allocates slots x max_points points (16 bytes each) now.
  ScanKeeper(std::size_t slots, std::size_t max_points);
  ScanKeeper(const ScanKeeper&) = delete;
  ScanKeeper& operator=(const ScanKeeper&) = delete;

  // ---- producer (one thread: the recognition worker) ----
  // Copies points (cut to max_points, counted) and info into the next slot; false (counted) when it is not free.
  bool keep(std::span<const algo::ScanPoint> points, const KeptScanInfo& info);
  // Every stride-th point (stride chosen so that at most max_points remain): a preview, never truncated.
  bool keep_thinned(std::span<const algo::ScanPoint> points, const KeptScanInfo& info);

  // ---- consumer (one thread) ----
  // The oldest kept scan, or false; it stays until release().
  bool peek(const KeptScanInfo*& info, std::span<const algo::ScanPoint>& points) const;
  void release();

  // ---- any thread ----
  [[nodiscard]] std::uint64_t kept() const { return head_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t dropped() const { return dropped_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t truncated() const { return truncated_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::size_t max_points() const { return max_points_; }

  // Copies `name` into a fixed field (cut to fit, always terminated).
  static void put_name(std::array<char, KeptScanInfo::kNameBytes>& field, std::string_view name);

 private:
  struct Slot {
    KeptScanInfo info;
    std::vector<algo::ScanPoint> points;  // max_points, allocated once
  };
  // Producer: the next slot when free (else counted as dropped), and making a filled one visible to the consumer.
  Slot* claim();
  void publish(Slot& slot, const KeptScanInfo& info, std::size_t points);

  std::size_t max_points_;
  std::vector<Slot> slots_;
  std::atomic<std::uint64_t> head_{0};  // slots filled (producer)
  std::atomic<std::uint64_t> tail_{0};  // slots freed (consumer)
  std::atomic<std::uint64_t> dropped_{0};
  std::atomic<std::uint64_t> truncated_{0};
};

}  // namespace cellsight::runtime
