#include "hmi/sessions.hpp"

#include <sys/random.h>

#include <array>
#include <cerrno>

namespace cellsight::hmi {

std::string random_token(std::size_t bytes) {
  std::string raw(bytes, '\0');
  std::size_t got = 0;
  while (got < bytes) {
    const ssize_t n = ::getrandom(raw.data() + got, bytes - got, 0);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return {};
    got += static_cast<std::size_t>(n);
  }
  static constexpr std::array<char, 16> kHex = {'0', '1', '2', '3', '4', '5', '6', '7',
                                                '8', '9', 'a', 'b', 'c', 'd', 'e', 'f'};
  std::string out;
  out.reserve(2 * bytes);
  for (const char c : raw) {
    const auto b = static_cast<unsigned char>(c);
    out += kHex[b >> 4U];
    out += kHex[b & 0xFU];
  }
  return out;
}

std::optional<Session> SessionTable::create(const std::string& user, Role role, HmiClock::time_point now) {
  Session s{random_token(), random_token(), user, role, now};
  if (s.token.empty() || s.csrf.empty()) return std::nullopt;
  const std::lock_guard<std::mutex> lock(mutex_);
  expire(now);
  while (sessions_.size() >= max_sessions_) {  // the least recently used goes
    auto oldest = sessions_.begin();
    for (auto it = sessions_.begin(); it != sessions_.end(); ++it) {
      if (it->second.last_used < oldest->second.last_used) oldest = it;
    }
    sessions_.erase(oldest);
  }
  sessions_[s.token] = s;
  return s;
}

std::optional<Session> SessionTable::find(const std::string& token, HmiClock::time_point now) {
  const std::lock_guard<std::mutex> lock(mutex_);
  expire(now);
  const auto it = sessions_.find(token);
  if (it == sessions_.end()) return std::nullopt;
  it->second.last_used = now;
  return it->second;
}

void SessionTable::remove(const std::string& token) {
  const std::lock_guard<std::mutex> lock(mutex_);
  sessions_.erase(token);
}

std::size_t SessionTable::size() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  return sessions_.size();
}

void SessionTable::expire(HmiClock::time_point now) {
  for (auto it = sessions_.begin(); it != sessions_.end();) {
    it = now - it->second.last_used > idle_timeout_ ? sessions_.erase(it) : std::next(it);
  }
}

long LoginBrake::locked_for_s(const std::string& address, HmiClock::time_point now) {
  const std::lock_guard<std::mutex> lock(mutex_);
  auto it = entries_.find(address);
  // A newcomer while the table is full would be counted under the shared entry (failed()): its lock applies.
  if (it == entries_.end() && entries_.size() >= max_addresses_) it = entries_.find(kShared);
  if (it == entries_.end() || it->second.locked_until <= now) return 0;
  return static_cast<long>(std::chrono::ceil<std::chrono::seconds>(it->second.locked_until - now).count());
}

void LoginBrake::failed(const std::string& address, HmiClock::time_point now) {
  const std::lock_guard<std::mutex> lock(mutex_);
  if (entries_.size() >= max_addresses_ && entries_.count(address) == 0) {
    // Forget the addresses that are not locked; if every one is, the table stays full and the newcomer is counted
    // under a shared entry, which locks all such newcomers together (a spraying attacker locks only itself out).
    for (auto it = entries_.begin(); it != entries_.end();) {
      // The shared entry keeps its count until its lock has been served, or newcomers would never be locked.
      const bool shared_counting = it->first == kShared && it->second.locked_until == HmiClock::time_point{};
      it = it->second.locked_until <= now && !shared_counting ? entries_.erase(it) : std::next(it);
    }
  }
  const bool known = entries_.count(address) != 0;
  Entry& e = known || entries_.size() < max_addresses_ ? entries_[address] : entries_[kShared];
  if (e.locked_until != HmiClock::time_point{} && e.locked_until <= now) e = Entry{};  // lock served: start over
  if (++e.failures >= max_failures_) e.locked_until = now + lockout_;
}

void LoginBrake::succeeded(const std::string& address) {
  const std::lock_guard<std::mutex> lock(mutex_);
  entries_.erase(address);
}

}  // namespace cellsight::hmi
