// Tests of runtime/log_queue: the production loop's log lines go through a fixed ring to a writer thread. Order is
// kept, a full ring drops (never waits), drops are counted and reported, and queuing a line allocates nothing.
#include <atomic>
#include <catch2/catch.hpp>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "drivers/log.hpp"
#include "runtime/log_queue.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using namespace cellsight;
using runtime::LogQueue;
using Clock = std::chrono::steady_clock;

struct Captured {
  log::Level level;
  std::string component;
  std::string text;
};

std::vector<Captured> drain_all(LogQueue& queue) {
  std::vector<Captured> out;
  (void)queue.drain([&out](const LogQueue::Line& line) { out.push_back({line.level, line.component, line.text}); });
  return out;
}

// Sets the process's log level for one test and puts it back.
struct LevelScope {
  explicit LevelScope(log::Level level) : saved(log::level()) { log::set_level(level); }
  ~LevelScope() { log::set_level(saved); }
  log::Level saved;
};

TEST_CASE("log queue: lines come out in the order they went in, with level, component and text", "[log_queue]") {
  const LevelScope level(log::Level::kDebug);
  LogQueue queue(8);
  for (int i = 0; i < 5; ++i) CHECK(queue.push(log::Level::kInfo, "loop", "line %d of %s", i, "five"));
  CHECK(queue.push(log::Level::kError, "loop", "fault: %u", 3u));
  const auto lines = drain_all(queue);
  REQUIRE(lines.size() == 6);
  for (int i = 0; i < 5; ++i) {
    CHECK(lines[static_cast<std::size_t>(i)].text == "line " + std::to_string(i) + " of five");
    CHECK(lines[static_cast<std::size_t>(i)].level == log::Level::kInfo);
    CHECK(lines[static_cast<std::size_t>(i)].component == "loop");
  }
  CHECK(lines[5].level == log::Level::kError);
  CHECK(lines[5].text == "fault: 3");
  CHECK(drain_all(queue).empty());  // each line once
}

TEST_CASE("log queue: the ring wraps around its slots many times without losing order", "[log_queue]") {
  LogQueue queue(4);
  int next_expected = 0;
  for (int round = 0; round < 50; ++round) {
    for (int i = 0; i < 3; ++i) REQUIRE(queue.push(log::Level::kWarn, "loop", "%d", round * 3 + i));
    for (const auto& line : drain_all(queue)) CHECK(std::atoi(line.text.c_str()) == next_expected++);
  }
  CHECK(next_expected == 150);
  CHECK(queue.dropped() == 0);
}

TEST_CASE("log queue: a full ring drops the line at once, counts it and reports the count before the next lines",
          "[log_queue]") {
  LogQueue queue(4);
  for (int i = 0; i < 4; ++i) REQUIRE(queue.push(log::Level::kInfo, "loop", "kept %d", i));
  // When the writer has not caught up: no wait (the producer is the real-time thread), the line is dropped.
  const auto before = Clock::now();
  for (int i = 0; i < 3; ++i) CHECK_FALSE(queue.push(log::Level::kInfo, "loop", "dropped %d", i));
  CHECK(Clock::now() - before < std::chrono::milliseconds(50));
  CHECK(queue.dropped() == 3);
  auto lines = drain_all(queue);
  REQUIRE(lines.size() == 5);
  CHECK(lines[0].level == log::Level::kWarn);
  CHECK(lines[0].component == "log");
  CHECK(lines[0].text.rfind("3 log lines of the loop dropped", 0) == 0);
  for (int i = 0; i < 4; ++i) CHECK(lines[static_cast<std::size_t>(i) + 1].text == "kept " + std::to_string(i));
  // Reported once: the next drain has only the new line; a new drop is reported with its own count.
  REQUIRE(queue.push(log::Level::kInfo, "loop", "after"));
  lines = drain_all(queue);
  REQUIRE(lines.size() == 1);
  CHECK(lines[0].text == "after");
  for (int i = 0; i < 5; ++i) (void)queue.push(log::Level::kInfo, "loop", "x");
  lines = drain_all(queue);
  REQUIRE(lines.size() == 5);
  CHECK(lines[0].text.rfind("1 log lines of the loop dropped", 0) == 0);
  CHECK(queue.dropped() == 4);
}

