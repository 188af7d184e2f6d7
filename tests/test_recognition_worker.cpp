// Tests of runtime/recognition_worker: the production loop's hand-off to the recognition thread. One job at a time
// through an atomic mailbox: the poster sees "busy" until the answer is published, a wait ends as soon as it is
// (not at its time limit), a full wait that is not answered gives up at its limit, and loading swaps the recogniser.
#include <atomic>
#include <catch2/catch.hpp>
#include <chrono>
#include <memory>
#include <string_view>
#include <thread>
#include <vector>

#include "runtime/recogniser.hpp"
#include "runtime/recognition_worker.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using namespace cellsight;
using runtime::RecognitionWorker;
using runtime::WorkerJob;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

// Answers with the number of points it was given as the part id, after holding until released (when gated).
class GatedRecogniser final : public runtime::Recogniser {
 public:
  explicit GatedRecogniser(int class_offset = 0) : class_offset_(class_offset) {}
  algo::Decision recognise(std::span<const algo::ScanPoint> points, Clock::time_point deadline) override {
    calls.fetch_add(1);
    while (gated.load() && Clock::now() < deadline) std::this_thread::sleep_for(milliseconds(1));
    algo::Decision d;
    d.source = algo::DecisionSource::kSvm;
    d.part_id = static_cast<int>(points.size());
    d.class_index = class_offset_;
    return d;
  }
  std::string_view class_name(int class_index) const override {
    static constexpr std::string_view kNames[] = {"bracket", "gear"};
    return kNames[class_index];
  }
  std::atomic<bool> gated{false};
  std::atomic<int> calls{0};

 private:
  int class_offset_;
};

std::vector<algo::ScanPoint> points(std::size_t n) {
  return std::vector<algo::ScanPoint>(n);
}

TEST_CASE("recognition worker: a posted scan comes back as the recogniser's decision, with its timing",
          "[recognition_worker][thread]") {
  RecognitionWorker worker;
  worker.set_recogniser(std::make_unique<GatedRecogniser>());
  REQUIRE(worker.has_recogniser());
  REQUIRE(worker.start());
  CHECK(worker.idle());
  const auto scan = points(17);
  const auto posted = Clock::now();
  REQUIRE(worker.post_recognise(scan, posted + std::chrono::seconds(5)));
  REQUIRE(worker.wait_idle(Clock::now() + std::chrono::seconds(5)));
  const runtime::WorkerAnswer& answer = worker.answer();
  CHECK(answer.job == WorkerJob::kRecognise);
  CHECK(answer.decision.source == algo::DecisionSource::kSvm);
  CHECK(answer.decision.part_id == 17);
  CHECK(answer.posted_at >= posted);
  CHECK(answer.finished_at >= answer.posted_at);
  CHECK(worker.class_name(answer.decision.class_index) == "bracket");
  worker.stop();
}

TEST_CASE(
    "recognition worker: busy until the answer is published, a second job is refused meanwhile, the wait wakes "
    "at the answer, not at its limit",
    "[recognition_worker][thread]") {
  auto owned = std::make_unique<GatedRecogniser>();
  GatedRecogniser& recogniser = *owned;
  recogniser.gated = true;
  RecognitionWorker worker;
  worker.set_recogniser(std::move(owned));
  REQUIRE(worker.start());
  const auto scan = points(3);
  REQUIRE(worker.post_recognise(scan, Clock::now() + std::chrono::seconds(30)));
  // While the recogniser holds the scan: not idle, a new post is refused, a short wait gives up at its limit.
  const auto before = Clock::now();
  CHECK_FALSE(worker.wait_idle(before + milliseconds(30)));
  CHECK(Clock::now() - before >= milliseconds(30));
  CHECK_FALSE(worker.idle());
  CHECK_FALSE(worker.post_recognise(scan, Clock::now() + std::chrono::seconds(1)));
  CHECK_FALSE(worker.post_load());
  CHECK(worker.class_name(0).empty());  // a job owns the recogniser
  // Released from another thread: a long wait returns as soon as the answer is there.
  std::thread release([&recogniser] {
    std::this_thread::sleep_for(milliseconds(20));
    recogniser.gated = false;
  });
  const auto waited = Clock::now();
  CHECK(worker.wait_idle(waited + std::chrono::seconds(20)));
  CHECK(Clock::now() - waited < std::chrono::seconds(5));
  release.join();
  CHECK(worker.answer().decision.part_id == 3);
  CHECK(worker.class_name(0) == "bracket");
  CHECK(recogniser.calls == 1);
  worker.stop();
}

