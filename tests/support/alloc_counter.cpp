// The one replaced operator new of the tests: counts while an AllocationWindow is open, outside UncountedScopes.
#include "tests/support/alloc_counter.hpp"

#include <atomic>
#include <cstdlib>
#include <new>

namespace {

std::atomic<bool> g_counting{false};
std::atomic<long> g_allocations{0};
// Constant-initialised, so reading it inside operator new never allocates.
thread_local int t_uncounted_depth = 0;

// Out of line on purpose: when GCC inlines these it pairs new-expressions with free() and warns
// (-Wmismatched-new-delete) although both sides are replaced consistently here.
[[gnu::noinline]] void* counted_malloc(std::size_t size) noexcept {
  if (g_counting.load(std::memory_order_relaxed) && t_uncounted_depth == 0) {
    g_allocations.fetch_add(1, std::memory_order_relaxed);
  }
  return std::malloc(size == 0 ? 1 : size);
}
[[gnu::noinline]] void* counted_new(std::size_t size) {
  void* memory = counted_malloc(size);
  if (memory == nullptr) throw std::bad_alloc();
  return memory;
}
[[gnu::noinline]] void counted_free(void* memory) noexcept {
  std::free(memory);
}

}  // namespace

// Every form that can release what the forms above return, or ASan reports a mismatch between ours and the library's.
[[gnu::noinline]] void* operator new(std::size_t size) {
  return counted_new(size);
}
[[gnu::noinline]] void* operator new[](std::size_t size) {
  return counted_new(size);
}
[[gnu::noinline]] void* operator new(std::size_t size, const std::nothrow_t& /*tag*/) noexcept {
  return counted_malloc(size);
}
[[gnu::noinline]] void* operator new[](std::size_t size, const std::nothrow_t& /*tag*/) noexcept {
  return counted_malloc(size);
}
[[gnu::noinline]] void operator delete(void* memory) noexcept {
  counted_free(memory);
}
[[gnu::noinline]] void operator delete[](void* memory) noexcept {
  counted_free(memory);
}
[[gnu::noinline]] void operator delete(void* memory, std::size_t /*size*/) noexcept {
  counted_free(memory);
}
[[gnu::noinline]] void operator delete[](void* memory, std::size_t /*size*/) noexcept {
  counted_free(memory);
}
[[gnu::noinline]] void operator delete(void* memory, const std::nothrow_t& /*tag*/) noexcept {
  counted_free(memory);
}
[[gnu::noinline]] void operator delete[](void* memory, const std::nothrow_t& /*tag*/) noexcept {
  counted_free(memory);
}

namespace cellsight::test {

AllocationWindow::AllocationWindow() {
  g_allocations.store(0);
  g_counting.store(true);
}
AllocationWindow::~AllocationWindow() {
  g_counting.store(false);
}
long AllocationWindow::count() const {
  return g_allocations.load();
}

UncountedScope::UncountedScope() {
  ++t_uncounted_depth;
}
UncountedScope::~UncountedScope() {
  --t_uncounted_depth;
}

}  // namespace cellsight::test
