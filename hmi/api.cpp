// The HMI's JSON routes and the live stream (server-sent events).
#include <cmath>
#include <cstdlib>
#include <cstring>

#include "drivers/log.hpp"
#include "hmi/server_impl.hpp"

namespace cellsight::hmi {
namespace {

constexpr const char* kComponent = "hmi";
constexpr double kUmPerMm = 1e3, kMdegPerDeg = 1e3;
constexpr auto kStatusEvery = std::chrono::seconds(1);
constexpr auto kStreamWake = std::chrono::milliseconds(200);

// A wire value in micrometres or millidegrees -> mm or degrees; null where the PLC gets the invalid marker.
nlohmann::json axis(std::int32_t wire, double per_unit) {
  if (wire == drivers::modbus_map::kInvalidS32) return nullptr;
  return static_cast<double>(wire) / per_unit;
}

nlohmann::json sigma(std::uint16_t wire, double per_unit) {
  if (wire == drivers::modbus_map::kInvalidSigma) return nullptr;
  return static_cast<double>(wire) / per_unit;
}

std::string session_cookie(const std::string& token, long max_age_s) {
  return "cs_session=" + token + "; Path=/; HttpOnly; SameSite=Strict; Max-Age=" + std::to_string(max_age_s);
}

}  // namespace

nlohmann::json read_json_body(const Request& r) {
  std::string body;
  if (r.content_length > 0) body.resize(static_cast<std::size_t>(r.content_length));
  std::size_t got = 0;
  while (got < body.size()) {
    const int n = mg_read(r.conn, body.data() + got, body.size() - got);
    if (n <= 0) return nlohmann::json::value_t::discarded;
    got += static_cast<std::size_t>(n);
  }
  return nlohmann::json::parse(body, nullptr, false);
}

std::string query_value(const Request& r, const char* key) {
  char value[256] = {};
  if (mg_get_var(r.query.c_str(), r.query.size(), key, value, sizeof value) < 0) return {};
  return value;
}

int send_png(const Request& r, const std::string& png) {
  mg_response_header_start(r.conn, 200);
  mg_response_header_add(r.conn, "Content-Type", "image/png", -1);
  mg_response_header_add(r.conn, "Content-Length", std::to_string(png.size()).c_str(), -1);
  mg_response_header_add(r.conn, "Cache-Control", "max-age=3600", -1);  // an entry's picture never changes
  mg_response_header_add(r.conn, "X-Content-Type-Options", "nosniff", -1);
  mg_response_header_send(r.conn);
  if (r.method == "GET") mg_write(r.conn, png.data(), png.size());
  return 200;
}

int send_json(mg_connection* conn, int status, const nlohmann::json& body, const std::string& extra_header_name,
              const std::string& extra_header_value) {
  const std::string text = body.dump();
  mg_response_header_start(conn, status);
  mg_response_header_add(conn, "Content-Type", "application/json", -1);
  mg_response_header_add(conn, "Content-Length", std::to_string(text.size()).c_str(), -1);
  mg_response_header_add(conn, "Cache-Control", "no-store", -1);
  mg_response_header_add(conn, "X-Content-Type-Options", "nosniff", -1);
  if (!extra_header_name.empty()) {
    mg_response_header_add(conn, extra_header_name.c_str(), extra_header_value.c_str(), -1);
  }
  mg_response_header_send(conn);
  mg_write(conn, text.data(), text.size());
  return status;
}

int send_error(mg_connection* conn, int status, const std::string& message) {
  return send_json(conn, status, {{"error", message}});
}

nlohmann::json result_json(std::uint64_t id, const LiveResult& r) {
  const drivers::PlcResult& p = r.plc;
  nlohmann::json j;
  j["id"] = id;
  j["seq"] = r.seq;
  j["acq_id"] = p.acq_id;
  j["time_ms"] = r.wall_ms;
  j["code"] = drivers::to_string(p.code);
  j["part"] = r.part_name[0] != '\0' ? nlohmann::json(r.part_name) : nlohmann::json(nullptr);
  j["part_id"] = p.part_id;
  j["confidence"] = p.confidence_permille / kUmPerMm;
  j["probability"] = r.probability;
  j["source"] = std::string(algo::to_string(r.source));
  j["reason"] = r.unknown_reason == algo::RejectReason::kNone
                    ? nlohmann::json(nullptr)
                    : nlohmann::json(std::string(to_string(r.unknown_reason)));
  j["pose"] = {{"x_mm", axis(p.x_um, kUmPerMm)},         {"y_mm", axis(p.y_um, kUmPerMm)},
               {"z_mm", axis(p.z_um, kUmPerMm)},         {"rx_deg", axis(p.rx_mdeg, kMdegPerDeg)},
               {"ry_deg", axis(p.ry_mdeg, kMdegPerDeg)}, {"theta_deg", axis(p.rz_mdeg, kMdegPerDeg)}};
  j["sigma"] = {{"x_mm", sigma(p.sigma_x_um, kUmPerMm)},         {"y_mm", sigma(p.sigma_y_um, kUmPerMm)},
                {"z_mm", sigma(p.sigma_z_um, kUmPerMm)},         {"rx_deg", sigma(p.sigma_rx_mdeg, kMdegPerDeg)},
                {"ry_deg", sigma(p.sigma_ry_mdeg, kMdegPerDeg)}, {"theta_deg", sigma(p.sigma_rz_mdeg, kMdegPerDeg)}};
  j["cycle_ms"] = r.cycle_ms;
  j["recognise_ms"] = r.recognise_ms;
  j["frames"] = r.frames;
  j["points"] = r.points;
  j["verified"] = r.verified;
  j["trigger"] = r.trigger == runtime::TriggerSource::kSoftware ? "software" : "part_present";
  j["aborted"] = r.aborted;
  return j;
}

std::vector<std::pair<std::uint64_t, LiveResult>> HmiServer::Impl::results_after(std::uint64_t id) {
  const std::lock_guard<std::mutex> lock(history_mutex);
  std::vector<std::pair<std::uint64_t, LiveResult>> out;
  for (const auto& e : history) {
    if (e.first > id) out.push_back(e);
  }
  return out;
}

nlohmann::json HmiServer::Impl::status_json() {
  nlohmann::json j = status ? status() : nlohmann::json::object();
  nlohmann::json codes = nlohmann::json::object();
  {
    const std::lock_guard<std::mutex> lock(history_mutex);
    for (std::size_t c = 0; c + 1 < by_code.size(); ++c) {
      codes[drivers::to_string(static_cast<drivers::ResultCode>(c))] = by_code[c];
    }
    codes["other"] = by_code.back();
  }
  j["results_by_code"] = codes;
  {
    const std::lock_guard<std::mutex> lock(history_mutex);
    nlohmann::json edges = nlohmann::json::array(), counts = nlohmann::json::array(), faults = nlohmann::json::array();
    for (std::size_t i = 0; i < cycle_counts.size(); ++i) {
      edges.push_back(i + 1 < kCycleEdgesMs.size() ? nlohmann::json(kCycleEdgesMs[i]) : nlohmann::json(nullptr));
      counts.push_back(cycle_counts[i]);
    }
    for (auto it = fault_log.rbegin(); it != fault_log.rend(); ++it) {
      faults.push_back({{"since_ms", it->since_ms},
                        {"until_ms", it->until_ms != 0 ? nlohmann::json(it->until_ms) : nlohmann::json(nullptr)},
                        {"error", drivers::to_string(it->error)}});
    }
    j["cycle_histogram"] = {{"upper_ms", edges}, {"counts", counts}};
    j["fault_log"] = faults;  // newest first
  }
  j["hmi"] = {{"results_taken", taken.load(std::memory_order_relaxed)},
              {"results_dropped", feed != nullptr ? feed->dropped() : 0},
              {"live_streams", streams.load(std::memory_order_relaxed)},
              {"live_streams_refused", streams_refused.load(std::memory_order_relaxed)},
              {"live_streams_dropped", streams_dropped.load(std::memory_order_relaxed)},
              {"sessions", sessions.size()},
              {"requests", requests.load(std::memory_order_relaxed)},
              {"status_builds", status_builds.load(std::memory_order_relaxed)}};
  return j;
}

// The live streams' status event: built at most once per kStatusEvery whatever the number of open views (building
// it reads the loop's and the link's counters and the session table), and shared as text.
std::string HmiServer::Impl::status_event_text() {
  const auto now = HmiClock::now();
  const std::lock_guard<std::mutex> lock(status_mutex);
  if (status_text.empty() || now - status_built >= kStatusEvery) {
    status_text = status_json().dump();
    status_built = now;
    status_builds.fetch_add(1, std::memory_order_relaxed);
  }
  return status_text;
}

int HmiServer::Impl::api_login(const Request& r) {
  const auto now = HmiClock::now();
  if (const long wait = brake.locked_for_s(r.remote, now); wait > 0) {
    log::write(log::Level::kWarn, kComponent, "login from %s refused: locked for %ld s more", r.remote.c_str(), wait);
    return send_json(r.conn, 429, {{"error", "too many failed logins: locked"}, {"retry_after_s", wait}}, "Retry-After",
                     std::to_string(wait));
  }
  const nlohmann::json body = read_json_body(r);
  if (body.is_discarded() || !body.is_object() || !body.contains("user") || !body.contains("password") ||
      !body["user"].is_string() || !body["password"].is_string()) {
    return send_error(r.conn, 400, "expected {\"user\": ..., \"password\": ...}");
  }
  const std::string user = body["user"].get<std::string>();
  const Role role = check_password(users, user, body["password"].get<std::string>());
  if (role == Role::kNone) {
    brake.failed(r.remote, now);
    log::write(log::Level::kWarn, kComponent, "failed login as '%s' from %s", user.c_str(), r.remote.c_str());
    return send_error(r.conn, 401, "wrong user name or password");
  }
  brake.succeeded(r.remote);
  const auto session = sessions.create(user, role, now);
  if (!session) return send_error(r.conn, 503, "no random numbers for a session token");
  log::write(log::Level::kInfo, kComponent, "%s logged in as %s from %s", user.c_str(), to_string(role),
             r.remote.c_str());
  const long max_age = static_cast<long>(params.session_idle_minutes) * 60;
  return send_json(r.conn, 200, {{"user", user}, {"role", to_string(role)}, {"csrf", session->csrf}}, "Set-Cookie",
                   session_cookie(session->token, max_age));
}

int HmiServer::Impl::api_logout(const Request& r) {
  sessions.remove(r.session->token);
  return send_json(r.conn, 200, {{"user", nullptr}}, "Set-Cookie", session_cookie("", 0));
}

int HmiServer::Impl::api_session(const Request& r) {
  if (!r.session) return send_json(r.conn, 200, {{"user", nullptr}, {"role", nullptr}, {"may_view", r.local}});
  return send_json(
      r.conn, 200,
      {{"user", r.session->user}, {"role", to_string(r.session->role)}, {"csrf", r.session->csrf}, {"may_view", true}});
}

int HmiServer::Impl::api_status(const Request& r) {
  return send_json(r.conn, 200, status_json());
}

int HmiServer::Impl::api_results(const Request& r) {
  char after_text[32] = {};
  std::uint64_t after = 0;
  if (mg_get_var(r.query.c_str(), r.query.size(), "after", after_text, sizeof after_text) > 0) {
    after = std::strtoull(after_text, nullptr, 10);
  }
  nlohmann::json list = nlohmann::json::array();
  for (const auto& [id, result] : results_after(after)) list.push_back(result_json(id, result));
  return send_json(r.conn, 200, {{"results", list}});
}

// The live stream: one civetweb thread per browser for as long as it watches; bounded to 3/4 of the threads so the
// other routes always get one. A write that fails (the browser left, or its socket stayed full for the request
// timeout: a slow browser) ends the stream.
int HmiServer::Impl::api_events(const Request& r) {
  const int limit = std::max(1, params.max_clients * 3 / 4);
  if (streams.fetch_add(1) >= limit) {
    streams.fetch_sub(1);
    streams_refused.fetch_add(1, std::memory_order_relaxed);
    // Closed after the answer: kept alive, each refused browser would hold one of the threads left for the other
    // routes for the keep-alive time, and 50 of them starve the screen (seen with tests/browser/idle_clients.py).
    mg_disable_keep_alive(r.conn);
    return send_error(r.conn, 503, "too many live views open");
  }
  mg_printf(r.conn,
            "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n"
            "X-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n");
  std::uint64_t sent = 0;
  if (const char* last = mg_get_header(r.conn, "Last-Event-ID"); last != nullptr)
    sent = std::strtoull(last, nullptr, 10);
  auto next_status = HmiClock::now();
  bool ok = true;
  while (ok && !stopping.load(std::memory_order_acquire)) {
    std::string chunk;
    for (const auto& [id, result] : results_after(sent)) {
      chunk += "id: " + std::to_string(id) + "\nevent: result\ndata: " + result_json(id, result).dump() + "\n\n";
      sent = id;
    }
    if (HmiClock::now() >= next_status) {
      chunk += "event: status\ndata: " + status_event_text() + "\n\n";
      next_status = HmiClock::now() + kStatusEvery;
    }
    if (!chunk.empty()) ok = mg_write(r.conn, chunk.data(), chunk.size()) == static_cast<int>(chunk.size());
    if (!ok) break;
    std::unique_lock<std::mutex> lock(history_mutex);
    history_changed.wait_for(lock, kStreamWake, [&] {
      return stopping.load(std::memory_order_acquire) || (!history.empty() && history.back().first > sent);
    });
  }
  if (!ok) streams_dropped.fetch_add(1, std::memory_order_relaxed);
  streams.fetch_sub(1);
  return 200;
}

}  // namespace cellsight::hmi
