// `cellsight scan` implementation.
#include "app/scan_mode.hpp"

namespace cellsight::app {

algo::ScanBuilderParams scan_builder_params(const Config& config) {
  algo::ScanBuilderParams p;
  p.exposure.width_min_px = static_cast<float>(config.exposure.width_min_px);
  p.exposure.width_max_px = static_cast<float>(config.exposure.width_max_px);
  p.exposure.max_step_ratio = static_cast<float>(config.exposure.max_step_ratio);
  p.exposure.exposure_min_us = static_cast<std::int32_t>(config.camera.exposure_min_us);
  p.exposure.exposure_max_us = static_cast<std::int32_t>(config.camera.exposure_max_us);
  p.carrier_start_offset_m = config.rig.carrier.start_offset_m;
  // Room for two stripes in every row of every frame of a pass, plus margin.
  const double frames = config.rig.carrier.length_m * 1e3 * config.rig.conveyor.counts_per_mm /
                        config.rig.conveyor.trigger_every_counts;
  p.max_points = static_cast<std::size_t>((frames + 16.0) * config.rig.camera.intrinsics.height_px * 2.0);
  return p;
}

}  // namespace cellsight::app
