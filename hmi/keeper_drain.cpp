// KeeperDrain: the screen's thread that empties a scan keeper.
#include "hmi/keeper_drain.hpp"

#include "base/start_thread.hpp"

namespace cellsight::hmi {

Status KeeperDrain::start(const char* name, runtime::ScanKeeper* keeper, std::chrono::milliseconds poll,
                          Handler handler) {
  if (keeper == nullptr) return {};
  keeper_ = keeper;
  poll_ = poll;
  handler_ = std::move(handler);
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = false;
  }
  return base::start_thread(thread_, name, [this] { run(); });
}

void KeeperDrain::stop() {
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void KeeperDrain::run() {
  for (;;) {
    const runtime::KeptScanInfo* info = nullptr;
    std::span<const algo::ScanPoint> points;
    while (keeper_->peek(info, points)) {
      handler_(*info, points);
      keeper_->release();
    }
    std::unique_lock<std::mutex> lock(mutex_);
    if (wake_.wait_for(lock, poll_, [this] { return stopping_; })) return;
  }
}

}  // namespace cellsight::hmi
