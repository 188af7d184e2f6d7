// The production loop's recognising state: the worker has the scan; the hard deadline runs on the loop thread.
#include "runtime/loop_internal.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::runtime {

void ProductionLoop::step_recognising(Clock::time_point now) {
  Clock::time_point until = now + std::chrono::milliseconds(config_.poll_slice_ms);
  if (!timeout_published_) until = std::min(until, deadline_);
  // A futex sleep on the worker's answer word: the worker publishes the answer with one atomic store and a wake,
  // and holds nothing the loop could wait for.
  if (worker_.wait_idle(until)) {
    take_answer(worker_.answer());
    return;
  }
  const Clock::time_point t = Clock::now();
  if (!timeout_published_ && t >= deadline_) {
    // The PLC gets "timeout" at the deadline, whatever the recogniser does; the scan buffer stays its own until it
    // returns, so the next part waits for that.
    recognise_ms_ = ms_between(cycle_start_, t);
    enter(LoopState::kPublishing);
    publish(decision_of(algo::DecisionSource::kTimeout), t, false);
    timeout_published_ = true;
    enter(LoopState::kRecognising);
    return;
  }
  if (timeout_published_ && t >= deadline_ + std::chrono::milliseconds(config_.hung_grace_ms)) {
    recogniser_hung_.store(true, std::memory_order_release);
    enter_fault(ErrorCode::kInternal, "the recogniser does not return (hung)");
    return;
  }
  if (!config_.conveyor_waits_for_ready) poll_edges_while_busy();
}

void ProductionLoop::take_answer(const WorkerAnswer& answer) {
  if (timeout_published_) {
    late_decisions_.fetch_add(1, std::memory_order_relaxed);
    CS_QLOG_WARN(log_, kComponent,
                 "acq %u: the recogniser answered %.0f ms after the deadline; its answer is discarded", acq_id_,
                 ms_between(deadline_, answer.finished_at));
    timeout_published_ = false;
    enter(LoopState::kIdle);
    return;
  }
  algo::Decision decision = answer.decision;
  if (answer.finished_at > deadline_ || decision.source == algo::DecisionSource::kTimeout) {
    if (decision.source != algo::DecisionSource::kTimeout) late_decisions_.fetch_add(1, std::memory_order_relaxed);
    decision = decision_of(algo::DecisionSource::kTimeout);  // never a guess
  }
  recognise_ms_ = ms_between(answer.posted_at, answer.finished_at);
  enter(LoopState::kPublishing);
  publish(decision, Clock::now(), false);
  enter(LoopState::kIdle);
}

}  // namespace cellsight::runtime
