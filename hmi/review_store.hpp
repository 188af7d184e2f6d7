// The scans the production loop kept (runtime::ScanKeeper), on disk for people: every unknown pass and every pass of
// a part being taught becomes an entry of the Review page — <dir>/<id>/scan.ply (binary PLY, what `teach` takes),
// info.json (what was decided, the candidates tried and why each was refused) and depth.png (a depth image for the
// page). A bounded ring: beyond `keep` entries the oldest are removed. The writer is a normal-priority thread; the
// loop never waits for it (a full keeper drops the scan and counts it).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "base/result.hpp"
#include "hmi/keeper_drain.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::hmi {

struct ReviewEntry {
  std::uint64_t id = 0;
  nlohmann::json info;  // info.json as written
};

class ReviewStore {
 public:
  // dir is created when missing; ids continue after the highest one found there.
  ReviewStore(std::string dir, int keep, runtime::ScanKeeper* keeper);
  ~ReviewStore();  // stop()
  ReviewStore(const ReviewStore&) = delete;
  ReviewStore& operator=(const ReviewStore&) = delete;

  [[nodiscard]] Status start();  // the writer thread
  void stop();

  // Called on the writer thread after each entry is stored (the teach session counts its passes with it).
  void set_on_stored(std::function<void(const ReviewEntry&)> on_stored);

  // ---- any thread ----
  [[nodiscard]] std::vector<ReviewEntry> list() const;  // newest first
  [[nodiscard]] std::optional<ReviewEntry> find(std::uint64_t id) const;
  [[nodiscard]] std::string scan_path(std::uint64_t id) const;
  [[nodiscard]] std::string image_path(std::uint64_t id) const;
  // Removes entries (their folders); unknown ids are ignored. Returns how many were removed.
  std::size_t remove(const std::vector<std::uint64_t>& ids);
  [[nodiscard]] std::uint64_t stored() const { return stored_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t failed() const { return failed_.load(std::memory_order_relaxed); }
  [[nodiscard]] const std::string& dir() const { return dir_; }

  // The entry's info.json for a kept scan (public for tests).
  [[nodiscard]] static nlohmann::json info_json(std::uint64_t id, const runtime::KeptScanInfo& kept);

 private:
  void store(const runtime::KeptScanInfo& kept, std::span<const algo::ScanPoint> points);
  void prune();

  std::string dir_;
  int keep_;
  runtime::ScanKeeper* keeper_;
  std::function<void(const ReviewEntry&)> on_stored_;
  mutable std::mutex mutex_;          // entries_ and the folders (the writer and the routes)
  std::vector<ReviewEntry> entries_;  // oldest first
  std::uint64_t next_id_ = 1;
  KeeperDrain drain_;  // the writer thread
  std::atomic<std::uint64_t> stored_{0};
  std::atomic<std::uint64_t> failed_{0};
};

}  // namespace cellsight::hmi
