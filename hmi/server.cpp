// HmiServer: life cycle, the pump that takes results from the loop's feed, routing and the access rules.
#include "hmi/server.hpp"

#include <algorithm>
#include <cstring>

#include "drivers/log.hpp"
#include "hmi/assets.hpp"
#include "hmi/server_impl.hpp"

namespace cellsight::hmi {
namespace {

constexpr const char* kComponent = "hmi";
constexpr auto kPumpPeriod = std::chrono::milliseconds(50);
constexpr std::size_t kCookieBytes = 128;

bool is_loopback(const char* address) {
  return std::strncmp(address, "127.", 4) == 0 || std::strcmp(address, "::1") == 0 ||
         std::strcmp(address, "[::1]") == 0;
}

int handle_request(mg_connection* conn, void* cbdata) {
  return static_cast<HmiServer::Impl*>(cbdata)->dispatch(conn);
}

int log_message(const mg_connection* /*conn*/, const char* message) {
  log::write(log::Level::kWarn, kComponent, "civetweb: %s", message);
  return 1;  // logged here, not on stderr
}

}  // namespace

HmiServer::Impl::Impl(HmiParams p, std::vector<User> u, LiveFeed* f, StatusFn s)
    : params(std::move(p)),
      users(std::move(u)),
      feed(f),
      status(std::move(s)),
      sessions(std::chrono::minutes(params.session_idle_minutes), static_cast<std::size_t>(params.max_sessions)),
      brake(params.max_failed_logins, std::chrono::seconds(params.lockout_s)) {}

void HmiServer::Impl::pump_loop() {
  std::unique_lock<std::mutex> lock(history_mutex);
  while (!stopping.load(std::memory_order_acquire)) {
    bool any = false;
    LiveResult r;
    while (feed != nullptr && feed->take(r)) {
      history.emplace_back(++last_id, r);
      ++by_code[std::min<std::size_t>(static_cast<std::size_t>(r.plc.code), by_code.size() - 1)];
      std::size_t bucket = 0;
      while (bucket + 1 < kCycleEdgesMs.size() && r.cycle_ms > kCycleEdgesMs[bucket]) ++bucket;
      ++cycle_counts[bucket];
      while (history.size() > static_cast<std::size_t>(params.history)) history.pop_front();
      taken.fetch_add(1, std::memory_order_relaxed);
      any = true;
    }
    take_faults();
    if (any) history_changed.notify_all();
    history_changed.wait_for(lock, kPumpPeriod);
  }
  history_changed.notify_all();
}

void HmiServer::Impl::take_faults() {
  constexpr std::size_t kKeep = 50;
  FaultEvent e;
  while (feed != nullptr && feed->take(e)) {
    if (e.to == runtime::LoopState::kFault) {
      fault_log.push_back({e.wall_ms, 0, e.error});
      while (fault_log.size() > kKeep) fault_log.pop_front();
    } else if (!fault_log.empty() && fault_log.back().until_ms == 0) {
      fault_log.back().until_ms = e.wall_ms;
    }
  }
}

int HmiServer::Impl::dispatch(mg_connection* conn) {
  requests.fetch_add(1, std::memory_order_relaxed);
  const mg_request_info* info = mg_get_request_info(conn);
  Request r;
  r.conn = conn;
  r.method = info->request_method != nullptr ? info->request_method : "";
  r.uri = info->local_uri != nullptr ? info->local_uri : "";
  r.query = info->query_string != nullptr ? info->query_string : "";
  r.remote = info->remote_addr;
  r.content_length = info->content_length;
  r.local = is_loopback(info->remote_addr);
  // Bounded before anything is read: a body over the limit (or of unknown length) is refused with 413.
  const bool has_body = r.content_length > 0 || mg_get_header(conn, "Transfer-Encoding") != nullptr;
  if (has_body && (r.content_length < 0 || r.content_length > params.max_request_bytes)) {
    mg_disable_keep_alive(conn);
    return send_error(conn, 413, "request body larger than " + std::to_string(params.max_request_bytes) + " bytes");
  }
  if (r.method != "GET" && r.method != "HEAD" && r.method != "POST") {
    return send_error(conn, 405, "method " + r.method + " not allowed");
  }
  if (r.uri.rfind("/api/", 0) != 0) return serve_asset(r);
  if (const char* cookies = mg_get_header(conn, "Cookie"); cookies != nullptr) {
    char token[kCookieBytes];
    if (mg_get_cookie(cookies, "cs_session", token, sizeof token) > 0) {
      r.session = sessions.find(token, HmiClock::now());
    }
  }
  return route_api(r);
}

int HmiServer::Impl::serve_asset(const Request& r) {
  if (r.method != "GET" && r.method != "HEAD") return send_error(r.conn, 405, "the page is read-only");
  const Asset* asset = find_asset(r.uri == "/index.html" ? "/" : r.uri);
  if (asset == nullptr) return send_error(r.conn, 404, "no such page: " + r.uri);
  mg_response_header_start(r.conn, 200);
  mg_response_header_add(r.conn, "Content-Type", asset->type.data(), static_cast<int>(asset->type.size()));
  mg_response_header_add(r.conn, "Content-Length", std::to_string(asset->size).c_str(), -1);
  mg_response_header_add(r.conn, "Cache-Control", "no-cache", -1);
  mg_response_header_add(r.conn, "X-Content-Type-Options", "nosniff", -1);
  mg_response_header_add(r.conn, "X-Frame-Options", "DENY", -1);
  mg_response_header_add(r.conn, "Content-Security-Policy",
                         "default-src 'self'; img-src 'self' data: blob:; frame-ancestors 'none'", -1);
  mg_response_header_send(r.conn);
  if (r.method == "GET") mg_write(r.conn, asset->data, asset->size);
  return 200;
}

int HmiServer::Impl::route_api(Request& r) {
  if (r.method == "POST") {
    if (r.uri == "/api/login") return api_login(r);
    // Every other POST changes state: a session, and the CSRF token that only the page of that session knows.
    if (!r.session) return send_error(r.conn, 401, "log in first");
    const char* csrf = mg_get_header(r.conn, "X-CSRF-Token");
    if (csrf == nullptr || r.session->csrf != csrf) return send_error(r.conn, 403, "missing or wrong CSRF token");
    if (r.uri == "/api/logout") return api_logout(r);
    return route_module(r);
  }
  if (r.uri == "/api/session") return api_session(r);  // tells the page whether to show the login
  if (!r.session && !r.local) return send_error(r.conn, 401, "log in first (viewing without login: this machine only)");
  if (r.uri == "/api/status") return api_status(r);
  if (r.uri == "/api/results") return api_results(r);
  if (r.uri == "/api/events") return api_events(r);
  return route_module(r);
}

// The modules' routes (routes.hpp). For a POST the session and its CSRF token were checked by route_api.
int HmiServer::Impl::route_module(const Request& r) {
  const std::string method = r.method == "HEAD" ? "GET" : r.method;
  for (const Route& route : routes) {
    const bool prefix = !route.path.empty() && route.path.back() == '/';
    const bool match = prefix ? r.uri.rfind(route.path, 0) == 0 : r.uri == route.path;
    if (!match || route.method != method) continue;
    const Role needed = method == "POST" ? std::max(route.min_role, Role::kOperator) : route.min_role;
    if (needed != Role::kNone) {
      if (!r.session) return send_error(r.conn, 401, "log in first");
      if (static_cast<int>(r.session->role) < static_cast<int>(needed)) {
        return send_error(r.conn, 403, std::string("needs the ") + to_string(needed) + " role");
      }
    }
    return route.handler(r);
  }
  return send_error(r.conn, 404, (method == "POST" ? "no such action: " : "no such resource: ") + r.uri);
}

HmiServer::HmiServer(HmiParams params, std::vector<User> users, LiveFeed* feed, StatusFn status)
    : impl_(std::make_unique<Impl>(std::move(params), std::move(users), feed, std::move(status))) {}

HmiServer::~HmiServer() {
  stop();
}

void HmiServer::add_routes(std::vector<Route> routes) {
  for (Route& route : routes) impl_->routes.push_back(std::move(route));
}

Status HmiServer::start() {
  Impl& d = *impl_;
  mg_init_library(0);
  const std::string listen = d.params.bind_address + ":" + std::to_string(d.params.port);
  // One civetweb thread per connection being served; live streams hold theirs (api_events bounds them).
  const std::string threads = std::to_string(d.params.max_clients);
  const char* options[] = {"listening_ports",
                           listen.c_str(),
                           "num_threads",
                           threads.c_str(),
                           "request_timeout_ms",
                           "5000",
                           "enable_keep_alive",
                           "yes",
                           "keep_alive_timeout_ms",
                           "5000",
                           "max_request_size",
                           "16384",
                           nullptr};
  mg_callbacks callbacks{};
  callbacks.log_message = log_message;
  mg_init_data init{&callbacks, &d, options};
  char text[256] = {};
  unsigned code = 0;
  mg_error_data error{&code, text, sizeof text};
  d.ctx = mg_start2(&init, &error);
  if (d.ctx == nullptr) {
    mg_exit_library();
    return make_error("HMI: cannot serve on " + listen + ": " + (text[0] != '\0' ? text : "civetweb failed to start"));
  }
  mg_server_port ports[4] = {};
  const int n = mg_get_server_ports(d.ctx, 4, ports);
  d.bound_port = n > 0 ? ports[0].port : d.params.port;
  mg_set_request_handler(d.ctx, "/", handle_request, &d);
  d.stopping.store(false);
  d.pump = std::thread([&d] { d.pump_loop(); });
  log::write(log::Level::kInfo, kComponent, "operator's screen at %s (%zu accounts)", url().c_str(), d.users.size());
  return {};
}

void HmiServer::stop() {
  Impl& d = *impl_;
  d.stopping.store(true, std::memory_order_release);
  d.history_changed.notify_all();
  if (d.ctx != nullptr) {
    mg_stop(d.ctx);  // waits for the handlers; the live streams end within a pump period
    d.ctx = nullptr;
    mg_exit_library();  // pairs with start()'s mg_init_library (civetweb counts them)
  }
  if (d.pump.joinable()) d.pump.join();
}

int HmiServer::port() const {
  return impl_->bound_port;
}

std::string HmiServer::url() const {
  const std::string& a = impl_->params.bind_address;
  return "http://" + (a == "0.0.0.0" ? std::string("127.0.0.1") : a) + ":" + std::to_string(port()) + "/";
}

std::uint64_t HmiServer::results_seen() const {
  return impl_->taken.load(std::memory_order_relaxed);
}

}  // namespace cellsight::hmi
