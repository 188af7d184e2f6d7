// The screen's pages beyond the live view (parts, review, teach, debug) plug in here: each module (hmi/*_api.cpp)
// gives HmiServer a list of routes before start(), so server.cpp keeps one set of access rules for all of them.
// Access rules, applied by server.cpp before a route's handler runs:
//   GET   viewing: a session, or the loopback address; and, when min_role is kMaintenance, a maintenance session
//   POST  a session (else 401), its X-CSRF-Token (else 403), and min_role (operator < maintenance; else 403)
#pragma once

#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "hmi/users.hpp"

struct mg_connection;

namespace cellsight::hmi {

struct Request;

struct Route {
  std::string method;           // "GET" or "POST"
  std::string path;             // exact, or a prefix when it ends with '/' (the handler reads the rest from r.uri)
  Role min_role = Role::kNone;  // kNone: viewing rules only (GET); a POST always needs at least kOperator
  std::function<int(const Request&)> handler;  // returns the HTTP status sent (for the access log)
};

// Helpers for route handlers (api.cpp).
int send_json(mg_connection* conn, int status, const nlohmann::json& body, const std::string& extra_header_name = "",
              const std::string& extra_header_value = "");
int send_error(mg_connection* conn, int status, const std::string& message);
// A PNG image (body omitted for HEAD); 200.
int send_png(const Request& r, const std::string& png);
// The request's body parsed as JSON (bounded by max_request_bytes before it is read); discarded() on failure.
[[nodiscard]] nlohmann::json read_json_body(const Request& r);
// ?key=value of the query string, or "" when absent.
[[nodiscard]] std::string query_value(const Request& r, const char* key);

}  // namespace cellsight::hmi
