// Counting global allocator for the tests that prove "no allocation here" (the Eigen nomalloc idea, STYLE.md rule 5).
// Linking cellsight_test_support replaces every form of operator new and delete the standard library and Catch2 use
// (plain, array, sized, nothrow; the aligned forms are left to the library); a window counts the news.
#pragma once

namespace cellsight::test {

// Counts operator new on every thread while alive, from zero. One window at a time (not nested).
class AllocationWindow {
 public:
  AllocationWindow();
  ~AllocationWindow();
  AllocationWindow(const AllocationWindow&) = delete;
  AllocationWindow& operator=(const AllocationWindow&) = delete;
  // Allocations so far in this window.
  [[nodiscard]] long count() const;
};

// While alive, this thread's allocations are not counted (scopes nest). For what stands in for the world outside
// the code under test, e.g. the simulated camera, conveyor and PLC around the production loop.
class UncountedScope {
 public:
  UncountedScope();
  ~UncountedScope();
  UncountedScope(const UncountedScope&) = delete;
  UncountedScope& operator=(const UncountedScope&) = delete;
};

}  // namespace cellsight::test
