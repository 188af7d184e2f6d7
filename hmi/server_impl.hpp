// HmiServer's insides, shared by server.cpp (life cycle, routing, access rules) and api.cpp (the JSON routes and
// the live stream). Not for other layers.
#pragma once

#include <civetweb.h>

#include <array>
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "hmi/routes.hpp"
#include "hmi/server.hpp"
#include "hmi/sessions.hpp"

namespace cellsight::hmi {

// One request as the routes see it.
struct Request {
  mg_connection* conn = nullptr;
  std::string method;
  std::string uri;
  std::string query;
  std::string remote;
  long long content_length = -1;
  bool local = false;              // from the loopback address
  std::optional<Session> session;  // from the cookie, when valid
};

struct HmiServer::Impl {
  Impl(HmiParams p, std::vector<User> u, LiveFeed* f, StatusFn s);

  HmiParams params;
  std::vector<User> users;
  LiveFeed* feed;
  StatusFn status;
  SessionTable sessions;
  LoginBrake brake;
  mg_context* ctx = nullptr;
  int bound_port = 0;

  // The results taken from the feed, newest last, each with its event id (1, 2, ...).
  std::mutex history_mutex;
  std::condition_variable history_changed;
  std::deque<std::pair<std::uint64_t, LiveResult>> history;
  std::uint64_t last_id = 0;
  std::array<std::uint64_t, 8> by_code{};  // results taken, per ResultCode (0-6; 7: any other value)
  // Cycle times of every result since start, counted per bucket (upper edges kCycleEdgesMs, the last open).
  static constexpr std::array<double, 10> kCycleEdgesMs = {5, 10, 20, 50, 100, 200, 500, 1000, 3000, 1e300};
  std::array<std::uint64_t, 10> cycle_counts{};
  // The last faults: when the loop went into fault, why, and when it came out (0: not yet).
  struct FaultEntry {
    std::int64_t since_ms = 0;
    std::int64_t until_ms = 0;
    drivers::ErrorCode error = drivers::ErrorCode::kNone;
  };
  std::deque<FaultEntry> fault_log;
  std::atomic<std::uint64_t> taken{0};
  std::atomic<bool> stopping{false};
  std::atomic<int> streams{0};
  std::atomic<std::uint64_t> streams_refused{0};
  std::atomic<std::uint64_t> streams_dropped{0};
  std::atomic<std::uint64_t> requests{0};
  std::mutex status_mutex;  // the shared status event
  std::string status_text;
  HmiClock::time_point status_built{};
  std::atomic<std::uint64_t> status_builds{0};
  std::thread pump;
  std::vector<Route> routes;  // the modules' (add_routes), matched after the built-in ones

  void pump_loop();
  void take_faults();  // with history_mutex held
  // server.cpp
  int dispatch(mg_connection* conn);
  int serve_asset(const Request& r);
  int route_api(Request& r);
  int route_module(const Request& r);
  // api.cpp
  int api_login(const Request& r);
  int api_logout(const Request& r);
  int api_session(const Request& r);
  int api_status(const Request& r);
  int api_results(const Request& r);
  int api_events(const Request& r);
  [[nodiscard]] nlohmann::json status_json();
  [[nodiscard]] std::string status_event_text();
  [[nodiscard]] std::vector<std::pair<std::uint64_t, LiveResult>> results_after(std::uint64_t id);
};

[[nodiscard]] nlohmann::json result_json(std::uint64_t id, const LiveResult& r);

}  // namespace cellsight::hmi
