// `cellsight scan`: one acquisition -> point cloud (PLY), on the simulated cell or the real one.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "algo/scan_builder.hpp"
#include "app/config.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::app {

// The reconstruction parameters that come from the configuration.
[[nodiscard]] algo::ScanBuilderParams scan_builder_params(const Config& config);

struct ScanOptions {
  bool sim = false;
  std::string part;  // --sim: which catalogue part passes
  std::uint64_t seed = 1;
  std::optional<sim::PartPose> pose;  // --sim: overrides the seeded pose
  bool empty_carrier = false;         // --sim --empty: the carrier alone (support calibration)
  std::string out_path;               // SCAN.ply
  std::string calibration_path;       // default: calibration.yaml beside the config
  bool ascii = false;
};

struct ScanSummary {
  std::size_t points = 0;
  int frames = 0, frames_with_stripe = 0, frames_in_band = 0;
  std::int32_t final_exposure_us = 0;
};

// One acquisition with the calibrated sensor, kept in memory.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> acquire_scan(const Config& config, const ScanOptions& options,
                                                                  ScanSummary& summary);

// `cellsight calibrate support (--scan EMPTY.ply | --sim [--seed S]) [--calibration FILE]`: fits the carrier plane
// on an empty-carrier scan and stores it in calibration.yaml (after a dated backup; other sections kept).
[[nodiscard]] int run_calibrate_support(const std::vector<std::string>& args, const Config& config);

// One acquisition with the calibrated sensor -> PLY written atomically. Never uses the simulator's true rig for
// reconstruction: the calibration file is required.
[[nodiscard]] Expected<ScanSummary> run_scan(const Config& config, const ScanOptions& options);

// Acquires passes of `part` on the simulated cell, seeds first_seed .. first_seed + count - 1, on all cores, and hands
// each to take(index, seed, points), one call at a time (under a lock), in completion order. Progress "  <label> n /
// count" on stdout: redrawn in place on a terminal, otherwise a line every 10th and the last (log files, journald).
// The first failure (of an acquisition or of take) stops the others and is returned. With `perturb`, each pass is
// perturbed (seed from its pass seed) before take sees it.
struct PassPerturbation;
using PassConsumer = std::function<Status(int index, std::uint64_t seed, std::vector<algo::ScanPoint>&& points)>;
[[nodiscard]] Status acquire_sim_passes(const Config& config, const std::string& part, int count,
                                        std::uint64_t first_seed, const std::string& calibration_path,
                                        const std::string& label, const PassConsumer& take,
                                        const PassPerturbation* perturb = nullptr);

}  // namespace cellsight::app
