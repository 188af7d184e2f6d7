// Config -> LoopConfig.
#include "app/loop_wiring.hpp"

#include <algorithm>
#include <cmath>

namespace cellsight::app {

namespace {
// Headroom over the nominal frames of one pass before the photo-eye counts as blocked.
constexpr double kMaxFramesFactor = 1.5;
constexpr int kMaxFramesMargin = 16;
constexpr double kMmPerM = 1e3;
}  // namespace

runtime::AcquirerParams acquirer_params(const Config& config) {
  runtime::AcquirerParams p;
  p.frame_timeout_ms = config.camera.timeout_ms;
  const auto& conveyor = config.rig.conveyor;
  const double frames_per_pass =
      config.rig.carrier.length_m * kMmPerM * conveyor.counts_per_mm / std::max(1, conveyor.trigger_every_counts);
  p.max_frames = static_cast<int>(std::ceil(frames_per_pass * kMaxFramesFactor)) + kMaxFramesMargin;
  p.start_exposure_us = static_cast<std::int32_t>(std::lround(config.camera.exposure_us));
  return p;
}

runtime::LoopConfig loop_config(const Config& config) {
  runtime::LoopConfig c;
  const runtime::AcquirerParams pass = acquirer_params(config);
  c.deadline_ms = config.runtime.deadline_ms;
  c.frame_timeout_ms = pass.frame_timeout_ms;
  c.max_frames = pass.max_frames;
  c.start_exposure_us = pass.start_exposure_us;
  c.cycle_slow_ms = config.runtime.deadline_ms / 2.0;
  c.realtime_priority = config.runtime.realtime_priority;
  c.lock_memory = config.runtime.lock_memory;
  c.result_queue_capacity = static_cast<std::size_t>(std::max(1, config.modbus.result_queue_depth));
  c.edge_timestamps_monotonic = config.gpio.backend != "sim";
  return c;
}

}  // namespace cellsight::app
