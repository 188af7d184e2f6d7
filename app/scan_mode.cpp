// `cellsight scan` implementation.
#include "app/scan_mode.hpp"

#include "algo/ply.hpp"
#include "app/acquire.hpp"
#include "app/atomic_file.hpp"
#include "app/calibration_file.hpp"
#include "app/devices.hpp"
#include "app/sim_mode.hpp"
#include "drivers/log.hpp"

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

Expected<ScanSummary> run_scan(const Config& config, const ScanOptions& options) {
  const std::string calibration_path =
      options.calibration_path.empty() ? default_calibration_path(config) : options.calibration_path;
  auto calibration = load_sensor_calibration(calibration_path);
  if (!calibration) {
    return make_error(calibration.error().message + "\n(run scripts/calibrate.sh, or cellsight calibrate, first)");
  }
  std::optional<sim::SimCell> cell;
  std::optional<sim::SimLine> line;
  if (options.sim) {
    auto made = make_sim_cell(config);
    if (!made) return made.error();
    cell.emplace(std::move(*made));
    line.emplace(*cell);
    sim::PassSpec pass;
    if (options.empty_carrier) {
      pass.with_part = false;
      pass.seed = options.seed;
    } else {
      auto drawn = cell->random_pass(options.part, options.seed);
      if (!drawn) return drawn.error();
      pass = *drawn;
      if (options.pose) pass.pose = *options.pose;
    }
    line->enqueue(pass);
  }
  auto devices = make_devices(config, line ? &*line : nullptr, options.sim);
  if (!devices) return devices.error();
  if (auto ok = devices->open(); !ok) return ok.error();
  algo::ScanBuilder builder(scan_builder_params(config), *calibration);
  AcquireParams params;
  params.start_exposure_us = static_cast<std::int32_t>(config.camera.exposure_us);
  params.frame_timeout_ms = config.camera.timeout_ms;
  params.edge_wait_ms = options.sim ? 0 : 60000;  // a real cell waits a minute for a part to arrive
  if (devices->io->set(drivers::Output::kLaserEnable, true) != drivers::DeviceStatus::kOk) {
    devices->close();
    return make_error("cannot switch the laser on (gpio.laser_line)");
  }
  AcquireReport report;
  const AcquireResult result = acquire_pass(*devices->camera, *devices->io, *devices->encoder, builder, params, report);
  (void)devices->io->set(drivers::Output::kLaserEnable, false);
  devices->close();
  if (result != AcquireResult::kOk) return make_error(std::string("scan failed: ") + to_string(result));
  const auto points = builder.scan().points();
  const std::string bytes = options.ascii ? algo::write_ply_ascii(points) : algo::write_ply_binary(points);
  if (auto ok = write_file_atomic(options.out_path, bytes); !ok) return ok.error();
  ScanSummary summary;
  summary.points = points.size();
  summary.frames = builder.stats().frames;
  summary.frames_with_stripe = builder.stats().frames_with_stripe;
  summary.frames_in_band = builder.stats().frames_in_band;
  summary.final_exposure_us = builder.exposure_us();
  CS_LOG_INFO("scan", "%zu points from %d frames (stripe width in band in %d of %d) -> %s", summary.points,
              summary.frames, summary.frames_in_band, summary.frames_with_stripe, options.out_path.c_str());
  return summary;
}

}  // namespace cellsight::app
