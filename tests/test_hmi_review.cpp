// The Review page's store (issue 14): scans the loop kept, written by the screen's thread as PLY + info.json +
// depth image, a bounded ring that survives a restart; checked against the scans put in and an independent reading
// of the files (the PLY parser, OpenCV's PNG decoder).
#include <catch2/catch.hpp>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "formats/ply.hpp"
#include "hmi/review_store.hpp"
#include "runtime/scan_keeper.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

// A plate of w x h mm at 1 mm pitch, depth rising left to right from z0 by `slope` per mm.
std::vector<algo::ScanPoint> plate(int w_mm, int h_mm, float z0, float slope) {
  std::vector<algo::ScanPoint> points;
  for (int y = 0; y < h_mm; ++y) {
    for (int x = 0; x < w_mm; ++x) {
      points.push_back({0.1f + x * 1e-3f, -0.05f + y * 1e-3f, z0 + slope * x * 1e-3f, static_cast<std::uint16_t>(x),
                        static_cast<std::uint16_t>(y)});
    }
  }
  return points;
}

runtime::KeptScanInfo unknown_info(std::uint32_t acq) {
  runtime::KeptScanInfo info;
  info.tag.acq_id = acq;
  info.wall_ms = 1'700'000'000'000 + acq;
  info.decision.source = algo::DecisionSource::kUnknown;
  info.decision.unknown_reason = algo::RejectReason::kMissingArea;
  info.decision.probability = 0.41;
  info.decision.candidate_count = 2;
  auto& c0 = info.decision.candidates[0];
  c0.class_index = 1;
  c0.probability = 0.41;
  c0.verified = true;
  c0.rejected_by = algo::RejectReason::kMissingArea;
  c0.value = 0.000694;
  c0.limit = 0.000200;
  c0.missing_area_m2 = 0.000694;
  auto& c1 = info.decision.candidates[1];
  c1.class_index = 0;
  c1.probability = 0.22;
  c1.rejected_by = algo::RejectReason::kNotVerified;
  runtime::ScanKeeper::put_name(info.names[0], "bracket_b");
  runtime::ScanKeeper::put_name(info.names[1], "bracket_a");
  return info;
}

template <class Pred>
bool wait_for(Pred done, int timeout_ms) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  while (!done()) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

std::string read_all(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace

TEST_CASE("review: a kept scan becomes an entry with its points, what was decided and a depth image", "[hmi][review]") {
  const fs::path dir = test::scratch_dir("review-store") / "review";
  runtime::ScanKeeper keeper(4, 100'000);
  hmi::ReviewStore store(dir.string(), 10, &keeper);
  std::vector<std::uint64_t> stored_ids;
  store.set_on_stored([&](const hmi::ReviewEntry& e) { stored_ids.push_back(e.id); });
  REQUIRE(store.start().ok());

  const auto points = plate(200, 120, 0.30f, 0.1f);
  REQUIRE(keeper.keep(points, unknown_info(17)));
  REQUIRE(wait_for([&] { return store.stored() == 1; }, 5000));
  const auto entries = store.list();
  REQUIRE(entries.size() == 1);
  const std::uint64_t id = entries[0].id;
  CHECK(stored_ids == std::vector<std::uint64_t>{id});

  // The scan, read back with the PLY parser: every point, as put in.
  const auto parsed = formats::parse_ply(read_all(store.scan_path(id)));
  REQUIRE(parsed.ok());
  REQUIRE(parsed->size() == points.size());
  for (std::size_t i = 0; i < points.size(); i += 997) {
    CHECK((*parsed)[i].x == points[i].x);
    CHECK((*parsed)[i].z == points[i].z);
  }
  // What was decided, with the candidates by name and why each was refused.
  const json& info = entries[0].info;
  CHECK(info["kind"] == "unknown");
  CHECK(info["code"] == "unknown part");
  CHECK(info["acq_id"] == 17);
  CHECK(info["points"] == points.size());
  CHECK(info["reason"] == "missing_area");
  CHECK(info["part"].is_null());
  REQUIRE(info["candidates"].size() == 2);
  CHECK(info["candidates"][0]["name"] == "bracket_b");
  CHECK(info["candidates"][0]["rejected_by"] == "missing_area");
  CHECK(info["candidates"][0]["missing_area_mm2"].get<double>() == Approx(694.0));
  CHECK(info["candidates"][0]["limit"].get<double>() == Approx(0.0002));
  CHECK(info["candidates"][1]["name"] == "bracket_a");
  CHECK(info["candidates"][1]["verified"] == false);
  CHECK(info["candidates"][1]["value"].is_null());
  CHECK(json::parse(read_all(dir / "00000001" / "info.json")) == info);

  // The depth image: 1 px per mm over the plate's 200 x 120 mm, darker (lower colour-map index) at low depth.
  const std::string png = read_all(store.image_path(id));
  const cv::Mat image = cv::imdecode(std::vector<std::uint8_t>(png.begin(), png.end()), cv::IMREAD_COLOR);
  REQUIRE(!image.empty());
  CHECK(std::abs(image.cols - 200) <= 1);
  CHECK(std::abs(image.rows - 120) <= 1);
  const cv::Vec3b left = image.at<cv::Vec3b>(60, 5), right = image.at<cv::Vec3b>(60, 195);
  CHECK(left != right);
  CHECK(left != cv::Vec3b(0, 0, 0));
  store.stop();
}

TEST_CASE("review: the ring keeps the newest entries, survives a restart and continues its numbers", "[hmi][review]") {
  const fs::path dir = test::scratch_dir("review-ring") / "review";
  const auto points = plate(40, 30, 0.3f, 0.0f);
  {
    runtime::ScanKeeper keeper(8, 10'000);
    hmi::ReviewStore store(dir.string(), 3, &keeper);
    REQUIRE(store.start().ok());
    for (std::uint32_t acq = 1; acq <= 5; ++acq) {
      runtime::KeptScanInfo info = unknown_info(acq);
      if (acq == 5) {
        info.tag.teach = true;
        info.tag.teach_part_id = 42;
      }
      REQUIRE(wait_for([&] { return keeper.keep(points, info); }, 5000));
    }
    REQUIRE(wait_for([&] { return store.stored() == 5; }, 5000));
    const auto entries = store.list();
    REQUIRE(entries.size() == 3);
    CHECK(entries[0].info["acq_id"] == 5);  // newest first
    CHECK(entries[0].info["kind"] == "teach");
    CHECK(entries[0].info["teach_part_id"] == 42);
    CHECK(entries[2].info["acq_id"] == 3);
    CHECK_FALSE(fs::exists(dir / "00000001"));
    CHECK_FALSE(fs::exists(dir / "00000002"));
    CHECK(store.remove({entries[1].id, 999}) == 1);
    CHECK_FALSE(fs::exists(dir / "00000004"));
  }
  // A half-written entry (no info.json) is not listed, and removed.
  fs::create_directories(dir / "00000009");
  runtime::ScanKeeper keeper(2, 10'000);
  hmi::ReviewStore store(dir.string(), 3, &keeper);
  auto entries = store.list();
  CHECK_FALSE(fs::exists(dir / "00000009"));  // removed
  REQUIRE(entries.size() == 2);
  CHECK(entries[0].id == 5);
  CHECK(entries[1].id == 3);
  REQUIRE(store.start().ok());
  REQUIRE(keeper.keep(points, unknown_info(6)));
  REQUIRE(wait_for([&] { return store.stored() == 1; }, 5000));
  entries = store.list();
  CHECK(entries[0].id == 10);  // after the highest folder seen
  store.stop();
}
