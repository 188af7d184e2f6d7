// The operator's screen: an HTTP server (civetweb, Debian's libcivetweb) inside `run`, on its own threads at normal
// priority. It never holds the production loop up: results come through LiveFeed's ring, counters through the
// status callback (atomics of the loop and the link), and the loop never waits for a browser. A slow browser is
// dropped when its socket stays full for the request timeout.
//
// Routes (README "Operator's screen"): the page and its assets (compiled in, nothing from the internet);
//   GET  /api/session   who is logged in (and the CSRF token the page sends back)
//   GET  /api/status    loop state, counters, PLC link, HMI figures
//   GET  /api/results   the kept history (?after=ID: only newer ones)
//   GET  /api/events    server-sent events: "result" as each part finishes, "status" every second
//   POST /api/login     {"user", "password"} -> session cookie (HttpOnly, SameSite=Strict)
//   POST /api/logout
// Viewing without a session only from the loopback address; every POST except login needs a session (else 401) and
// its X-CSRF-Token (else 403); a body above max_request_bytes gets 413 before it is read; max_failed_logins in a row
// lock the address out for lockout_s (429).
#pragma once

#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "base/result.hpp"
#include "hmi/hmi_params.hpp"
#include "hmi/live_feed.hpp"
#include "hmi/routes.hpp"
#include "hmi/users.hpp"

namespace cellsight::hmi {

class HmiServer {
 public:
  // Called on an HMI thread for /api/status and the status events; must be thread-safe.
  using StatusFn = std::function<nlohmann::json()>;

  // feed: borrowed, outlives the server (may be null: no results). users: from load_users().
  HmiServer(HmiParams params, std::vector<User> users, LiveFeed* feed, StatusFn status);
  ~HmiServer();  // stop()
  HmiServer(const HmiServer&) = delete;
  HmiServer& operator=(const HmiServer&) = delete;

  // Before start(): more pages' routes (routes.hpp: the access rules are the server's).
  void add_routes(std::vector<Route> routes);

  // Binds bind_address:port and starts serving; the error names the address, the port and why.
  [[nodiscard]] Status start();
  void stop();                                       // ends the live streams, then the server; idempotent
  [[nodiscard]] int port() const;                    // the bound port (port 0 in the params: the one the kernel chose)
  [[nodiscard]] std::string url() const;             // http://ADDRESS:PORT/
  [[nodiscard]] std::uint64_t results_seen() const;  // results taken from the feed so far

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace cellsight::hmi
