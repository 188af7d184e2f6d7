// LivePreview: the live page's depth image with the decided part's outline.
#include "hmi/live_preview.hpp"

#include <filesystem>

#include "base/start_thread.hpp"
#include "drivers/log.hpp"
#include "hmi/server_impl.hpp"

namespace cellsight::hmi {
namespace {
constexpr const char* kComponent = "hmi";
constexpr auto kPoll = std::chrono::milliseconds(50);
}  // namespace

LivePreview::LivePreview(std::string models_dir, runtime::ScanKeeper* preview)
    : models_dir_(std::move(models_dir)), preview_(preview) {}

LivePreview::~LivePreview() {
  stop();
}

Status LivePreview::start() {
  if (preview_ == nullptr) return {};
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = false;
  }
  return base::start_thread(thread_, "cs-preview", [this] { run(); });
}

void LivePreview::stop() {
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void LivePreview::forget_outlines() {
  const std::lock_guard<std::mutex> lock(mutex_);
  forget_ = true;
}

void LivePreview::run() {
  for (;;) {
    const runtime::KeptScanInfo* info = nullptr;
    std::span<const algo::ScanPoint> points;
    // Only the newest matters: older previews waiting behind it are skipped.
    while (preview_->peek(info, points)) {
      render(*info, points);
      preview_->release();
    }
    std::unique_lock<std::mutex> lock(mutex_);
    if (forget_) {
      outlines_.clear();
      forget_ = false;
    }
    if (wake_.wait_for(lock, kPoll, [this] { return stopping_; })) return;
  }
}

const Outline* LivePreview::outline(const std::string& part) {
  auto it = outlines_.find(part);
  if (it == outlines_.end()) {
    Outline loaded;
    std::string error;
    const std::string path = (std::filesystem::path(models_dir_) / "templates" / (part + ".dmap")).string();
    if (!load_outline(path, loaded, error)) {
      CS_LOG_WARN(kComponent, "live picture without the outline of %s: %s", part.c_str(), error.c_str());
    }
    it = outlines_.emplace(part, std::move(loaded)).first;
  }
  return it->second.polygons.empty() ? nullptr : &it->second;
}

void LivePreview::render(const runtime::KeptScanInfo& info, std::span<const algo::ScanPoint> points) {
  DepthImage image = depth_image(points);
  const algo::Decision& d = info.decision;
  const std::string part(info.names[algo::kMaxReportedCandidates].data());
  if (d.accepted() && d.pose_valid && !part.empty()) {
    if (const Outline* o = outline(part); o != nullptr) draw_outline(image, *o, d.pose);
  }
  std::string png = encode_png(image.colour);
  const std::lock_guard<std::mutex> lock(mutex_);
  pictures_.emplace_back(info.tag.acq_id, std::move(png));
  while (pictures_.size() > kKeep) pictures_.pop_front();
  ++rendered_;
}

std::string LivePreview::png(std::uint32_t acq) const {
  const std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [id, png] : pictures_) {
    if (id == acq) return png;
  }
  return {};
}

std::uint64_t LivePreview::rendered() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  return rendered_;
}

std::vector<Route> LivePreview::routes() {
  return {{"GET", "/api/live/", Role::kNone, [this](const Request& r) {
             const std::string rest = r.uri.substr(std::string("/api/live/").size());
             const auto dot = rest.find(".png");
             if (dot == std::string::npos || dot == 0 || dot > 10 || rest.size() != dot + 4 ||
                 rest.find_first_not_of("0123456789") != dot) {
               return send_error(r.conn, 404, "no such resource: " + r.uri);
             }
             const std::string image = png(static_cast<std::uint32_t>(std::stoul(rest.substr(0, dot))));
             if (image.empty()) return send_error(r.conn, 404, "no picture of acquisition " + rest.substr(0, dot));
             return send_png(r, image);
           }}};
}

}  // namespace cellsight::hmi
