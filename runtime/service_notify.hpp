// systemd service protocol (sd_notify): READY=1 once serving, WATCHDOG=1 while the production loop is healthy,
// STOPPING=1 on shutdown. Every call is a no-op when cellsight does not run under systemd ($NOTIFY_SOCKET unset).
#pragma once

#include <atomic>
#include <cstdint>

namespace cellsight::runtime {

class ServiceNotifier {
 public:
  // Reads $NOTIFY_SOCKET and the watchdog interval (sd_watchdog_enabled: $WATCHDOG_USEC for this process).
  ServiceNotifier();

  // True when systemd expects WATCHDOG=1 (WatchdogSec= in the unit).
  [[nodiscard]] bool watchdog_enabled() const { return watchdog_interval_us_ > 0; }
  [[nodiscard]] std::uint64_t watchdog_interval_us() const { return watchdog_interval_us_; }
  // How often pet_watchdog() really sends: half the interval, as sd_watchdog_enabled(3) recommends.
  [[nodiscard]] std::int64_t pet_period_ns() const { return pet_period_ns_; }

  // STATUS= is the one line `systemctl status` shows; the text must be a string literal or otherwise outlive the
  // call (it is copied into a stack buffer with the state, never allocated).
  void ready(const char* status);
  void stopping();
  void status(const char* status);
  // Call from the loop on every healthy iteration; sends WATCHDOG=1 at most every pet_period_ns(). Thread-safe;
  // no allocation in cellsight's code (libsystemd sends one datagram).
  void pet_watchdog(std::int64_t now_ns);

  // Counters for logs and tests.
  [[nodiscard]] std::uint64_t watchdog_pets() const { return pets_.load(std::memory_order_relaxed); }
  [[nodiscard]] bool under_systemd() const { return under_systemd_; }

 private:
  void send(const char* state);

  std::uint64_t watchdog_interval_us_ = 0;
  std::int64_t pet_period_ns_ = 0;
  std::atomic<std::int64_t> last_pet_ns_{0};
  std::atomic<std::uint64_t> pets_{0};
  bool under_systemd_ = false;
};

}  // namespace cellsight::runtime
