// `cellsight perturb` (seeded artefacts on a PLY scan) and the --perturb option of teach and eval --sim.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "cli/mode_args.hpp"

namespace cellsight::cli {

// The --perturb SPEC option of a mode (nullopt when absent or "none"), with the carrier plane from the calibration
// file and the carrier band from the configuration.
[[nodiscard]] Expected<std::optional<app::PassPerturbation>> perturbation_option(const ModeArgs& args,
                                                                                 const app::Config& config,
                                                                                 const std::string& calibration_path,
                                                                                 std::uint64_t purpose);

// `cellsight perturb --kind SPEC [--seed S] [--calibration FILE] IN.ply OUT.ply`
[[nodiscard]] int run_perturb(const std::vector<std::string>& args, const app::Config& config);

}  // namespace cellsight::cli
