// One acquisition with the calibrated sensor through the device interfaces, and the simulated cell's passes
// acquired on all cores (optionally perturbed): what the scan, calibrate support, teach and eval modes share.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "algo/perturb.hpp"
#include "algo/random.hpp"
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

// Salts of the perturbation seeds: a taught and a test pass with the same pass seed never share a draw.
inline constexpr std::uint64_t kPerturbTeach = 0x7EAC;
inline constexpr std::uint64_t kPerturbEval = 0xE7A1;

// What teach and eval --sim apply to every generated pass before it is stored or written.
struct PassPerturbation {
  algo::PerturbSpec spec;
  algo::Plane support;
  std::uint64_t purpose = 0;  // kPerturbTeach or kPerturbEval

  [[nodiscard]] std::uint64_t seed_for(std::uint64_t pass_seed) const { return algo::mix_seed(pass_seed, purpose); }
};

// Acquires passes of `part` on the simulated cell, seeds first_seed .. first_seed + count - 1, on all cores, and hands
// each to take(index, seed, points), one call at a time (under a lock), in completion order. Progress "  <label> n /
// count" on stdout: redrawn in place on a terminal, otherwise a line every 10th and the last (log files, journald).
// The first failure (of an acquisition or of take) stops the others and is returned. With `perturb`, each pass is
// perturbed (seed from its pass seed) before take sees it.
using PassConsumer = std::function<Status(int index, std::uint64_t seed, std::vector<algo::ScanPoint>&& points)>;
[[nodiscard]] Status acquire_sim_passes(const Config& config, const std::string& part, int count,
                                        std::uint64_t first_seed, const std::string& calibration_path,
                                        const std::string& label, const PassConsumer& take,
                                        const PassPerturbation* perturb = nullptr);

}  // namespace cellsight::app
