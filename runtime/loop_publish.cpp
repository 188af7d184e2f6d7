// The production loop's publishing step: a decision becomes the PLC's result block, the part's counters, warning
// and log line, and the observer's record.
#include <cstdio>
#include <numbers>
#include <string_view>

#include "runtime/loop_internal.hpp"
#include "runtime/plc_mapping.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::runtime {

namespace {
constexpr double kDegPerRad = 180.0 / std::numbers::pi;
constexpr double kMmPerM = 1e3;
}  // namespace

void ProductionLoop::publish(const algo::Decision& decision, Clock::time_point now, bool aborted) {
  const PartRecord record = make_record(decision, now, aborted);
  count_result(record);
  PartWarningInputs part;
  part.missed_since_result = missed_since_result_;
  part.exposure_at_limit = exposure_at_limit_;
  part.aborted = aborted;
  part.cycle_ms = record.cycle_ms;
  part.cycle_slow_ms = config_.cycle_slow_ms;
  missed_since_result_ = 0;
  set_warning(part_warning(part));
  log_part(record);
  if (observer_ != nullptr) observer_->on_part_done(record);
  note_finished();
}

PartRecord ProductionLoop::make_record(const algo::Decision& decision, Clock::time_point now, bool aborted) {
  PartRecord record;
  record.acq_id = acq_id_;
  record.trigger = pass_trigger_;
  record.decision = decision;
  record.result =
      to_plc_result(decision, acq_id_, loop_detail::monotonic_us(), aborted ? 0.0 : ms_between(cycle_start_, now));
  record.publish = link_.publish(record.result);
  const Clock::time_point published = Clock::now();
  record.seq = record.publish == drivers::PublishStatus::kQueued ? link_.stats().last_seq : 0;
  record.frames = acquirer_.frames();
  record.points = builder_.scan().size();
  record.cycle_ms = aborted ? 0.0 : ms_between(cycle_start_, published);
  record.recognise_ms = recognise_ms_;
  record.cycle_start_ns = to_ns(cycle_start_);
  record.published_ns = to_ns(published);
  record.aborted = aborted;
  if (decision.class_index >= 0) record.class_name = worker_.class_name(decision.class_index);
  recognise_ms_ = 0.0;
  return record;
}

// Counters, cycle times and the "repeated timeouts" error the PLC sees; a cycle inside the deadline clears it.
void ProductionLoop::count_result(const PartRecord& record) {
  results_.fetch_add(1, std::memory_order_relaxed);
  if (record.publish != drivers::PublishStatus::kQueued) {
    rejected_.fetch_add(1, std::memory_order_relaxed);
    CS_QLOG_ERROR(log_, kComponent, "acq %u: result not handed to the PLC: %s (RESULT_OVERRUN)", acq_id_,
                  drivers::to_string(record.publish));
  }
  if (!record.aborted) {
    last_cycle_ms_.store(record.cycle_ms, std::memory_order_relaxed);
    if (record.cycle_ms > max_cycle_ms_.load(std::memory_order_relaxed)) {
      max_cycle_ms_.store(record.cycle_ms, std::memory_order_relaxed);
    }
  }
  if (record.result.code == drivers::ResultCode::kTimeout) {
    timeouts_.fetch_add(1, std::memory_order_relaxed);
    ++consecutive_timeouts_;
    if (consecutive_timeouts_ >= config_.max_consecutive_timeouts && error_ == ErrorCode::kNone) {
      CS_QLOG_ERROR(log_, kComponent, "%d timeouts in a row: ERROR_CODE repeated timeouts", consecutive_timeouts_);
      set_error(ErrorCode::kRepeatedTimeouts);
    }
  } else if (!record.aborted) {
    consecutive_timeouts_ = 0;
    if (error_ == ErrorCode::kRepeatedTimeouts) set_error(ErrorCode::kNone);
  }
}

