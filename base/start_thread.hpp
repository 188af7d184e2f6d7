// Starting a named thread without letting an exception out: std::thread reports "no more threads" by throwing
// std::system_error, which start-up turns into a Status for the person reading the message.
#pragma once

#include <pthread.h>

#include <string>
#include <system_error>
#include <thread>
#include <utility>

#include "base/result.hpp"

namespace cellsight::base {

// Starts `body` on a new thread in `out` (which must not hold a running thread). `name` (at most 15 characters,
// the kernel's limit) shows in `top -H`, gdb and the journal, so a stuck thread can be told apart from the others.
template <class Body>
[[nodiscard]] Status start_thread(std::thread& out, const char* name, Body&& body) {
  try {
    out = std::thread(std::forward<Body>(body));
  } catch (const std::system_error& error) {
    return make_error(std::string("cannot start the thread '") + name + "': " + error.what());
  }
  (void)pthread_setname_np(out.native_handle(), name);  // cosmetic: a name too long is refused, the thread still runs
  return {};
}

}  // namespace cellsight::base
