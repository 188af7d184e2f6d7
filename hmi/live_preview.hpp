// The live page's picture of each part: the loop's recognition thread hands a thinned copy of every recognised pass
// to a preview keeper (runtime::ScanKeeper::keep_thinned, never a wait); this class's thread renders it as a depth
// image with the decided part's outline drawn at the estimated pose, PNG-encoded here (never on the loop's threads),
// and keeps the last few for GET /api/live/ACQ.png.
#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "base/result.hpp"
#include "hmi/depth_image.hpp"
#include "hmi/keeper_drain.hpp"
#include "hmi/routes.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::hmi {

class LivePreview {
 public:
  static constexpr std::size_t kKeep = 16;  // pictures kept (newest)

  // preview: borrowed (the loop's preview keeper); templates are read from <models_dir>/templates/NAME.dmap.
  LivePreview(std::string models_dir, runtime::ScanKeeper* preview);
  ~LivePreview();  // stop()
  LivePreview(const LivePreview&) = delete;
  LivePreview& operator=(const LivePreview&) = delete;

  [[nodiscard]] Status start();
  void stop();
  // After a retrain or delete the outlines are read again.
  void forget_outlines();

  // The PNG of acquisition acq (empty when not, or no longer, kept).
  [[nodiscard]] std::string png(std::uint32_t acq) const;
  [[nodiscard]] std::vector<Route> routes();
  [[nodiscard]] std::uint64_t rendered() const;

 private:
  void render(const runtime::KeptScanInfo& info, std::span<const algo::ScanPoint> points);
  const Outline* outline(const std::string& part);

  std::string models_dir_;
  runtime::ScanKeeper* preview_;
  std::map<std::string, Outline> outlines_;  // the drain thread's; an empty one: the template could not be read
  std::atomic<bool> forget_{false};          // forget_outlines() -> the drain thread
  mutable std::mutex mutex_;
  std::deque<std::pair<std::uint32_t, std::string>> pictures_;
  std::uint64_t rendered_ = 0;
  KeeperDrain drain_;
};

}  // namespace cellsight::hmi
