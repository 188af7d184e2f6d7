// The loop's log queue and its writer thread.
#include "runtime/log_queue.hpp"

#include <algorithm>

#include "base/start_thread.hpp"
#include "runtime/futex.hpp"

namespace cellsight::runtime {

namespace {
// Where a queued line goes: the process log, as a direct log::write would have put it.
void write_line(const LogQueue::Line& line) {
  log::write(line.level, line.component, "%s", line.text);
}
}  // namespace

LogQueue::LogQueue(std::size_t capacity)
    : capacity_(std::max<std::size_t>(1, capacity)), lines_(std::make_unique<Line[]>(capacity_)) {}

LogQueue::~LogQueue() {
  stop_writer();
}

bool LogQueue::push(log::Level level, const char* component, const char* format, ...) {
  va_list args;
  va_start(args, format);
  const bool queued = vpush(level, component, format, args);
  va_end(args);
  return queued;
}

bool LogQueue::vpush(log::Level level, const char* component, const char* format, va_list args) {
  if (level == log::Level::kOff || static_cast<int>(level) < static_cast<int>(log::level())) return true;
  const std::uint64_t head = head_.load(std::memory_order_relaxed);
  if (head - tail_.load(std::memory_order_acquire) >= capacity_) {  // the writer has not freed a slot yet
    dropped_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  Line& line = lines_[head % capacity_];
  line.level = level;
  line.component = component;
  std::vsnprintf(line.text, sizeof line.text, format, args);  // cuts a longer line; stack only
  head_.store(head + 1, std::memory_order_release);
  futex_ring(bell_);
  return true;
}

Status LogQueue::start_writer() {
  if (writer_.joinable()) return make_error("log queue: start_writer() called twice");
  stop_.store(false, std::memory_order_release);
  return base::start_thread(writer_, "cs-log", [this] { writer_thread(); });
}

void LogQueue::stop_writer() {
  stop_.store(true, std::memory_order_release);
  futex_ring(bell_);
  if (writer_.joinable()) writer_.join();
  (void)drain(write_line);
}

void LogQueue::writer_thread() {
  for (;;) {
    // The bell before the ring: a push after this load changes the bell, so the wait below does not sleep past it.
    const std::uint32_t bell = bell_.load(std::memory_order_acquire);
    (void)drain(write_line);
    if (stop_.load(std::memory_order_acquire)) return;  // stop_writer() drains what came after
    futex_wait(bell_, bell);
  }
}

}  // namespace cellsight::runtime
