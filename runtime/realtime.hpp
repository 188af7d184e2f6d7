// Real-time set-up of the production loop: locked memory, SCHED_FIFO for the calling thread, a pre-faulted stack.
// Each returns 0 or the errno value, so the caller decides how to report it (the loop thread through its log queue).
#pragma once

namespace cellsight::runtime {

// mlockall(MCL_CURRENT | MCL_FUTURE): no page of the process is paged out or faulted in lazily later.
[[nodiscard]] int lock_all_memory();

// SCHED_FIFO at `priority` (1..99) for the calling thread.
[[nodiscard]] int set_thread_fifo(int priority);

// Touches the next 64 KiB of the calling thread's stack, so its page faults happen now and not in the first part.
void prefault_stack();

}  // namespace cellsight::runtime
