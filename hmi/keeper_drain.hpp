// The screen's consumer of a runtime::ScanKeeper: a normal-priority thread that hands every kept scan, oldest first,
// to a handler and then frees its slot, looking every `poll` (the keeper has no bell: the loop never rings anything
// for the screen). Used by the Review store (writes entries) and the live picture (renders them).
#pragma once

#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <span>
#include <thread>

#include "base/result.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::hmi {

class KeeperDrain {
 public:
  using Handler = std::function<void(const runtime::KeptScanInfo&, std::span<const algo::ScanPoint>)>;

  KeeperDrain() = default;
  ~KeeperDrain() { stop(); }
  KeeperDrain(const KeeperDrain&) = delete;
  KeeperDrain& operator=(const KeeperDrain&) = delete;

  // Starts the thread (named `name`); a null keeper starts nothing.
  [[nodiscard]] Status start(const char* name, runtime::ScanKeeper* keeper, std::chrono::milliseconds poll,
                             Handler handler);
  void stop();  // after the scan being handled; idempotent

 private:
  void run();

  runtime::ScanKeeper* keeper_ = nullptr;
  std::chrono::milliseconds poll_{100};
  Handler handler_;
  std::mutex mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace cellsight::hmi
