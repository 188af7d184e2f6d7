// Logged-in browsers and the login brake. A session is a random 256-bit token in an HttpOnly, SameSite=Strict cookie,
// with a second random token the page must send in X-CSRF-Token on every state-changing request. Sessions expire
// after a time without use and their number is bounded (the oldest goes). The brake counts failed logins per client
// address: after max_failures in a row that address is refused for lockout_s, whatever it sends.
#pragma once

#include <chrono>
#include <cstddef>
#include <map>
#include <mutex>
#include <optional>
#include <string>

#include "hmi/users.hpp"

namespace cellsight::hmi {

using HmiClock = std::chrono::steady_clock;

struct Session {
  std::string token;
  std::string csrf;
  std::string user;
  Role role = Role::kNone;
  HmiClock::time_point last_used{};
};

// 2 * bytes lower-case hex digits from getrandom(2); empty if the kernel has no entropy to give (never a weak token).
[[nodiscard]] std::string random_token(std::size_t bytes = 32);

class SessionTable {
 public:
  SessionTable(std::chrono::seconds idle_timeout, std::size_t max_sessions)
      : idle_timeout_(idle_timeout), max_sessions_(max_sessions == 0 ? 1 : max_sessions) {}

  // A new session; nullopt when no random token could be made.
  [[nodiscard]] std::optional<Session> create(const std::string& user, Role role, HmiClock::time_point now);
  // The live session of `token` (its idle time restarts), or nullopt.
  [[nodiscard]] std::optional<Session> find(const std::string& token, HmiClock::time_point now);
  void remove(const std::string& token);
  [[nodiscard]] std::size_t size() const;

 private:
  void expire(HmiClock::time_point now);  // with mutex_ held

  mutable std::mutex mutex_;
  std::map<std::string, Session> sessions_;
  std::chrono::seconds idle_timeout_;
  std::size_t max_sessions_;
};

class LoginBrake {
 public:
  // max_addresses bounds the table (memory against address-spraying clients); when every one of them is locked,
  // newcomers are counted together under one shared entry and locked out together.
  LoginBrake(int max_failures, std::chrono::seconds lockout, std::size_t max_addresses = 4096)
      : max_addresses_(max_addresses), max_failures_(max_failures), lockout_(lockout) {}

  // Seconds the address must still wait (0: it may try); for a newcomer while the table is full, the shared entry's.
  [[nodiscard]] long locked_for_s(const std::string& address, HmiClock::time_point now);
  void failed(const std::string& address, HmiClock::time_point now);
  void succeeded(const std::string& address);

 private:
  struct Entry {
    int failures = 0;
    HmiClock::time_point locked_until{};
  };
  static constexpr const char* kShared = "(many addresses)";
  std::size_t max_addresses_;
  std::mutex mutex_;
  std::map<std::string, Entry> entries_;
  int max_failures_;
  std::chrono::seconds lockout_;
};

}  // namespace cellsight::hmi
