// A fixed-capacity single-producer / single-consumer ring of trivially copyable records: the producer (a real-time
// thread) never waits and never allocates; a full ring drops the record and counts it. The slots are allocated once,
// in the constructor.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <type_traits>
#include <vector>

namespace cellsight::base {

template <class T>
class SpscRing {
  static_assert(std::is_trivially_copyable_v<T>, "records are copied into and out of the slots");

 public:
  explicit SpscRing(std::size_t capacity) : slots_(capacity == 0 ? 1 : capacity) {}
  SpscRing(const SpscRing&) = delete;
  SpscRing& operator=(const SpscRing&) = delete;

  // Producer only. False (and counted) when the consumer has not taken the oldest record yet.
  bool try_push(const T& record) {
    const std::uint64_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) >= slots_.size()) {
      dropped_.fetch_add(1, std::memory_order_relaxed);
      return false;
    }
    slots_[head % slots_.size()] = record;
    head_.store(head + 1, std::memory_order_release);
    return true;
  }

  // Consumer only. False when nothing is queued.
  bool try_pop(T& out) {
    const std::uint64_t tail = tail_.load(std::memory_order_relaxed);
    if (tail == head_.load(std::memory_order_acquire)) return false;
    out = slots_[tail % slots_.size()];
    tail_.store(tail + 1, std::memory_order_release);
    return true;
  }

  [[nodiscard]] std::size_t capacity() const { return slots_.size(); }
  [[nodiscard]] std::uint64_t pushed() const { return head_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t dropped() const { return dropped_.load(std::memory_order_relaxed); }

 private:
  std::vector<T> slots_;
  alignas(64) std::atomic<std::uint64_t> head_{0};  // next slot the producer fills
  alignas(64) std::atomic<std::uint64_t> tail_{0};  // next slot the consumer takes
  std::atomic<std::uint64_t> dropped_{0};
};

}  // namespace cellsight::base
