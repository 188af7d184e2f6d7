// Wait and wake on a 32-bit atomic word through futex(2): how the real-time loop thread and its helper threads wake
// each other without a mutex. A waiter sleeps only while the word still holds the value it saw, so a wake that comes
// first is never lost, and the waker takes no lock (the loop never waits for a lower-priority thread to unlock).
#pragma once

#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <climits>
#include <cstdint>
#include <ctime>

namespace cellsight::runtime {

static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t) &&
                  std::atomic<std::uint32_t>::is_always_lock_free,
              "futex(2) works on the plain 32-bit word inside the atomic");

// Sleeps while `word` equals `expected`, at most `timeout`. May return early (a signal, a wake for another value):
// callers re-check their condition in a loop.
inline void futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected, std::chrono::nanoseconds timeout) {
  if (timeout <= std::chrono::nanoseconds::zero()) return;
  constexpr std::int64_t kNsPerS = 1'000'000'000;
  const std::int64_t ns = timeout.count();
  timespec relative{};
  relative.tv_sec = static_cast<time_t>(ns / kNsPerS);
  relative.tv_nsec = static_cast<long>(ns % kNsPerS);
  (void)syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&word), FUTEX_WAIT_PRIVATE, expected, &relative, nullptr,
                0);
}

// Without a time limit: for threads that have nothing else to do (the recognition worker, the log writer).
inline void futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected) {
  (void)syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&word), FUTEX_WAIT_PRIVATE, expected, nullptr, nullptr, 0);
}

// Wakes every thread sleeping on `word`. Never blocks; a system call only, safe on the real-time thread.
inline void futex_wake_all(std::atomic<std::uint32_t>& word) {
  (void)syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&word), FUTEX_WAKE_PRIVATE, INT_MAX, nullptr, nullptr, 0);
}

// Changes `word` and wakes its sleepers: the one-line "ring the bell" of the hand-offs.
inline void futex_ring(std::atomic<std::uint32_t>& word) {
  word.fetch_add(1, std::memory_order_release);
  futex_wake_all(word);
}

}  // namespace cellsight::runtime
