// The Parts and Debug pages (issue 14): the job runner against real child processes (a shell through its command
// seam), and the routes against a real server, a real model database taught by the executable and the jobs it runs.
#include <sys/stat.h>
#include <sys/wait.h>

#include <atomic>
#include <catch2/catch.hpp>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <string>
#include <thread>

#include "app/recognition.hpp"
#include "formats/manifest.hpp"
#include "formats/template_file.hpp"
#include "hmi/jobs.hpp"
#include "hmi/parts_api.hpp"
#include "hmi/server.hpp"
#include "tests/free_port.hpp"
#include "tests/http_client.hpp"
#include "tests/small_cell.hpp"

using namespace cellsight;
using nlohmann::json;
using test::http;
using test::Reply;
namespace fs = std::filesystem;

namespace {

using Clock = std::chrono::steady_clock;

// A runner whose jobs are `/bin/sh -c SCRIPT sh ARGS...`.
std::unique_ptr<hmi::JobRunner> shell_runner(const std::string& script) {
  return std::make_unique<hmi::JobRunner>(std::vector<std::string>{"/bin/sh", "-c", script, "sh"});
}

// Polls until `done` holds or `limit` passes; the last view.
template <class Done>
hmi::JobView wait_for(const hmi::JobRunner& runner, Done done, std::chrono::seconds limit = std::chrono::seconds(10)) {
  const auto until = Clock::now() + limit;
  hmi::JobView v = runner.view();
  while (!done(v) && Clock::now() < until) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    v = runner.view();
  }
  return v;
}

bool ended(const hmi::JobView& v) {
  return v.state != "running";
}

// The pid the script printed first ("echo $$"), and whether that process is gone (reaped: no zombie left).
bool process_gone(const hmi::JobView& v) {
  REQUIRE_FALSE(v.log_tail.empty());
  const pid_t pid = std::stoi(v.log_tail.front());
  return ::kill(pid, 0) == -1 && errno == ESRCH;
}

}  // namespace

TEST_CASE("jobs: a child's progress lines move the bar, its JSON lines are the result, and it ends reaped",
          "[hmi][jobs]") {
  const auto owned = shell_runner(
      "echo $$; echo 'progress: 0.25 first quarter'; echo '{\"scan\": \"a\", \"class\": \"plate\"}'; "
      "echo 'to stderr' >&2; read -r line < \"$1\"; echo '{\"scan\": \"b\"}'; exit 0");
  hmi::JobRunner& runner = *owned;
  const auto fifo = test::scratch_path("jobs-fifo");
  REQUIRE(::mkfifo(fifo.c_str(), 0600) == 0);
  REQUIRE(runner.start(hmi::JobKind::kClassify, {fifo.string()}, "two scans").ok());
  // While it waits on the fifo: running, the progress parsed, the line not in the tail.
  hmi::JobView v = wait_for(runner, [](const hmi::JobView& j) { return j.progress_text == "first quarter"; });
  CHECK(v.state == "running");
  CHECK(v.progress == Approx(0.25));
  CHECK(runner.busy());
  // One job at a time.
  const auto second = runner.start(hmi::JobKind::kTrain, {}, "another");
  REQUIRE_FALSE(second.ok());
  CHECK(second.error().message.find("two scans") != std::string::npos);
  std::ofstream(fifo) << "go\n";
  v = wait_for(runner, ended);
  CHECK(v.state == "done");
  CHECK(v.exit_code == 0);
  CHECK(v.progress == 1.0);
  CHECK(v.title == "two scans");
  CHECK(v.ended_ms >= v.started_ms);
  REQUIRE(v.result.is_array());
  REQUIRE(v.result.size() == 2);
  CHECK(v.result[0]["class"] == "plate");
  CHECK(v.result[1]["scan"] == "b");
  const std::set<std::string> tail(v.log_tail.begin(), v.log_tail.end());
  CHECK(tail.count("to stderr") == 1);
  CHECK(tail.count("progress: 0.25 first quarter") == 0);
  CHECK(process_gone(v));
}

TEST_CASE("jobs: the tail keeps the last lines, each cut to a bounded length", "[hmi][jobs]") {
  const auto owned = shell_runner("seq 1 1000; head -c 5000 /dev/zero | tr '\\0' x; echo; exit 3");
  hmi::JobRunner& runner = *owned;
  REQUIRE(runner.start(hmi::JobKind::kDelete, {}, "noisy").ok());
  const hmi::JobView v = wait_for(runner, ended);
  CHECK(v.state == "failed");
  CHECK(v.exit_code == 3);
  REQUIRE(v.log_tail.size() == hmi::JobRunner::kTailLines);
  CHECK(v.log_tail.front() == "802");  // 1001 lines: the last 200 are 802..1000 and the long one
  CHECK(v.log_tail[v.log_tail.size() - 2] == "1000");
  CHECK(v.log_tail.back().size() == hmi::JobRunner::kLineBytes + std::string(" [...]").size());
  CHECK(v.log_tail.back().rfind("xxxx", 0) == 0);
  CHECK(v.result.is_null());
}

