// The loop's log lines, queued: the real-time thread formats a line into a fixed slot of a single-producer /
// single-consumer ring and goes on; a normal-priority writer thread hands the lines to log::write (one write(2)
// each, which can block on a slow journal or a full pipe). A full ring drops the line, counts it and says so later:
// the loop never waits for its log and never allocates for it.
#pragma once

#include <atomic>
#include <cstdarg>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string_view>
#include <thread>

#include "base/result.hpp"
#include "drivers/log.hpp"

namespace cellsight::runtime {

class LogQueue {
 public:
  // Longer lines are cut (log::write's own limit is 1 KiB; the loop's longest per-part line is about 200 bytes).
  static constexpr std::size_t kLineBytes = 448;

  struct Line {
    log::Level level = log::Level::kInfo;
    const char* component = "";  // a string literal: outlives the queue
    char text[kLineBytes] = {};
  };

  explicit LogQueue(std::size_t capacity);  // allocates the slots: start-up only
  ~LogQueue();                              // stop_writer()
  LogQueue(const LogQueue&) = delete;
  LogQueue& operator=(const LogQueue&) = delete;

  // ---- producer (one thread at a time; the loop thread once it runs) ----
  // Formats into the next free slot. False when the line was dropped because the ring is full (counted in
  // dropped()); a line below log::level() is not queued and not counted, as log::write would not write it.
  bool push(log::Level level, const char* component, const char* format, ...) __attribute__((format(printf, 4, 5)));
  bool vpush(log::Level level, const char* component, const char* format, va_list args);

  // ---- consumer (one thread: the writer, or the owner while no writer runs) ----
  // Hands every queued line, oldest first, to sink(const Line&); before them, when lines were dropped since the
  // last report, one warning line saying how many. Returns the number of lines handed over.
  template <class Sink>
  std::size_t drain(Sink&& sink);

  // Starts the writer thread, which drains into log::write as soon as lines arrive.
  [[nodiscard]] Status start_writer();
  // Ends the writer thread after a last drain (also without a writer: the queue is then drained here).
  void stop_writer();

  [[nodiscard]] std::size_t capacity() const { return capacity_; }
  [[nodiscard]] std::uint64_t pushed() const { return head_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t dropped() const { return dropped_.load(std::memory_order_relaxed); }
  // Lines queued and not yet taken by the consumer (a snapshot).
  [[nodiscard]] std::size_t size() const {
    return static_cast<std::size_t>(head_.load(std::memory_order_acquire) - tail_.load(std::memory_order_acquire));
  }

 private:
  void writer_thread();

  const std::size_t capacity_;
  std::unique_ptr<Line[]> lines_;
  // Monotonic counts: head_ written by the producer only, tail_ by the consumer only.
  std::atomic<std::uint64_t> head_{0};
  std::atomic<std::uint64_t> tail_{0};
  std::atomic<std::uint64_t> dropped_{0};
  std::uint64_t dropped_reported_ = 0;  // consumer only
  std::atomic<std::uint32_t> bell_{0};  // rung on every push and on stop: the writer's futex word
  std::atomic<bool> stop_{false};
  std::thread writer_;
};

template <class Sink>
std::size_t LogQueue::drain(Sink&& sink) {
  std::size_t handed = 0;
  const std::uint64_t dropped = dropped_.load(std::memory_order_relaxed);
  if (dropped != dropped_reported_) {
    Line report;
    report.level = log::Level::kWarn;
    report.component = "log";
    std::snprintf(report.text, sizeof report.text,
                  "%llu log lines of the loop dropped (queue of %zu full: the log writer fell behind)",
                  static_cast<unsigned long long>(dropped - dropped_reported_), capacity_);
    dropped_reported_ = dropped;
    sink(static_cast<const Line&>(report));
    ++handed;
  }
  std::uint64_t tail = tail_.load(std::memory_order_relaxed);
  const std::uint64_t head = head_.load(std::memory_order_acquire);  // the slots before head are written
  for (; tail != head; ++tail) {
    sink(static_cast<const Line&>(lines_[tail % capacity_]));
    ++handed;
    tail_.store(tail + 1, std::memory_order_release);  // the slot may be reused from here
  }
  return handed;
}

}  // namespace cellsight::runtime

namespace cellsight::runtime {

// How many conversions one queued line may have. Once any custom printf handler is registered, glibc formats every
// printf through printf_positional, which keeps the conversion specs in a 1 KiB buffer on the stack and mallocs a
// bigger one past it: with glibc 2.36, 15 or more conversions cost a 2 KiB malloc per call. libquadmath registers
// such a handler when it loads (it comes in with OpenCV's BLAS / LAPACK), so in cellsight a 17-conversion line
// allocated in the loop thread on every part (found by test_run_loop's RSS test under ASan). The macros below hold
// every loop format to the bound at compile time; a longer line is formatted in two steps (loop_publish.cpp).
inline constexpr int kMaxLogConversions = 14;

// The conversions of a printf format ("%%" is none).
constexpr int log_conversions(std::string_view format) {
  int count = 0;
  for (std::size_t i = 0; i < format.size(); ++i) {
    if (format[i] != '%') continue;
    if (i + 1 < format.size() && format[i + 1] == '%') {
      ++i;
      continue;
    }
    ++count;
  }
  return count;
}

}  // namespace cellsight::runtime

// The loop's logging: like CS_LOG_* (drivers/log.hpp), through a LogQueue. The format must be a literal within
// kMaxLogConversions.
#define CS_QLOG_AT(level, queue, component, format, ...)                                                     \
  do {                                                                                                       \
    static_assert(::cellsight::runtime::log_conversions(format) <= ::cellsight::runtime::kMaxLogConversions, \
                  "a loop log line with this many conversions makes glibc's printf allocate");               \
    (void)(queue).push(level, component, format __VA_OPT__(, ) __VA_ARGS__);                                 \
  } while (false)
#define CS_QLOG_DEBUG(queue, component, ...) CS_QLOG_AT(::cellsight::log::Level::kDebug, queue, component, __VA_ARGS__)
#define CS_QLOG_INFO(queue, component, ...) CS_QLOG_AT(::cellsight::log::Level::kInfo, queue, component, __VA_ARGS__)
#define CS_QLOG_WARN(queue, component, ...) CS_QLOG_AT(::cellsight::log::Level::kWarn, queue, component, __VA_ARGS__)
#define CS_QLOG_ERROR(queue, component, ...) CS_QLOG_AT(::cellsight::log::Level::kError, queue, component, __VA_ARGS__)
