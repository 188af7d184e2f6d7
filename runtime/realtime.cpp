// Real-time set-up: the system calls behind LoopConfig::lock_memory and realtime_priority.
#include "runtime/realtime.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>

#include <cerrno>
#include <cstddef>

namespace cellsight::runtime {

namespace {
// Stack the loop thread touches at start so its page faults happen before the first part (with mlockall).
constexpr std::size_t kStackPrefaultBytes = std::size_t{64} * 1024;
constexpr std::size_t kPageBytes = 4096;
}  // namespace

int lock_all_memory() {
  return mlockall(MCL_CURRENT | MCL_FUTURE) == 0 ? 0 : errno;
}

int set_thread_fifo(int priority) {
  sched_param param{};
  param.sched_priority = priority;
  return pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
}

[[gnu::noinline]] void prefault_stack() {
  volatile char stack[kStackPrefaultBytes];
  for (std::size_t i = 0; i < sizeof stack; i += kPageBytes) stack[i] = 0;
}

}  // namespace cellsight::runtime