// The one line per part (formatted into the log queue: the loop does not wait for stderr).
void ProductionLoop::log_part(const PartRecord& record) const {
  const auto& r = record.result;
  const algo::Decision& decision = record.decision;
  const auto name = record.class_name.empty() ? std::string_view("-") : record.class_name;
  if (r.code == drivers::ResultCode::kOk) {
    // The pose first on its own (a stack buffer): one format for the whole line would exceed kMaxLogConversions.
    char pose[160];
    std::snprintf(pose, sizeof pose, "x %+.2f mm y %+.2f mm theta %+.3f deg z %+.2f mm rx %+.3f deg ry %+.3f deg",
                  decision.pose.x_m * kMmPerM, decision.pose.y_m * kMmPerM, decision.pose.theta_rad * kDegPerRad,
                  decision.z_m * kMmPerM, decision.rx_rad * kDegPerRad, decision.ry_rad * kDegPerRad);
    CS_QLOG_INFO(log_, kComponent,
                 "acq %u %s: part %.*s (id %u) source %s p %.3f pose %s cycle %.1f ms (recognition %.1f ms) "
                 "frames %d points %zu seq %u",
                 r.acq_id, drivers::to_string(r.code), static_cast<int>(name.size()), name.data(),
                 static_cast<unsigned>(r.part_id), algo::to_string(decision.source).data(), decision.probability, pose,
                 record.cycle_ms, record.recognise_ms, record.frames, record.points, record.seq);
    return;
  }
  CS_QLOG_INFO(log_, kComponent,
               "acq %u %s: part %.*s (id %u) source %s p %.3f pose - cycle %.1f ms (recognition %.1f ms) "
               "frames %d points %zu seq %u",
               r.acq_id, drivers::to_string(r.code), static_cast<int>(name.size()), name.data(),
               static_cast<unsigned>(r.part_id), algo::to_string(decision.source).data(), decision.probability,
               record.cycle_ms, record.recognise_ms, record.frames, record.points, record.seq);
  if (decision.source == algo::DecisionSource::kUnknown) log_unknown(record);
}

// Why a part is unknown (issue 10): the most probable verified candidate's failed gate, and how deep the search went.
void ProductionLoop::log_unknown(const PartRecord& record) const {
  const algo::Decision& decision = record.decision;
  const algo::CandidateOutcome* why = nullptr;
  for (int i = 0; i < decision.candidate_count && why == nullptr; ++i) {
    const algo::CandidateOutcome& c = decision.candidates[static_cast<std::size_t>(i)];
    if (c.verified) why = &c;
  }
  std::string_view cand = why != nullptr ? worker_.class_name(why->class_index) : std::string_view();
  if (why == nullptr || cand.empty()) cand = "-";
  CS_QLOG_INFO(log_, kComponent,
               "acq %u unknown: %s; %d of %d candidates verified; first: %.*s (p %.3f) %s %.4g > %.4g",
               record.result.acq_id, algo::to_string(decision.unknown_reason).data(), decision.verified_count,
               decision.candidate_count, static_cast<int>(cand.size()), cand.data(),
               why != nullptr ? why->probability : 0.0, why != nullptr ? algo::to_string(why->rejected_by).data() : "-",
               why != nullptr ? why->value : 0.0, why != nullptr ? why->limit : 0.0);
}

// max_parts results: the loop takes no more parts (it keeps serving the PLC) and wakes wait_finished().
void ProductionLoop::note_finished() {
  if (config_.max_parts == 0 || results_.load(std::memory_order_relaxed) < config_.max_parts ||
      finished_.load(std::memory_order_relaxed)) {
    return;
  }
  finished_.store(true, std::memory_order_release);
  wake_waiters();
  CS_QLOG_INFO(log_, kComponent, "%llu parts done: taking no more parts",
               static_cast<unsigned long long>(config_.max_parts));
}

}  // namespace cellsight::runtime