TEST_CASE("jobs: cancel sends SIGTERM, the destructor cancels and reaps, and the hooks see the end", "[hmi][jobs]") {
  int done_calls = 0;
  std::string done_state;
  auto runner = shell_runner("echo $$; exec sleep 30");
  hmi::JobHooks hooks;
  hooks.result = [](const hmi::JobView& v) { return json{{"exit", v.exit_code}}; };
  hooks.on_done = [&](const hmi::JobView& v) {
    ++done_calls;
    done_state = v.state;
  };
  CHECK_FALSE(runner->cancel());  // nothing runs yet
  REQUIRE(runner->start(hmi::JobKind::kTrain, {}, "long", hooks).ok());
  wait_for(*runner, [](const hmi::JobView& j) { return !j.log_tail.empty(); });
  const auto t0 = Clock::now();
  CHECK(runner->cancel());
  const hmi::JobView v = wait_for(*runner, ended);
  CHECK(Clock::now() - t0 < std::chrono::seconds(5));
  CHECK(v.state == "cancelled");
  CHECK(v.exit_code == 128 + SIGTERM);
  CHECK(v.result == json{{"exit", 128 + SIGTERM}});
  CHECK(process_gone(v));
  // A new job may start once the last has ended; the destructor ends it.
  REQUIRE(runner->start(hmi::JobKind::kTrain, {}, "again").ok());
  const hmi::JobView again = wait_for(*runner, [](const hmi::JobView& j) { return !j.log_tail.empty(); });
  CHECK(again.id == v.id + 1);
  CHECK(again.state == "running");
  const auto t1 = Clock::now();
  runner.reset();
  CHECK(Clock::now() - t1 < std::chrono::seconds(5));
  CHECK(process_gone(again));
  CHECK(done_calls == 1);  // the hooks belong to the job they were given with
  CHECK(done_state == "cancelled");
}

namespace {

// A server with the parts routes over a small database taught by the executable (two parts, scans from the
// simulated cell), an operator and a maintenance account.
// The database every PartsScreen starts from: taught once per process (Catch runs the test case once per section).
const test::SmallCell& taught_cell() {
  static const test::SmallCell cell = [] {
    test::SmallCell c = test::SmallCell::named("hmi-parts-taught");
    for (const auto& [part, id] : {std::pair<const char*, int>{"plate_4h", 7}, {"bracket_l", 9}}) {
      const test::Run r =
          c.run(std::string("teach --sim --part ") + part + " --id " + std::to_string(id) + " --count 5");
      INFO(r.output);
      REQUIRE(r.exit_code == 0);
    }
    return c;
  }();
  return cell;
}

struct PartsScreen {
  test::SmallCell cell = test::SmallCell(test::numbered_scratch_dir("hmi-parts"));
  hmi::HmiParams params;
  std::unique_ptr<hmi::JobRunner> jobs;
  std::unique_ptr<hmi::HmiServer> server;
  std::atomic<int> models_changed{0};

  PartsScreen() {
    fs::copy(taught_cell().models, cell.models, fs::copy_options::recursive);
    params.port = test::free_tcp_port();
    params.users_file = (cell.dir / "hmi-users").string();
    REQUIRE(hmi::set_user(params.users_file, "anna", hmi::Role::kOperator, "operator-pass").ok());
    REQUIRE(hmi::set_user(params.users_file, "max", hmi::Role::kMaintenance, "maintenance-pass").ok());
    auto users = hmi::load_users(params.users_file);
    REQUIRE(users.ok());
    jobs = std::make_unique<hmi::JobRunner>(test::kExe, cell.config_path, cell.models);
    server = std::make_unique<hmi::HmiServer>(params, *users, nullptr, [] { return json::object(); });
    server->add_routes(
        hmi::parts_routes(*jobs, {cell.models, app::grid_spec(cell.config), [this] { ++models_changed; }}));
    REQUIRE(server->start().ok());
  }
  ~PartsScreen() {
    server->stop();
    jobs.reset();
  }
  PartsScreen(const PartsScreen&) = delete;
  PartsScreen& operator=(const PartsScreen&) = delete;

