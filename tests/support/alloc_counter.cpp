// The one replaced operator new (and, outside the sanitizers, malloc) of the tests: counts while an AllocationWindow is
// open, outside UncountedScopes.
#include "tests/support/alloc_counter.hpp"

#include <atomic>
#include <cerrno>
#include <cstdlib>
#include <new>

// Outside the sanitizers, C's malloc family is counted as well: C code and libraries allocate without operator new
// (glibc's printf did, in the loop thread, once per part: see runtime/log_queue.hpp). glibc allows replacing malloc;
// these forward to its own implementation. Under ASan and TSan the sanitizer owns malloc, so only new is counted.
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define CS_COUNT_MALLOC 0
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer) || __has_feature(memory_sanitizer)
#define CS_COUNT_MALLOC 0
#endif
#endif
#ifndef CS_COUNT_MALLOC
#define CS_COUNT_MALLOC 1
#endif

#if CS_COUNT_MALLOC
extern "C" {
void* __libc_malloc(std::size_t size);
void* __libc_calloc(std::size_t count, std::size_t size);
void* __libc_realloc(void* memory, std::size_t size);
void* __libc_memalign(std::size_t alignment, std::size_t size);
}
#endif

namespace {

std::atomic<bool> g_counting{false};
std::atomic<long> g_allocations{0};
// Constant-initialised, so reading it inside operator new never allocates.
thread_local int t_uncounted_depth = 0;

void count_one() noexcept {
  if (g_counting.load(std::memory_order_relaxed) && t_uncounted_depth == 0) {
    g_allocations.fetch_add(1, std::memory_order_relaxed);
  }
}

// Out of line on purpose: when GCC inlines these it pairs new-expressions with free() and warns
// (-Wmismatched-new-delete) although both sides are replaced consistently here.
[[gnu::noinline]] void* counted_malloc(std::size_t size) noexcept {
#if CS_COUNT_MALLOC
  count_one();
  return __libc_malloc(size == 0 ? 1 : size);  // not malloc(): that would count it twice
#else
  count_one();
  return std::malloc(size == 0 ? 1 : size);
#endif
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

#if CS_COUNT_MALLOC
// free() stays glibc's: every block below comes from glibc's allocator.
extern "C" {
void* malloc(std::size_t size) noexcept {
  count_one();
  return __libc_malloc(size);
}
void* calloc(std::size_t count, std::size_t size) noexcept {
  count_one();
  return __libc_calloc(count, size);
}
void* realloc(void* memory, std::size_t size) noexcept {
  count_one();
  return __libc_realloc(memory, size);
}
void* memalign(std::size_t alignment, std::size_t size) noexcept {
  count_one();
  return __libc_memalign(alignment, size);
}
void* aligned_alloc(std::size_t alignment, std::size_t size) noexcept {
  count_one();
  return __libc_memalign(alignment, size);
}
int posix_memalign(void** out, std::size_t alignment, std::size_t size) noexcept {
  count_one();
  void* memory = __libc_memalign(alignment, size);
  if (memory == nullptr) return ENOMEM;
  *out = memory;
  return 0;
}
}
#endif

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
