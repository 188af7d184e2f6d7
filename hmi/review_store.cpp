// ReviewStore: the writer thread, the ring on disk and the depth image.
#include "hmi/review_store.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "base/atomic_file.hpp"
#include "base/file_read.hpp"
#include "drivers/log.hpp"
#include "formats/ply.hpp"
#include "hmi/depth_image.hpp"
#include "runtime/plc_mapping.hpp"

namespace cellsight::hmi {
namespace {

namespace fs = std::filesystem;
constexpr const char* kComponent = "hmi";
constexpr std::size_t kMaxInfoBytes = 1 << 20;          // an entry's info.json is ~1-2 KB
constexpr auto kPoll = std::chrono::milliseconds(100);  // the keeper has no bell: the writer looks this often

nlohmann::json finite_or_null(double v, double scale = 1.0) {
  return std::isfinite(v) ? nlohmann::json(v * scale) : nlohmann::json(nullptr);
}

std::string name_of(const std::array<char, runtime::KeptScanInfo::kNameBytes>& field) {
  return std::string(field.data());
}

bool is_id(const std::string& text) {
  return !text.empty() && text.size() <= 12 &&
         std::all_of(text.begin(), text.end(), [](char c) { return c >= '0' && c <= '9'; });
}

std::string folder_name(std::uint64_t id) {
  char text[24];
  std::snprintf(text, sizeof text, "%08llu", static_cast<unsigned long long>(id));
  return text;
}

}  // namespace

ReviewStore::ReviewStore(std::string dir, int keep, runtime::ScanKeeper* keeper)
    : dir_(std::move(dir)), keep_(std::max(1, keep)), keeper_(keeper) {
  std::error_code ec;
  fs::create_directories(dir_, ec);
  // Entries left by an earlier run: kept (the operator may still teach them), read back in id order.
  for (const auto& item : fs::directory_iterator(dir_, ec)) {
    const std::string name = item.path().filename().string();
    if (!item.is_directory() || !is_id(name)) continue;
    const std::uint64_t id = std::stoull(name);
    next_id_ = std::max(next_id_, id + 1);
    auto text = base::read_file((item.path() / "info.json").string(), kMaxInfoBytes);
    nlohmann::json info =
        text ? nlohmann::json::parse(*text, nullptr, false) : nlohmann::json(nlohmann::json::value_t::discarded);
    if (info.is_discarded() || !fs::exists(item.path() / "scan.ply")) {
      fs::remove_all(item.path(), ec);  // half-written when the cell stopped: the loop had moved on anyway
      continue;
    }
    ReviewEntry entry{id, std::move(info)};
    entries_.push_back(std::move(entry));
  }
  std::sort(entries_.begin(), entries_.end(), [](const auto& a, const auto& b) { return a.id < b.id; });
}

ReviewStore::~ReviewStore() {
  stop();
}

void ReviewStore::set_on_stored(std::function<void(const ReviewEntry&)> on_stored) {
  on_stored_ = std::move(on_stored);
}

Status ReviewStore::start() {
  return drain_.start(
      "cs-review", keeper_, kPoll,
      [this](const runtime::KeptScanInfo& kept, std::span<const algo::ScanPoint> points) { store(kept, points); });
}

void ReviewStore::stop() {
  drain_.stop();
}

void ReviewStore::store(const runtime::KeptScanInfo& kept, std::span<const algo::ScanPoint> points) {
  std::uint64_t id = 0;
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    id = next_id_++;
  }
  const fs::path folder = fs::path(dir_) / folder_name(id);
  std::error_code ec;
  fs::create_directories(folder, ec);
  ReviewEntry entry{id, info_json(id, kept)};
  // The scan first and the info last: an entry without info.json is not listed (a crash in between leaves a folder
  // that the next start ignores and prune() removes).
  Status ok = base::write_file_atomic((folder / "scan.ply").string(), formats::write_ply_binary(points));
  if (ok) {
    const std::string png = encode_png(depth_image(points).colour);
    if (!png.empty()) ok = base::write_file_atomic((folder / "depth.png").string(), png);
  }
  if (ok) ok = base::write_file_atomic((folder / "info.json").string(), entry.info.dump(1));
  if (!ok) {
    failed_.fetch_add(1, std::memory_order_relaxed);
    CS_LOG_ERROR(kComponent, "review: cannot keep acq %u: %s", kept.tag.acq_id, ok.error().message.c_str());
    fs::remove_all(folder, ec);
    return;
  }
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    entries_.push_back(entry);
  }
  stored_.fetch_add(1, std::memory_order_relaxed);
  prune();
  if (on_stored_) on_stored_(entry);
}

