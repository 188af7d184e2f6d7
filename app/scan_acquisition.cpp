// One acquisition with the calibrated sensor, and the simulated passes on all cores.
#include "app/scan_acquisition.hpp"

#include <unistd.h>

#include <cstdio>
#include <mutex>

#include "app/acquire.hpp"
#include "app/devices.hpp"
#include "app/loop_wiring.hpp"
#include "app/sim_setup.hpp"
#include "base/parallel_for.hpp"
#include "formats/calibration_file.hpp"

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
  const double frames =
      config.rig.carrier.length_m * 1e3 * config.rig.conveyor.counts_per_mm / config.rig.conveyor.trigger_every_counts;
  p.max_points = static_cast<std::size_t>((frames + 16.0) * config.rig.camera.intrinsics.height_px * 2.0);
  return p;
}

Expected<std::vector<algo::ScanPoint>> acquire_scan(const Config& config, const ScanOptions& options,
                                                    ScanSummary& summary) {
  const std::string calibration_path =
      options.calibration_path.empty() ? default_calibration_path(config) : options.calibration_path;
  auto calibration = formats::load_sensor_calibration(calibration_path);
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
  const runtime::AcquirerParams pass = acquirer_params(config);  // the production loop's, from the config
  params.start_exposure_us = pass.start_exposure_us;
  params.frame_timeout_ms = pass.frame_timeout_ms;
  params.max_frames = pass.max_frames;
  params.edge_wait_ms = options.sim ? 0 : 60000;  // a real cell waits a minute for a part to arrive
  // The laser is the acquirer's: on from the rising edge to the end of the pass, as in production.
  AcquireReport report;
  const AcquireResult result = acquire_pass(*devices->camera, *devices->io, *devices->encoder, builder, params, report);
  devices->close();
  if (result != AcquireResult::kOk) return make_error(std::string("scan failed: ") + to_string(result));
  summary.points = builder.scan().size();
  summary.frames = builder.stats().frames;
  summary.frames_with_stripe = builder.stats().frames_with_stripe;
  summary.frames_in_band = builder.stats().frames_in_band;
  summary.final_exposure_us = builder.exposure_us();
  return std::vector<algo::ScanPoint>(builder.scan().points().begin(), builder.scan().points().end());
}

Status acquire_sim_passes(const Config& config, const std::string& part, int count, std::uint64_t first_seed,
                          const std::string& calibration_path, const std::string& label, const PassConsumer& take,
                          const PassPerturbation* perturb) {
  int done = 0;
  std::mutex mutex;
  std::string first_error;
  const bool terminal = ::isatty(::fileno(stdout)) != 0;
  // One pass per index on every core; the first failure stops the handing out of further passes.
  const bool complete = base::parallel_for(count, base::hardware_threads(), [&](int i, int /*worker*/) {
    ScanOptions options;
    options.sim = true;
    options.part = part;
    options.seed = first_seed + static_cast<std::uint64_t>(i);
    options.calibration_path = calibration_path;
    ScanSummary summary;
    auto points = acquire_scan(config, options, summary);
    if (points && perturb != nullptr) {
      (void)algo::perturb_scan(*points, perturb->spec, perturb->support, perturb->seed_for(options.seed));
    }
    const std::lock_guard<std::mutex> lock(mutex);
    if (!first_error.empty()) return false;
    if (!points) {
      first_error = part + " seed " + std::to_string(options.seed) + ": " + points.error().message;
      return false;
    }
    if (auto ok = take(i, options.seed, std::move(*points)); !ok) {
      first_error = ok.error().message;
      return false;
    }
    const int n = ++done;
    if (terminal) {
      std::printf("\r  %s %d / %d   ", label.c_str(), n, count);
    } else if (n % 10 == 0 || n == count) {
      std::printf("  %s %d / %d\n", label.c_str(), n, count);
    }
    std::fflush(stdout);
    return true;
  });
  if (terminal && done > 0) std::printf("\n");
  if (!complete) return make_error(first_error);  // a pass failed: first_error says which
  return {};
}

}  // namespace cellsight::app
