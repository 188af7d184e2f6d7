// Logging implementation: stack-formatted lines, one write(2) each.
#include "drivers/log.hpp"

#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstring>
#include <ctime>

namespace cellsight::log {
namespace {
std::atomic<int> g_level{static_cast<int>(Level::kInfo)};  // process-wide by nature: one stderr per process
constexpr const char* kNames[] = {"DEBUG", "INFO", "WARN", "ERROR"};
constexpr std::size_t kLineBytes = 1024;
}  // namespace

void set_level(Level level) {
  g_level.store(static_cast<int>(level), std::memory_order_relaxed);
}
Level level() {
  return static_cast<Level>(g_level.load(std::memory_order_relaxed));
}

bool parse_level(const char* text, Level& out) {
  static constexpr struct {
    const char* name;
    Level level;
  } kTable[] = {{"debug", Level::kDebug},
                {"info", Level::kInfo},
                {"warn", Level::kWarn},
                {"error", Level::kError},
                {"off", Level::kOff}};
  for (const auto& entry : kTable) {
    if (std::strcmp(text, entry.name) == 0) {
      out = entry.level;
      return true;
    }
  }
  return false;
}

void write(Level lvl, const char* component, const char* format, ...) {
  if (static_cast<int>(lvl) < g_level.load(std::memory_order_relaxed) || lvl == Level::kOff) return;
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  char line[kLineBytes];
  int used = std::snprintf(line, sizeof line, "%lld.%03ld %s %s: ", static_cast<long long>(now.tv_sec),
                           now.tv_nsec / 1000000, kNames[static_cast<int>(lvl)], component);
  if (used < 0) return;
  va_list args;
  va_start(args, format);
  int body = std::vsnprintf(line + used, sizeof line - static_cast<std::size_t>(used), format, args);
  va_end(args);
  std::size_t length = static_cast<std::size_t>(used) + (body > 0 ? static_cast<std::size_t>(body) : 0);
  if (length > sizeof line - 2) length = sizeof line - 2;  // truncated lines still end cleanly
  line[length++] = '\n';
  ssize_t ignored = ::write(STDERR_FILENO, line, length);
  (void)ignored;  // nowhere left to report a failing stderr
}

}  // namespace cellsight::log
