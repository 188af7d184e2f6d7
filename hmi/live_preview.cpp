// LivePreview: the live page's depth image with the decided part's outline.
#include "hmi/live_preview.hpp"

#include <filesystem>

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
  return drain_.start(
      "cs-preview", preview_, kPoll,
      [this](const runtime::KeptScanInfo& info, std::span<const algo::ScanPoint> points) { render(info, points); });
}

void LivePreview::stop() {
  drain_.stop();
}

void LivePreview::forget_outlines() {
  forget_.store(true, std::memory_order_relaxed);
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
  if (forget_.exchange(false, std::memory_order_relaxed)) outlines_.clear();  // the models changed: read again
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
