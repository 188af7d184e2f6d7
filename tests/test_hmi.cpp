// The operator's screen (issue 14): accounts, access rules and the live results, against a real civetweb server on
// this machine and real HTTP requests (civetweb's client).
#include <arpa/inet.h>
#include <civetweb.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <catch2/catch.hpp>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "hmi/assets.hpp"
#include "hmi/live_feed.hpp"
#include "hmi/server.hpp"
#include "hmi/sessions.hpp"
#include "hmi/users.hpp"
#include "tests/free_port.hpp"
#include "tests/http_client.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
using nlohmann::json;
using test::http;
using test::Reply;

namespace {

// An IPv4 address of this machine that is not loopback: requests from it count as "another machine".
std::string non_loopback_address() {
  ifaddrs* list = nullptr;
  REQUIRE(getifaddrs(&list) == 0);
  std::string found;
  for (ifaddrs* a = list; a != nullptr && found.empty(); a = a->ifa_next) {
    if (a->ifa_addr == nullptr || a->ifa_addr->sa_family != AF_INET) continue;
    char text[INET_ADDRSTRLEN] = {};
    inet_ntop(AF_INET, &reinterpret_cast<sockaddr_in*>(a->ifa_addr)->sin_addr, text, sizeof text);
    if (std::string(text).rfind("127.", 0) != 0) found = text;
  }
  freeifaddrs(list);
  return found;
}

runtime::PartRecord record(std::uint32_t acq, const char* name, std::uint16_t id) {
  runtime::PartRecord r;
  r.acq_id = acq;
  r.seq = acq;
  r.result.acq_id = acq;
  r.result.code = drivers::ResultCode::kOk;
  r.result.part_id = id;
  r.result.confidence_permille = 912;
  r.result.source = drivers::ResultSource::kPerfectMatch;
  r.result.x_um = 12'310;
  r.result.y_um = -4'020;
  r.result.rz_mdeg = 1'250;
  r.result.sigma_x_um = 110;
  r.decision.source = algo::DecisionSource::kPm;
  r.cycle_ms = 21.5;
  r.class_name = name;
  return r;
}

// A server on a free port with an operator and a maintenance account, fed by a LiveFeed the test drives.
struct Screen {
  std::filesystem::path dir = test::scratch_dir("hmi");
  hmi::LiveFeed feed{64};
  hmi::HmiParams params;
  std::unique_ptr<hmi::HmiServer> server;

  explicit Screen(const std::string& bind = "127.0.0.1", int max_failed_logins = 10) {
    params.bind_address = bind;
    params.port = test::free_tcp_port();
    params.max_failed_logins = max_failed_logins;
    params.lockout_s = 60;
    params.users_file = (dir / "hmi-users").string();
    REQUIRE(hmi::set_user(params.users_file, "anna", hmi::Role::kOperator, "operator-pass").ok());
    REQUIRE(hmi::set_user(params.users_file, "max", hmi::Role::kMaintenance, "maintenance-pass").ok());
    auto users = hmi::load_users(params.users_file);
    REQUIRE(users.ok());
    server = std::make_unique<hmi::HmiServer>(params, *users, &feed, [] {
      return json{{"state", "idle"}, {"counters", {{"results", 0}}}};
    });
    const Status started = server->start();
    INFO((started.ok() ? "" : started.error().message));
    REQUIRE(started.ok());
  }
  [[nodiscard]] int port() const { return server->port(); }

  // Logs in from `host`; returns the cookie header value and the CSRF token.
  std::pair<std::string, std::string> login(const std::string& user, const std::string& password,
                                            const std::string& host = "127.0.0.1") const {
    const Reply r = http(host, port(), "POST", "/api/login", json{{"user", user}, {"password", password}}.dump(),
                         {{"Content-Type", "application/json"}});
    REQUIRE(r.status == 200);
    const std::string cookie = r.headers.at("Set-Cookie");
    return {cookie.substr(0, cookie.find(';')), r.as_json().at("csrf").get<std::string>()};
  }
};

}  // namespace

