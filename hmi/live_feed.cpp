#include "hmi/live_feed.hpp"

#include <algorithm>

#include "base/local_time.hpp"

namespace cellsight::hmi {

LiveFeed::LiveFeed(std::size_t capacity, runtime::LoopObserver* next) : ring_(capacity), next_(next) {}

void LiveFeed::on_state(runtime::LoopState from, runtime::LoopState to, drivers::ErrorCode error) {
  if (to == runtime::LoopState::kFault || from == runtime::LoopState::kFault) {
    faults_.try_push(FaultEvent{from, to, error, base::wall_clock_ms()});
  }
  if (next_ != nullptr) next_->on_state(from, to, error);
}

void LiveFeed::on_pass_started(std::uint32_t acq_id, runtime::TriggerSource trigger) {
  passes_.fetch_add(1, std::memory_order_relaxed);
  if (next_ != nullptr) next_->on_pass_started(acq_id, trigger);
}

void LiveFeed::on_frame(std::uint32_t acq_id, int frame_index) {
  if (next_ != nullptr) next_->on_frame(acq_id, frame_index);
}

void LiveFeed::on_part_done(const runtime::PartRecord& record) {
  LiveResult r;
  r.plc = record.result;
  r.seq = record.seq;
  r.source = record.decision.source;
  r.unknown_reason = record.decision.unknown_reason;
  r.trigger = record.trigger;
  r.aborted = record.aborted;
  r.frames = record.frames;
  r.verified = record.decision.verified_count;
  r.points = record.points;
  r.cycle_ms = record.cycle_ms;
  r.recognise_ms = record.recognise_ms;
  r.probability = record.decision.probability;
  r.wall_ms = base::wall_clock_ms();
  const std::size_t n = std::min(record.class_name.size(), LiveResult::kNameBytes - 1);
  std::copy_n(record.class_name.data(), n, r.part_name);
  r.part_name[n] = '\0';
  ring_.try_push(r);
  if (next_ != nullptr) next_->on_part_done(record);
}

}  // namespace cellsight::hmi