void ReviewStore::prune() {
  std::vector<std::uint64_t> old;
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    for (std::size_t i = 0; i + static_cast<std::size_t>(keep_) < entries_.size(); ++i) old.push_back(entries_[i].id);
  }
  (void)remove(old);
}

std::vector<ReviewEntry> ReviewStore::list() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  return {entries_.rbegin(), entries_.rend()};
}

std::optional<ReviewEntry> ReviewStore::find(std::uint64_t id) const {
  const std::lock_guard<std::mutex> lock(mutex_);
  for (const ReviewEntry& e : entries_) {
    if (e.id == id) return e;
  }
  return std::nullopt;
}

std::string ReviewStore::scan_path(std::uint64_t id) const {
  return (fs::path(dir_) / folder_name(id) / "scan.ply").string();
}

std::string ReviewStore::image_path(std::uint64_t id) const {
  return (fs::path(dir_) / folder_name(id) / "depth.png").string();
}

std::size_t ReviewStore::remove(const std::vector<std::uint64_t>& ids) {
  std::size_t removed = 0;
  const std::lock_guard<std::mutex> lock(mutex_);
  for (const std::uint64_t id : ids) {
    const auto it = std::find_if(entries_.begin(), entries_.end(), [id](const auto& e) { return e.id == id; });
    if (it == entries_.end()) continue;
    entries_.erase(it);
    std::error_code ec;
    fs::remove_all(fs::path(dir_) / folder_name(id), ec);
    ++removed;
  }
  return removed;
}

nlohmann::json ReviewStore::info_json(std::uint64_t id, const runtime::KeptScanInfo& kept) {
  const algo::Decision& d = kept.decision;
  nlohmann::json candidates = nlohmann::json::array();
  for (int i = 0; i < d.candidate_count && i < algo::kMaxReportedCandidates; ++i) {
    const algo::CandidateOutcome& c = d.candidates[static_cast<std::size_t>(i)];
    candidates.push_back({{"name", name_of(kept.names[static_cast<std::size_t>(i)])},
                          {"probability", c.probability},
                          {"verified", c.verified},
                          {"passed", c.passed},
                          {"rejected_by", std::string(algo::to_string(c.rejected_by))},
                          {"value", finite_or_null(c.value)},
                          {"limit", finite_or_null(c.limit)},
                          {"pm_error_mm", finite_or_null(c.pm_error, 1e3)},
                          {"missing_area_mm2", finite_or_null(c.missing_area_m2, 1e6)},
                          {"extra_area_mm2", finite_or_null(c.extra_area_m2, 1e6)},
                          {"coverage", finite_or_null(c.coverage)},
                          {"outliers", finite_or_null(c.outliers)}});
  }
  const std::string chosen = name_of(kept.names[algo::kMaxReportedCandidates]);
  return {{"id", id},
          {"kind", kept.tag.teach ? "teach" : "unknown"},
          {"teach_part_id", kept.tag.teach ? nlohmann::json(kept.tag.teach_part_id) : nlohmann::json(nullptr)},
          {"acq_id", kept.tag.acq_id},
          {"time_ms", kept.wall_ms},
          {"points", kept.points},
          {"source", std::string(algo::to_string(d.source))},
          {"code", drivers::to_string(runtime::to_plc_result(d, 0, 0, 0.0).code)},  // what the PLC was given
          {"part", d.accepted() && !chosen.empty() ? nlohmann::json(chosen) : nlohmann::json(nullptr)},
          {"reason", d.unknown_reason == algo::RejectReason::kNone
                         ? nlohmann::json(nullptr)
                         : nlohmann::json(std::string(algo::to_string(d.unknown_reason)))},
          {"probability", d.probability},
          {"candidates", candidates}};
}

}  // namespace cellsight::hmi