  [[nodiscard]] Reply get(const std::string& path) const { return http("127.0.0.1", server->port(), "GET", path); }
  // POST as `who` ("" = no session).
  [[nodiscard]] Reply post(const std::string& who, const std::string& path, const json& body) const {
    std::map<std::string, std::string> headers;
    if (!who.empty()) {
      headers = test::session_headers(server->port(), who, who == "max" ? "maintenance-pass" : "operator-pass");
    }
    return http("127.0.0.1", server->port(), "POST", path, body.dump(), headers);
  }
  // Waits for job `id` to end; its view.
  [[nodiscard]] json finished_job(std::uint64_t id, std::chrono::seconds limit = std::chrono::seconds(120)) const {
    const auto until = Clock::now() + limit;
    json j = get("/api/job").as_json();
    while ((j["id"] != id || j["state"] == "running") && Clock::now() < until) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      j = get("/api/job").as_json();
    }
    return j;
  }
};

}  // namespace

TEST_CASE("hmi parts: the parts, their templates and the jobs over a real database, with the access rules",
          "[hmi][parts]") {
  PartsScreen s;
  SECTION("delete, retrain, debug and cancel need a session (401) and the maintenance role (403)") {
    const json bodies[] = {{{"name", "plate_4h"}}, json::object(), {{"mode", "svm"}, {"files", {"1"}}}, json::object()};
    const char* routes[] = {"/api/parts/delete", "/api/retrain", "/api/debug", "/api/job/cancel"};
    for (std::size_t i = 0; i < 4; ++i) {
      INFO(routes[i]);
      CHECK(s.post("", routes[i], bodies[i]).status == 401);
      CHECK(s.post("anna", routes[i], bodies[i]).status == 403);
    }
    CHECK(s.get("/api/job").as_json()["id"] == 0);  // nothing was started
  }

  SECTION("GET /api/parts lists what teach stored: names, PLC ids, scans, template sizes") {
    const json list = s.get("/api/parts").as_json();
    REQUIRE(list["parts"].size() == 2);
    std::uint64_t templates = 0;
    for (const json& p : list["parts"]) {
      const std::string name = p["name"];
      INFO(name);
      CHECK(p["id"] == (name == "plate_4h" ? 7 : 9));
      std::size_t files = 0;  // the scans folder is the truth, not the manifest the route reads
      for (const auto& e : fs::directory_iterator(fs::path(s.cell.models) / "scans" / name))
        files += e.is_regular_file();
      CHECK(p["scans"] == files);
      CHECK(files == 5);
      const auto bytes = fs::file_size(fs::path(s.cell.models) / "templates" / (name + ".dmap"));
      CHECK(p["template_bytes"] == bytes);
      templates += bytes;
      CHECK(p["thresholds"]["learnt"] == false);
    }
    CHECK(list["trained"] == false);  // taught, not trained yet
    CHECK(list["total_bytes"] == templates);
  }

  SECTION("the template's depth picture has one opaque pixel per occupied x-y column of the template") {
    const Reply png = s.get("/api/parts/plate_4h/template.png");
    REQUIRE(png.status == 200);
    CHECK(png.headers.at("Content-Type") == "image/png");
    const cv::Mat image =
        cv::imdecode(std::vector<unsigned char>(png.body.begin(), png.body.end()), cv::IMREAD_UNCHANGED);
    const algo::GridSpec g = app::grid_spec(s.cell.config);
    REQUIRE(image.type() == CV_8UC4);
    CHECK(image.cols == g.nx);
    CHECK(image.rows == g.ny);
    auto t = formats::TemplateFile::open(s.cell.models + "/templates/plate_4h.dmap", g);
    REQUIRE(t.ok());
    std::set<std::pair<int, int>> columns;
    for (const algo::SurfaceCell& c : t->surface_cells()) columns.insert({c.x, g.ny - 1 - c.y});
    std::vector<cv::Mat> planes;
    cv::split(image, planes);
    CHECK(static_cast<std::size_t>(cv::countNonZero(planes[3])) == columns.size());
    const auto [x, row] = *columns.begin();
    CHECK(planes[3].at<std::uint8_t>(row, x) == 255);
    const json points = s.get("/api/parts/plate_4h/points.json").as_json();
    CHECK(points["cells"] == t->surface_cells().size());
    CHECK(points["points"].size() <= hmi::kMaxPointsJson);
    CHECK(points["points"].size() > 100);
    CHECK(s.get("/api/parts/nothing/template.png").status == 404);
    CHECK(s.get("/api/parts/bad%20name/template.png").status == 400);
  }

  SECTION("bad input is refused with 400 before any job starts; a path is never taken from the browser") {
    CHECK(s.post("max", "/api/parts/delete", {{"name", "../templates"}}).status == 400);
    CHECK(s.post("max", "/api/parts/delete", {{"nme", "plate_4h"}}).status == 400);
    CHECK(s.post("max", "/api/parts/delete", {{"name", "ghost"}}).status == 404);
    CHECK(s.post("max", "/api/debug", {{"mode", "fast"}, {"files", {"plate_4h:1"}}}).status == 400);
    CHECK(s.post("max", "/api/debug", {{"mode", "svm"}, {"files", {"/etc/passwd"}}}).status == 400);
    CHECK(s.post("max", "/api/debug", {{"mode", "svm"}, {"files", {"1234567890123"}}}).status == 400);
    CHECK(s.post("max", "/api/debug", {{"mode", "svm"}, {"files", {"42"}}}).status == 400);  // no such review scan
    CHECK(s.post("max", "/api/debug", {{"mode", "svm"}, {"files", {"plate_4h:6"}}}).status == 400);
    CHECK(s.post("max", "/api/debug", {{"mode", "svm"}, {"files", json::array()}}).status == 400);
    CHECK(s.post("max", "/api/job/cancel", json::object()).status == 409);
    CHECK(s.get("/api/job").as_json()["id"] == 0);
  }

  SECTION("retrain runs train as a job with its progress and report; debug then classifies stored scans") {
    const Reply started = s.post("max", "/api/retrain", json::object());
    REQUIRE(started.status == 200);
    const std::uint64_t id = started.as_json()["job"];
    CHECK(s.post("max", "/api/retrain", json::object()).status == 409);  // one job at a time
    const json job = s.finished_job(id);
    INFO(job.dump(1));
    REQUIRE(job["state"] == "done");
    CHECK(job["kind"] == "train");
    CHECK(job["progress"] == 1.0);
    CHECK(s.models_changed == 1);
    // The report's figures against the manifest train wrote (read here by the manifest parser, not the route).
    const std::string text = test::read_all(s.cell.models + "/manifest.yaml");
    auto manifest = formats::parse_manifest("manifest.yaml", text);
    REQUIRE(manifest.ok());
    const json& r = job["result"];
    CHECK(r["accuracy"].get<double>() == Approx(manifest->svm.test_accuracy));
    CHECK(r["test_samples"] == manifest->svm.test_scans);
    CHECK(r["classes"] == json{"plate_4h", "bracket_l"});
    int in_confusion = 0;
    for (const json& row : r["confusion"]) {
      for (const json& n : row) in_confusion += n.get<int>();
    }
    CHECK(in_confusion == manifest->svm.test_scans);
    CHECK(r["summary"].get<std::string>().find("cellsight training report") == 0);
    CHECK(s.get("/api/parts").as_json()["trained"] == true);

    // A review scan (a taught scan exported as PLY) and a taught scan as stored: each recognised as its part.
    const fs::path exported = s.cell.dir / "export";
    const test::Run ex = s.cell.run("parts export bracket_l --out " + exported.string());
    REQUIRE(ex.exit_code == 0);
    fs::create_directories(fs::path(s.cell.models) / "review" / "42");
    fs::copy_file(exported / "00002.ply", fs::path(s.cell.models) / "review" / "42" / "scan.ply");
    const json scans = s.get("/api/debug/scans").as_json();
    CHECK(scans["review"] == json{"42"});
    const Reply debug = s.post("max", "/api/debug", {{"mode", "cascade"}, {"files", {"42", "plate_4h:3"}}});
    REQUIRE(debug.status == 200);
    const json classified = s.finished_job(debug.as_json()["job"]);
    INFO(classified.dump(1));
    CHECK(classified["state"] == "done");
    REQUIRE(classified["result"].size() == 2);
    CHECK(classified["result"][0]["ref"] == "42");
    CHECK(classified["result"][0]["class"] == "bracket_l");
    CHECK(classified["result"][1]["ref"] == "plate_4h:3");
    CHECK(classified["result"][1]["class"] == "plate_4h");
    CHECK(s.models_changed == 1);  // classify changes nothing
  }

  SECTION("delete runs `parts delete` as a job; the part is gone and the loop is told") {
    const Reply started = s.post("max", "/api/parts/delete", {{"name", "bracket_l"}});
    REQUIRE(started.status == 200);
    const json job = s.finished_job(started.as_json()["job"]);
    CHECK(job["state"] == "done");
    CHECK(job["title"] == "delete bracket_l");
    CHECK(s.models_changed == 1);
    CHECK_FALSE(fs::exists(fs::path(s.cell.models) / "templates" / "bracket_l.dmap"));
    const json list = s.get("/api/parts").as_json();
    REQUIRE(list["parts"].size() == 1);
    CHECK(list["parts"][0]["name"] == "plate_4h");
  }
}