TEST_CASE("hmi: accounts are stored as salted yescrypt hashes in a private file and checked", "[hmi][users]") {
  const auto dir = test::scratch_dir("hmi-users");
  const std::string path = (dir / "users").string();
  REQUIRE(hmi::set_user(path, "anna", hmi::Role::kOperator, "correct horse").ok());
  REQUIRE(hmi::set_user(path, "bob", hmi::Role::kOperator, "correct horse").ok());
  struct stat st {};
  REQUIRE(stat(path.c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0600);
  auto users = hmi::load_users(path);
  REQUIRE(users.ok());
  REQUIRE(users->size() == 2);
  CHECK((*users)[0].hash.rfind("$y$", 0) == 0);
  CHECK((*users)[0].hash != (*users)[1].hash);  // same password, another salt
  std::ifstream in(path);
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  CHECK(text.find("correct horse") == std::string::npos);
  CHECK(hmi::check_password(*users, "anna", "correct horse") == hmi::Role::kOperator);
  CHECK(hmi::check_password(*users, "anna", "correct horsf") == hmi::Role::kNone);
  CHECK(hmi::check_password(*users, "carl", "correct horse") == hmi::Role::kNone);
  // Replacing an account changes its role and password, not the others.
  REQUIRE(hmi::set_user(path, "anna", hmi::Role::kMaintenance, "another pass").ok());
  users = hmi::load_users(path);
  REQUIRE(users.ok());
  CHECK(users->size() == 2);
  CHECK(hmi::check_password(*users, "anna", "another pass") == hmi::Role::kMaintenance);
  CHECK(hmi::check_password(*users, "anna", "correct horse") == hmi::Role::kNone);
  CHECK(hmi::check_password(*users, "bob", "correct horse") == hmi::Role::kOperator);
  // Bad input is refused with a reason.
  CHECK_FALSE(hmi::set_user(path, "x y", hmi::Role::kOperator, "long enough").ok());
  CHECK_FALSE(hmi::set_user(path, "carl", hmi::Role::kOperator, "short").ok());
  CHECK_FALSE(hmi::set_user(path, "carl", hmi::Role::kNone, "long enough").ok());
}

TEST_CASE("hmi: a damaged accounts file is refused naming file and line, a missing one means no accounts",
          "[hmi][users]") {
  const auto dir = test::scratch_dir("hmi-users-bad");
  CHECK(hmi::load_users((dir / "none").string())->empty());
  const auto write = [&](const std::string& text) {
    std::ofstream((dir / "users").string()) << text;
    return hmi::load_users((dir / "users").string());
  };
  auto r = write("# comment\nanna:operator:$y$j9T$abc$def\nbob:admin:$y$j9T$abc$def\n");
  REQUIRE_FALSE(r.ok());
  CHECK(r.error().message.find("users:3: role must be operator or maintenance") != std::string::npos);
  r = write("anna:operator:$1$md5$old\n");
  REQUIRE_FALSE(r.ok());
  CHECK(r.error().message.find("users:1: the hash is not a yescrypt hash") != std::string::npos);
  r = write("anna:operator:$y$a\nanna:maintenance:$y$b\n");
  REQUIRE_FALSE(r.ok());
  CHECK(r.error().message.find("appears twice") != std::string::npos);
  r = write("just one field\n");
  REQUIRE_FALSE(r.ok());
  CHECK(r.error().message.find("users:1: expected NAME:ROLE:HASH") != std::string::npos);
}

TEST_CASE("hmi: the page and its assets are served from the binary with no reference to another host",
          "[hmi][server]") {
  const Screen screen;
  const Reply page = http("127.0.0.1", screen.port(), "GET", "/");
  REQUIRE(page.status == 200);
  CHECK(page.headers.at("Content-Type").find("text/html") == 0);
  CHECK(page.headers.at("Content-Security-Policy").find("default-src 'self'") == 0);
  CHECK(page.body.find("<script src=\"/app.js\">") != std::string::npos);
  for (const char* asset : {"/", "/app.js", "/app.css"}) {
    const hmi::Asset* a = hmi::find_asset(asset);
    REQUIRE(a != nullptr);
    const std::string text(reinterpret_cast<const char*>(a->data), a->size);
    INFO(asset);
    CHECK(text.find("http://") == std::string::npos);  // works offline: nothing from a CDN
    CHECK(text.find("https://") == std::string::npos);
    const Reply r = http("127.0.0.1", screen.port(), "GET", asset);
    CHECK(r.status == 200);
    CHECK(r.body == text);
  }
  CHECK(http("127.0.0.1", screen.port(), "GET", "/nothing.js").status == 404);
  CHECK(http("127.0.0.1", screen.port(), "DELETE", "/api/results").status == 405);
}

TEST_CASE("hmi: results from the loop's feed appear in /api/results and the live stream, with pose in mm and deg",
          "[hmi][server]") {
  Screen screen;
  screen.feed.on_part_done(record(7, "ribbed_v4", 3));
  json results;
  for (int i = 0; i < 100 && (results.is_null() || results["results"].empty()); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    results = http("127.0.0.1", screen.port(), "GET", "/api/results").as_json();
  }
  REQUIRE(results["results"].size() == 1);
  const json& r = results["results"][0];
  CHECK(r["part"] == "ribbed_v4");
  CHECK(r["part_id"] == 3);
  CHECK(r["code"] == "ok");
  CHECK(r["source"] == "pm");
  CHECK(r["confidence"].get<double>() == Approx(0.912));
  CHECK(r["pose"]["x_mm"].get<double>() == Approx(12.31));
  CHECK(r["pose"]["y_mm"].get<double>() == Approx(-4.02));
  CHECK(r["pose"]["theta_deg"].get<double>() == Approx(1.25));
  CHECK(r["pose"]["z_mm"].is_null());  // invalid on the PLC: null here, never 0
  CHECK(r["sigma"]["x_mm"].get<double>() == Approx(0.11));
  CHECK(r["sigma"]["y_mm"].is_null());
  const std::uint64_t first_id = r["id"];
  CHECK(http("127.0.0.1", screen.port(), "GET", "/api/results?after=" + std::to_string(first_id))
            .as_json()["results"]
            .empty());

  // The live stream: the next result arrives as an event without asking again.
  char error[256] = {};
  mg_connection* conn = mg_connect_client("127.0.0.1", screen.port(), 0, error, sizeof error);
  REQUIRE(conn != nullptr);
  const std::string request =
      "GET /api/events HTTP/1.1\r\nHost: x\r\nLast-Event-ID: " + std::to_string(first_id) + "\r\n\r\n";
  mg_write(conn, request.data(), request.size());
  REQUIRE(mg_get_response(conn, error, sizeof error, 5000) >= 0);
  CHECK(mg_get_response_info(conn)->status_code == 200);
  screen.feed.on_part_done(record(8, "plate_5h", 2));
  std::string stream;
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (stream.find("\"plate_5h\"") == std::string::npos && std::chrono::steady_clock::now() < until) {
    char buffer[4096];
    const int n = mg_read(conn, buffer, sizeof buffer);
    if (n <= 0) break;
    stream.append(buffer, static_cast<std::size_t>(n));
  }
  mg_close_connection(conn);
  CHECK(stream.find("event: status") != std::string::npos);
  CHECK(stream.find("id: " + std::to_string(first_id + 1) + "\nevent: result") != std::string::npos);
  CHECK(stream.find("\"plate_5h\"") != std::string::npos);
  CHECK(stream.find("\"ribbed_v4\"") == std::string::npos);  // the browser had it already
}

TEST_CASE("hmi: state-changing requests need a session (401) and its CSRF token (403), bodies are bounded (413)",
          "[hmi][server][security]") {
  const Screen screen;
  const int port = screen.port();
  for (const char* route : {"/api/logout", "/api/command", "/api/parts/delete", "/api/train"}) {
    INFO(route);
    CHECK(http("127.0.0.1", port, "POST", route, "{}").status == 401);
  }
  const auto [cookie, csrf] = screen.login("anna", "operator-pass");
  CHECK(cookie.rfind("cs_session=", 0) == 0);
  CHECK(http("127.0.0.1", port, "POST", "/api/logout", "{}", {{"Cookie", cookie}}).status == 403);
  CHECK(
      http("127.0.0.1", port, "POST", "/api/logout", "{}", {{"Cookie", cookie}, {"X-CSRF-Token", "0" + csrf}}).status ==
      403);
  const Reply session = http("127.0.0.1", port, "GET", "/api/session", "", {{"Cookie", cookie}});
  CHECK(session.as_json()["user"] == "anna");
  CHECK(session.as_json()["role"] == "operator");
  // The cookie is for this site's scripts-free use only.
  const Reply login =
      http("127.0.0.1", port, "POST", "/api/login", json{{"user", "max"}, {"password", "maintenance-pass"}}.dump());
  const std::string set_cookie = login.headers.at("Set-Cookie");
  CHECK(set_cookie.find("HttpOnly") != std::string::npos);
  CHECK(set_cookie.find("SameSite=Strict") != std::string::npos);
  // 1 MB is refused before it is read.
  const Reply big = http("127.0.0.1", port, "POST", "/api/login", std::string(1 << 20, 'x'));
  CHECK(big.status == 413);
  // With the token: logged out, and the cookie is no longer a session.
  CHECK(http("127.0.0.1", port, "POST", "/api/logout", "{}", {{"Cookie", cookie}, {"X-CSRF-Token", csrf}}).status ==
        200);
  CHECK(http("127.0.0.1", port, "POST", "/api/logout", "{}", {{"Cookie", cookie}, {"X-CSRF-Token", csrf}}).status ==
        401);
}

TEST_CASE("hmi: after max_failed_logins wrong passwords the address is locked out, even for the right one",
          "[hmi][server][security]") {
  const Screen screen("127.0.0.1", 10);
  const auto attempt = [&](const char* password) {
    return http("127.0.0.1", screen.port(), "POST", "/api/login",
                json{{"user", "anna"}, {"password", password}}.dump());
  };
  for (int i = 0; i < 10; ++i) CHECK(attempt("guess").status == 401);
  const Reply eleventh = attempt("operator-pass");
  CHECK(eleventh.status == 429);
  CHECK(std::stoi(eleventh.headers.at("Retry-After")) > 55);
  CHECK(std::stoi(eleventh.headers.at("Retry-After")) <= 60);
}

TEST_CASE("hmi: from another machine nothing is shown without a login, from this one viewing needs none",
          "[hmi][server][security]") {
  const std::string other = non_loopback_address();
  REQUIRE_FALSE(other.empty());
  const Screen screen("0.0.0.0");
  CHECK(http("127.0.0.1", screen.port(), "GET", "/api/status").status == 200);
  CHECK(http(other, screen.port(), "GET", "/api/status").status == 401);
  CHECK(http(other, screen.port(), "GET", "/api/results").status == 401);
  CHECK(http(other, screen.port(), "GET", "/api/events").status == 401);
  CHECK(http(other, screen.port(), "GET", "/api/session").as_json()["may_view"] == false);
  CHECK(http(other, screen.port(), "GET", "/").status == 200);  // the login page itself
  const auto [cookie, csrf] = screen.login("anna", "operator-pass", other);
  const Reply status = http(other, screen.port(), "GET", "/api/status", "", {{"Cookie", cookie}});
  CHECK(status.status == 200);
  CHECK(status.as_json()["state"] == "idle");
  CHECK(status.as_json()["hmi"]["sessions"] == 1);
}

TEST_CASE("hmi: when the login brake's table is full of locked addresses, newcomers are locked out together",
          "[hmi][security]") {
  const auto t0 = hmi::HmiClock::now();
  hmi::LoginBrake brake(2, std::chrono::seconds(60), 3);
  for (const char* address : {"10.0.0.1", "10.0.0.2", "10.0.0.3"}) {
    brake.failed(address, t0);
    brake.failed(address, t0);
    CHECK(brake.locked_for_s(address, t0) == 60);
  }
  // Newcomers: the table is full of locked entries, so their failures count together.
  CHECK(brake.locked_for_s("10.0.0.4", t0) == 0);
  brake.failed("10.0.0.4", t0);
  CHECK(brake.locked_for_s("10.0.0.4", t0) == 0);
  brake.failed("10.0.0.5", t0);
  CHECK(brake.locked_for_s("10.0.0.4", t0) == 60);
  CHECK(brake.locked_for_s("10.0.0.6", t0) == 60);  // a third newcomer that never tried is locked out as well
  // Once the locks are served, the table frees up and each address counts on its own again.
  const auto later = t0 + std::chrono::seconds(61);
  CHECK(brake.locked_for_s("10.0.0.6", later) == 0);
  brake.failed("10.0.0.6", later);
  CHECK(brake.locked_for_s("10.0.0.6", later) == 0);
  CHECK(brake.locked_for_s("10.0.0.1", later) == 0);
}

TEST_CASE("hmi: the status event is built once per second however many live views are open", "[hmi][live]") {
  Screen screen;
  constexpr int kViews = 6;
  std::vector<mg_connection*> views;
  for (int i = 0; i < kViews; ++i) {
    char error[256] = {};
    mg_connection* conn = mg_connect_client("127.0.0.1", screen.port(), 0, error, sizeof error);
    REQUIRE(conn != nullptr);
    const std::string request = "GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n";
    mg_write(conn, request.data(), request.size());
    REQUIRE(mg_get_response(conn, error, sizeof error, 5000) >= 0);
    CHECK(mg_get_response_info(conn)->status_code == 200);
    views.push_back(conn);
  }
  const auto builds = [&] {
    return http("127.0.0.1", screen.port(), "GET", "/api/status").as_json()["hmi"]["status_builds"].get<int>();
  };
  const int before = builds();
  std::this_thread::sleep_for(std::chrono::milliseconds(3500));
  const int during = builds() - before;
  for (mg_connection* conn : views) mg_close_connection(conn);
  // Each view sends a status event every second (3-4 here); built per view that would be 18-24.
  CHECK(during >= 3);
  CHECK(during <= 5);
}

TEST_CASE("hmi: Health's cycle histogram counts every result, the fault log has each fault with its recovery",
          "[hmi][health]") {
  Screen screen;
  using runtime::LoopState;
  screen.feed.on_state(LoopState::kIdle, LoopState::kScanning, drivers::ErrorCode::kNone);  // not a fault: not logged
  screen.feed.on_state(LoopState::kScanning, LoopState::kFault, drivers::ErrorCode::kCameraTimeout);
  screen.feed.on_state(LoopState::kFault, LoopState::kIdle, drivers::ErrorCode::kNone);
  screen.feed.on_state(LoopState::kIdle, LoopState::kFault, drivers::ErrorCode::kEncoderFault);
  for (const double ms : {3.0, 21.5, 22.0, 140.0, 4000.0}) {
    runtime::PartRecord r = record(7, "plate_5h", 2);
    r.cycle_ms = ms;
    screen.feed.on_part_done(r);
  }
  json status;
  for (int i = 0; i < 100; ++i) {  // the pump takes the feed every 50 ms
    status = http("127.0.0.1", screen.port(), "GET", "/api/status").as_json();
    if (status["hmi"]["results_taken"] == 5 && status["fault_log"].size() == 2) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  REQUIRE(status["hmi"]["results_taken"] == 5);
  const json& h = status["cycle_histogram"];
  REQUIRE(h["counts"].size() == h["upper_ms"].size());
  CHECK(h["upper_ms"][0] == 5.0);
  CHECK(h["upper_ms"].back().is_null());  // the last bucket is open
  CHECK(h["counts"] == json::array({1, 0, 0, 2, 0, 1, 0, 0, 0, 1}));
  const json& faults = status["fault_log"];
  REQUIRE(faults.size() == 2);
  CHECK(faults[0]["error"] == "encoder fault");  // newest first, not recovered yet
  CHECK(faults[0]["until_ms"].is_null());
  CHECK(faults[1]["error"] == "camera timeout");
  CHECK(faults[1]["until_ms"].get<std::int64_t>() >= faults[1]["since_ms"].get<std::int64_t>());
}