TEST_CASE("log queue: lines below the log level are neither queued nor counted as dropped", "[log_queue]") {
  const LevelScope level(log::Level::kInfo);
  LogQueue queue(2);
  CHECK(queue.push(log::Level::kDebug, "loop", "state change"));
  CHECK(queue.pushed() == 0);
  CHECK(queue.dropped() == 0);
  CHECK(drain_all(queue).empty());
}

TEST_CASE("log queue: a line longer than a slot is cut, not spilled", "[log_queue]") {
  LogQueue queue(2);
  const std::string longer(LogQueue::kLineBytes * 2, 'a');
  REQUIRE(queue.push(log::Level::kInfo, "loop", "%s", longer.c_str()));
  const auto lines = drain_all(queue);
  REQUIRE(lines.size() == 1);
  CHECK(lines[0].text == std::string(LogQueue::kLineBytes - 1, 'a'));
}

TEST_CASE("log queue: queuing a line allocates nothing (the loop thread's side)", "[log_queue][alloc]") {
  LogQueue queue(16);  // the slots: start-up
  long allocations = 0;
  {
    const test::AllocationWindow window;
    for (int i = 0; i < 40; ++i) {
      (void)queue.push(log::Level::kInfo, "loop", "acq %u ok: part %.*s p %.3f cycle %.1f ms", 7u, 4, "gear", 0.97,
                       12.5);
    }
    allocations = window.count();
  }
  CHECK(allocations == 0);
  CHECK(queue.dropped() == 24);
  CHECK(drain_all(queue).size() == 17);  // the 16 lines and the drop report, here rather than on stderr
}

TEST_CASE("log queue: a consumer on another thread gets every line in order or the line is counted as dropped",
          "[log_queue][thread]") {
  LogQueue queue(8);
  constexpr int kLines = 20000;
  std::atomic<bool> producer_done{false};
  std::vector<int> seen;
  seen.reserve(kLines);
  std::thread consumer([&] {
    const auto take = [&seen](const LogQueue::Line& line) {
      if (std::strcmp(line.component, "test") == 0) seen.push_back(std::atoi(line.text));
    };
    while (!producer_done.load(std::memory_order_acquire)) (void)queue.drain(take);
    (void)queue.drain(take);
  });
  int queued = 0;
  for (int i = 0; i < kLines; ++i) {
    if (queue.push(log::Level::kError, "test", "%d", i)) ++queued;
  }
  producer_done.store(true, std::memory_order_release);
  consumer.join();
  CHECK(static_cast<std::uint64_t>(queued) + queue.dropped() == kLines);
  REQUIRE(seen.size() == static_cast<std::size_t>(queued));
  bool increasing = true;
  for (std::size_t i = 1; i < seen.size(); ++i) increasing = increasing && seen[i] > seen[i - 1];
  CHECK(increasing);
}

TEST_CASE("log queue: the writer thread takes the lines off the ring, and stopping it leaves nothing behind",
          "[log_queue][thread]") {
  LogQueue queue(4);
  REQUIRE(queue.start_writer());
  // Error lines pass any log level; each is written once to stderr by the writer.
  for (int i = 0; i < 3; ++i) REQUIRE(queue.push(log::Level::kError, "test", "log queue test line %d of 3", i + 1));
  // The writer is woken by the push: the ring empties without anyone else draining it.
  const auto deadline = Clock::now() + std::chrono::seconds(5);
  while (queue.size() > 0 && Clock::now() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  CHECK(queue.size() == 0);
  queue.stop_writer();
  CHECK(queue.pushed() == 3);
  CHECK(queue.dropped() == 0);
  CHECK(drain_all(queue).empty());
}

}  // namespace
