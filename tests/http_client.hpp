// One HTTP request to a test's server with civetweb's client (Connection: close), and its reply: for the tests of
// the operator's screen (test_hmi, test_hmi_parts).
#pragma once

#include <civetweb.h>

#include <catch2/catch.hpp>
#include <map>
#include <nlohmann/json.hpp>
#include <string>

namespace cellsight::test {

struct Reply {
  int status = 0;
  std::map<std::string, std::string> headers;
  std::string body;
  [[nodiscard]] nlohmann::json as_json() const { return nlohmann::json::parse(body, nullptr, false); }
};

inline Reply http(const std::string& host, int port, const std::string& method, const std::string& path,
                  const std::string& body = "", const std::map<std::string, std::string>& headers = {}) {
  char error[256] = {};
  mg_connection* conn = mg_connect_client(host.c_str(), port, 0, error, sizeof error);
  INFO(error);
  REQUIRE(conn != nullptr);
  std::string request = method + " " + path + " HTTP/1.1\r\nHost: " + host + "\r\nConnection: close\r\n";
  for (const auto& [k, v] : headers) request += k + ": " + v + "\r\n";
  if (!body.empty() || method == "POST") request += "Content-Length: " + std::to_string(body.size()) + "\r\n";
  request += "\r\n";
  mg_write(conn, request.data(), request.size());
  if (!body.empty()) mg_write(conn, body.data(), body.size());
  Reply reply;
  if (mg_get_response(conn, error, sizeof error, 10000) >= 0) {
    const mg_response_info* info = mg_get_response_info(conn);
    reply.status = info->status_code;
    for (int i = 0; i < info->num_headers; ++i) reply.headers[info->http_headers[i].name] = info->http_headers[i].value;
    char buffer[4096];
    int n = 0;
    while ((n = mg_read(conn, buffer, sizeof buffer)) > 0) reply.body.append(buffer, static_cast<std::size_t>(n));
  }
  mg_close_connection(conn);
  return reply;
}

// Logs in as `user` and returns the headers a state-changing request of that session needs (cookie, CSRF token).
inline std::map<std::string, std::string> session_headers(int port, const std::string& user,
                                                          const std::string& password) {
  const Reply login =
      http("127.0.0.1", port, "POST", "/api/login", nlohmann::json{{"user", user}, {"password", password}}.dump());
  REQUIRE(login.status == 200);
  const std::string cookie = login.headers.at("Set-Cookie");
  return {{"Cookie", cookie.substr(0, cookie.find(';'))},
          {"X-CSRF-Token", login.as_json().at("csrf").get<std::string>()}};
}

}  // namespace cellsight::test
