// The one thread pool of the project's data-parallel loops (see the header for what it is not for).
#include "base/parallel_for.hpp"

#include <algorithm>
#include <system_error>
#include <thread>
#include <vector>

namespace cellsight::base {

int hardware_threads() {
  return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
}

bool parallel_for(int count, int threads, const std::function<bool(int index, int worker)>& task,
                  const std::atomic<bool>* stop) {
  std::atomic<int> next{0};
  std::atomic<bool> ended_early{false};
  const auto run = [&](int worker) {
    for (;;) {
      // Checked before an index is taken, so a stop or a failure ends every worker after its current task.
      if (ended_early.load() || (stop != nullptr && stop->load(std::memory_order_relaxed))) {
        ended_early.store(true);
        return;
      }
      const int i = next.fetch_add(1);
      if (i >= count) return;
      if (!task(i, worker)) ended_early.store(true);
    }
  };
  std::vector<std::thread> pool;
  const int wanted = std::clamp(threads, 1, std::max(1, count));
  for (int t = 1; t < wanted; ++t) {
    try {
      pool.emplace_back(run, t);
    } catch (const std::system_error&) {
      break;  // no more threads available: the ones we have (at least this one) finish the work
    }
  }
  run(0);
  for (std::thread& t : pool) t.join();
  return !ended_early.load();
}

}  // namespace cellsight::base
