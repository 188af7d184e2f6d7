// A data-parallel loop on a few short-lived threads: training's cross-validation, feature extraction, simulated
// teaching passes. Not for the long-lived real-time threads (production loop, Modbus server, encoder).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <functional>
#include <optional>
#include <vector>

namespace cellsight::base {

// std::thread::hardware_concurrency(), at least 1 (the standard allows 0 for "unknown").
[[nodiscard]] int hardware_threads();

// Runs task(index, worker) for every index in [0, count) on up to `threads` threads, the caller's included (never
// more threads than indices); each worker takes the next index when it has finished the last one and `worker` in
// [0, threads) says which thread runs it, for state a thread keeps between its tasks. Joins every thread before it
// returns. A thread the system refuses to create is done without: the threads there are finish the work.
// Returns true when every task ran and returned true. Once a task returns false, or `stop` is seen set before an
// index is taken, no further index is handed out and the result is false: some tasks did not run, and the
// caller discards the lot.
[[nodiscard]] bool parallel_for(int count, int threads, const std::function<bool(int index, int worker)>& task,
                                const std::atomic<bool>* stop = nullptr);

// parallel_for for tasks that need state of their own on each thread (a scan preparer, a matcher: costly to build,
// not to be shared): a thread builds its State from `args` on itself before its first task and hands it to every
// task it runs, task(index, state) -> bool. Threads that get no index build none.
template <class State, class Task, class... Args>
[[nodiscard]] bool parallel_for_with_state(int count, int threads, const std::atomic<bool>* stop, Task&& task,
                                           const Args&... args) {
  std::vector<std::optional<State>> states(static_cast<std::size_t>(std::max(1, threads)));
  return parallel_for(
      count, threads,
      [&](int index, int worker) {
        std::optional<State>& state = states[static_cast<std::size_t>(worker)];
        if (!state) state.emplace(args...);
        return task(index, *state);
      },
      stop);
}

}  // namespace cellsight::base
