// `cellsight sim`: render one simulated pass to PNG frames plus truth.yaml, list the catalogue, or write a random one.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "app/sim_setup.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::cli {

struct SimOptions {
  std::string part;
  std::uint64_t seed = 1;
  std::optional<sim::PartPose> pose;  // overrides the seeded pose
  std::string out_dir;
};

// Parses "x,y,theta[,swing]" (metres, metres, degrees, degrees).
[[nodiscard]] Expected<sim::PartPose> parse_pose(const std::string& text);

// Renders every frame of the pass into a staged folder and moves it to options.out_dir when complete.
[[nodiscard]] Status write_sim_pass(const app::Config& config, sim::SimCell& cell, const SimOptions& options);

// `sim --random-catalogue N --seed S --out FILE`: a generated catalogue (drivers/sim/random_catalogue.hpp), checked
// against the configured grid, written atomically to a new file (an existing file is never replaced).
[[nodiscard]] Status write_random_catalogue(const app::Config& config, int count, std::uint64_t seed,
                                            const std::string& out_path);

// The truth.yaml text of the current pass (deterministic: no wall-clock data).
[[nodiscard]] std::string truth_yaml(const app::Config& config, const sim::SimCell& cell,
                                     const std::vector<double>& exposures_us);

}  // namespace cellsight::cli