TEST_CASE("recognition worker: many jobs in a row, each answered once and in turn", "[recognition_worker][thread]") {
  RecognitionWorker worker;
  auto owned = std::make_unique<GatedRecogniser>();
  GatedRecogniser& recogniser = *owned;
  worker.set_recogniser(std::move(owned));
  REQUIRE(worker.start());
  std::vector<std::vector<algo::ScanPoint>> scans;
  for (std::size_t n = 1; n <= 200; ++n) scans.push_back(points(n));
  bool all_right = true;
  long allocations = 0;
  {
    // The poster's side (the loop thread) allocates nothing; the recogniser here allocates nothing either.
    const test::AllocationWindow window;
    for (const auto& scan : scans) {
      if (!worker.post_recognise(scan, Clock::now() + std::chrono::seconds(5)) ||
          !worker.wait_idle(Clock::now() + std::chrono::seconds(5)) ||
          worker.answer().decision.part_id != static_cast<int>(scan.size())) {
        all_right = false;
      }
    }
    allocations = window.count();
  }
  CHECK(all_right);
  CHECK(recogniser.calls == 200);
  CHECK(allocations == 0);
  worker.stop();
}

TEST_CASE("recognition worker: a load job puts the loader's recogniser in place, a failed load keeps none",
          "[recognition_worker][thread]") {
  RecognitionWorker worker;
  bool fail_next = true;
  worker.set_loader([&fail_next]() -> Expected<std::unique_ptr<runtime::Recogniser>> {
    if (fail_next) {
      fail_next = false;
      return make_error("manifest.yaml: checksum mismatch (test)");
    }
    return std::unique_ptr<runtime::Recogniser>(std::make_unique<GatedRecogniser>(1));
  });
  REQUIRE(worker.start());
  CHECK_FALSE(worker.has_recogniser());
  REQUIRE(worker.post_load());
  REQUIRE(worker.wait_idle(Clock::now() + std::chrono::seconds(5)));
  CHECK(worker.answer().job == WorkerJob::kLoad);
  CHECK_FALSE(worker.answer().load_ok);
  CHECK_FALSE(worker.has_recogniser());
  REQUIRE(worker.post_load());
  REQUIRE(worker.wait_idle(Clock::now() + std::chrono::seconds(5)));
  CHECK(worker.answer().load_ok);
  CHECK(worker.has_recogniser());
  const auto scan = points(5);
  REQUIRE(worker.post_recognise(scan, Clock::now() + std::chrono::seconds(5)));
  REQUIRE(worker.wait_idle(Clock::now() + std::chrono::seconds(5)));
  CHECK(worker.class_name(worker.answer().decision.class_index) == "gear");
  worker.stop();
}

TEST_CASE("recognition worker: without a recogniser a scan is 'unknown', stop() ends an idle worker at once",
          "[recognition_worker][thread]") {
  RecognitionWorker worker;
  REQUIRE(worker.start());
  const auto scan = points(2);
  REQUIRE(worker.post_recognise(scan, Clock::now() + std::chrono::seconds(5)));
  REQUIRE(worker.wait_idle(Clock::now() + std::chrono::seconds(5)));
  CHECK(worker.answer().decision.source == algo::DecisionSource::kUnknown);
  const auto stopping = Clock::now();
  worker.stop();
  CHECK(Clock::now() - stopping < std::chrono::seconds(2));
}

}  // namespace
