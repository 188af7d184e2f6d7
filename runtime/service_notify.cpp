// sd_notify wrapper of the systemd unit (scripts/cellsight.service).
#include "runtime/service_notify.hpp"

#include <systemd/sd-daemon.h>

#include <cstdio>
#include <cstdlib>

#include "drivers/log.hpp"

namespace cellsight::runtime {
namespace {
constexpr const char* kComponent = "service";
constexpr std::int64_t kNsPerUs = 1000;
constexpr std::size_t kStateBytes = 256;
}  // namespace

ServiceNotifier::ServiceNotifier() {
  const char* socket = std::getenv("NOTIFY_SOCKET");
  under_systemd_ = socket != nullptr && socket[0] != '\0';
  std::uint64_t usec = 0;
  // > 0: this process is the one systemd watches (the PID in $WATCHDOG_PID, when given, matches).
  if (sd_watchdog_enabled(0, &usec) > 0 && usec > 0) {
    watchdog_interval_us_ = usec;
    pet_period_ns_ = static_cast<std::int64_t>(usec / 2) * kNsPerUs;
    CS_LOG_INFO(kComponent, "systemd watchdog: %.0f ms (WATCHDOG=1 every %.0f ms while healthy)",
                static_cast<double>(usec) * 1e-3, static_cast<double>(usec) * 0.5e-3);
  }
}

void ServiceNotifier::send(const char* state) {
  if (!under_systemd_) return;
  const int sent = sd_notify(0, state);
  if (sent < 0) CS_LOG_WARN(kComponent, "sd_notify failed (%d)", sent);
}

void ServiceNotifier::ready(const char* status_text) {
  char state[kStateBytes];
  std::snprintf(state, sizeof state, "READY=1\nSTATUS=%s", status_text);
  send(state);
}

void ServiceNotifier::stopping() {
  send("STOPPING=1\nSTATUS=stopping");
}

void ServiceNotifier::status(const char* status_text) {
  char state[kStateBytes];
  std::snprintf(state, sizeof state, "STATUS=%s", status_text);
  send(state);
}

void ServiceNotifier::pet_watchdog(std::int64_t now_ns) {
  if (watchdog_interval_us_ == 0) return;
  std::int64_t last = last_pet_ns_.load(std::memory_order_relaxed);
  if (last != 0 && now_ns - last < pet_period_ns_) return;
  if (!last_pet_ns_.compare_exchange_strong(last, now_ns, std::memory_order_relaxed)) return;  // another thread did
  pets_.fetch_add(1, std::memory_order_relaxed);
  send("WATCHDOG=1");
}

}  // namespace cellsight::runtime
