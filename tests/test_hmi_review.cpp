// The Review page (issue 14). Its store: scans the loop kept, written by the screen's thread as PLY + info.json +
// depth image, a bounded ring that survives a restart; checked against the scans put in and an independent reading
// of the files (the PLY parser, OpenCV's PNG decoder). Its routes and the teach session, against a real server, a
// stand-in for the loop's command path and a job runner whose "cellsight" is a shell script that records its
// arguments.
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
#include "hmi/jobs.hpp"
#include "hmi/review_api.hpp"
#include "hmi/review_store.hpp"
#include "hmi/server.hpp"
#include "hmi/users.hpp"
#include "runtime/scan_keeper.hpp"
#include "tests/free_port.hpp"
#include "tests/http_client.hpp"
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

namespace {

// The loop's command path as the screen sees it: records what was posted, takes it at once (or refuses).
class FakeCell final : public hmi::CellCommands {
 public:
  bool post(drivers::CommandCode command, std::uint32_t arg) override {
    const std::lock_guard<std::mutex> lock(mutex_);
    posted_.emplace_back(command, arg);
    if (refuse_) {
      ok_ = false;
      return true;
    }
    ok_ = true;
    if (command == drivers::CommandCode::kEnterTeach) teaching_ = static_cast<std::uint16_t>(arg);
    if (command == drivers::CommandCode::kLeaveTeach) teaching_ = 0;
    return true;
  }
  [[nodiscard]] Fate fate() const override {
    const std::lock_guard<std::mutex> lock(mutex_);
    return ok_ ? Fate::kDone : Fate::kRefused;
  }
  [[nodiscard]] std::uint16_t teaching_part_id() const override {
    const std::lock_guard<std::mutex> lock(mutex_);
    return teaching_;
  }
  std::vector<std::pair<drivers::CommandCode, std::uint32_t>> posted() const {
    const std::lock_guard<std::mutex> lock(mutex_);
    return posted_;
  }
  void refuse() {
    const std::lock_guard<std::mutex> lock(mutex_);
    refuse_ = true;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<std::pair<drivers::CommandCode, std::uint32_t>> posted_;
  bool refuse_ = false;
  bool ok_ = true;
  std::uint16_t teaching_ = 0;
};

struct ReviewScreen {
  fs::path dir = test::numbered_scratch_dir("review-api");
  fs::path args_file = dir / "teach-args.txt";
  runtime::ScanKeeper keeper{8, 20'000};
  hmi::ReviewStore store{(dir / "review").string(), 20, &keeper};
  FakeCell cell;
  // "cellsight": writes its arguments one per line; a part named "failing" fails as teach would (exit 2).
  hmi::JobRunner jobs{std::vector<std::string>{
      "/bin/sh", "-c", "printf '%s\\n' \"$@\" > '" + args_file.string() + "'; [ \"$3\" != failing ] || exit 2", "sh"}};
  hmi::ReviewApi api{store, jobs, cell};
  std::unique_ptr<hmi::HmiServer> server;
  std::map<std::string, std::string> operator_headers;

  ReviewScreen() {
    hmi::HmiParams params;
    params.port = test::free_tcp_port();
    params.users_file = (dir / "hmi-users").string();
    REQUIRE(hmi::set_user(params.users_file, "anna", hmi::Role::kOperator, "operator-pass").ok());
    auto users = hmi::load_users(params.users_file);
    REQUIRE(users.ok());
    server = std::make_unique<hmi::HmiServer>(params, *users, nullptr, [] { return json::object(); });
    server->add_routes(api.routes());
    REQUIRE(server->start().ok());
    REQUIRE(store.start().ok());
    operator_headers = test::session_headers(server->port(), "anna", "operator-pass");
  }
  ~ReviewScreen() {
    server->stop();
    store.stop();
  }
  ReviewScreen(const ReviewScreen&) = delete;
  ReviewScreen& operator=(const ReviewScreen&) = delete;

  test::Reply get(const std::string& path) const { return test::http("127.0.0.1", server->port(), "GET", path); }
  test::Reply post(const std::string& path, const json& body, bool with_session = true) const {
    return test::http("127.0.0.1", server->port(), "POST", path, body.dump(),
                      with_session ? operator_headers : std::map<std::string, std::string>{});
  }
  // Keeps `n` scans as the loop's recognition thread would; waits until they are stored.
  void keep(int n, bool teach = false, std::uint16_t part_id = 0) {
    const std::uint64_t before = store.stored();
    for (int i = 0; i < n; ++i) {
      runtime::KeptScanInfo info = unknown_info(static_cast<std::uint32_t>(100 + before + i));
      info.tag.teach = teach;
      info.tag.teach_part_id = part_id;
      REQUIRE(wait_for([&] { return keeper.keep(plate(30, 20, 0.3f, 0.0f), info); }, 5000));
    }
    REQUIRE(wait_for([&] { return store.stored() == before + n; }, 5000));
  }
  std::vector<std::uint64_t> ids() const {
    std::vector<std::uint64_t> out;
    for (const auto& e : store.list()) out.push_back(e.id);
    return out;
  }
  json job_done(std::uint64_t id) const {
    hmi::JobView v;
    REQUIRE(wait_for(
        [&] {
          v = jobs.view();
          return v.id == id && v.state != "running";
        },
        10'000));
    return hmi::to_json(v);
  }
  std::vector<std::string> teach_args() const {
    std::ifstream in(args_file);
    std::vector<std::string> lines;
    for (std::string line; std::getline(in, line);) lines.push_back(line);
    return lines;
  }
};

}  // namespace

TEST_CASE("review routes: picked scans are taught as a part by a teach job and leave the ring, the rules hold",
          "[hmi][review]") {
  ReviewScreen screen;
  screen.keep(4);
  const json listed = screen.get("/api/review").as_json();
  REQUIRE(listed["entries"].size() == 4);
  CHECK(listed["entries"][0]["code"] == "unknown part");
  CHECK(listed["entries"][0]["image"] == "/api/review/" + std::to_string(screen.ids()[0]) + "/depth.png");
  const test::Reply png = screen.get(listed["entries"][0]["image"].get<std::string>());
  CHECK(png.status == 200);
  CHECK(png.headers.at("Content-Type") == "image/png");
  CHECK(screen.get("/api/review/99999/depth.png").status == 404);
  CHECK(screen.get("/api/review/../x").status == 404);

  const std::vector<std::uint64_t> all = screen.ids();
  const json picked = {{"ids", {all[0], all[1]}}, {"name", "bracket_new"}, {"part_id", 12}};
  CHECK(screen.post("/api/review/teach", picked, false).status == 401);
  CHECK(screen.post("/api/review/discard", {{"ids", {all[3]}}}, false).status == 401);
  CHECK(screen.post("/api/teach/start", {{"name", "x"}, {"part_id", 1}, {"passes", 2}}, false).status == 401);
  CHECK(screen.post("/api/review/teach", {{"ids", {all[0]}}, {"name", ".hidden"}, {"part_id", 12}}).status == 400);
  CHECK(screen.post("/api/review/teach", {{"ids", {all[0]}}, {"name", "ok"}, {"part_id", 70000}}).status == 400);
  CHECK(screen.post("/api/review/teach", {{"ids", json::array()}, {"name", "ok"}, {"part_id", 3}}).status == 400);
  CHECK(screen.post("/api/review/teach", {{"ids", {424242}}, {"name", "ok"}, {"part_id", 3}}).status == 409);

  // Taught: the job got exactly these scans, and they leave the ring.
  const test::Reply taught = screen.post("/api/review/teach", picked);
  REQUIRE(taught.status == 200);
  const json job = screen.job_done(taught.as_json()["job"].get<std::uint64_t>());
  CHECK(job["state"] == "done");
  CHECK(screen.teach_args() == std::vector<std::string>{"teach", "--part", "bracket_new", "--id", "12",
                                                        screen.store.scan_path(all[0]),
                                                        screen.store.scan_path(all[1])});
  REQUIRE(wait_for([&] { return screen.ids().size() == 2; }, 5000));
  CHECK(screen.ids() == std::vector<std::uint64_t>{all[2], all[3]});

  // A teach that fails keeps them; discard removes them.
  const test::Reply failing =
      screen.post("/api/review/teach", {{"ids", {all[2]}}, {"name", "failing"}, {"part_id", 13}});
  REQUIRE(failing.status == 200);
  CHECK(screen.job_done(failing.as_json()["job"].get<std::uint64_t>())["state"] == "failed");
  CHECK(screen.ids().size() == 2);
  const test::Reply discarded = screen.post("/api/review/discard", {{"ids", {all[2], all[3]}}});
  CHECK(discarded.status == 200);
  CHECK(discarded.as_json()["removed"] == 2);
  CHECK(screen.ids().empty());
}

TEST_CASE(
    "teach session: ENTER_TEACH through the loop's command path, the next passes collected and taught, then "
    "LEAVE_TEACH",
    "[hmi][review]") {
  ReviewScreen screen;
  screen.keep(1);  // an unknown scan before: not part of the session
  const std::uint64_t before = screen.ids()[0];
  const test::Reply started = screen.post("/api/teach/start", {{"name", "hook_7"}, {"part_id", 7}, {"passes", 2}});
  REQUIRE(started.status == 200);
  CHECK(started.as_json()["state"] == "collecting");
  CHECK(screen.post("/api/teach/start", {{"name", "other"}, {"part_id", 8}, {"passes", 2}}).status == 409);
  REQUIRE(screen.cell.posted().size() == 1);
  CHECK(screen.cell.posted()[0] == std::pair{drivers::CommandCode::kEnterTeach, std::uint32_t{7}});
  CHECK(screen.get("/api/teach").as_json()["loop_teaching_part_id"] == 7);

  // A teach pass of another id (the PLC's own teach) is kept but not counted; two of id 7 complete the session.
  screen.keep(1, true, 9);
  CHECK(screen.get("/api/teach").as_json()["passes_kept"] == 0);
  screen.keep(2, true, 7);
  json session;
  REQUIRE(wait_for(
      [&] {
        session = screen.get("/api/teach").as_json();
        return session["state"] == "done";
      },
      10'000));
  CHECK(session["passes_kept"] == 2);
  CHECK(screen.cell.posted().back() == std::pair{drivers::CommandCode::kLeaveTeach, std::uint32_t{0}});
  const std::vector<std::string> args = screen.teach_args();
  REQUIRE(args.size() == 7);
  CHECK(args[2] == "hook_7");
  CHECK(args[4] == "7");
  // The two passes taught left the ring; the unknown one and the other id's pass stay.
  REQUIRE(wait_for([&] { return screen.ids().size() == 2; }, 5000));
  CHECK(screen.ids().back() == before);

  // The loop refusing teach mode (no keeper, or a bad id) fails the session with a clear answer.
  screen.cell.refuse();
  const test::Reply refused = screen.post("/api/teach/start", {{"name", "hook_8"}, {"part_id", 8}, {"passes", 1}});
  CHECK(refused.status == 409);
  CHECK(screen.get("/api/teach").as_json()["state"] == "failed");
}
