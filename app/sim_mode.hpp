// `cellsight sim`: render one simulated pass to PNG frames plus truth.yaml, or list the catalogue.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::app {

struct SimOptions {
  std::string part;
  std::uint64_t seed = 1;
  std::optional<sim::PartPose> pose;  // overrides the seeded pose
  std::string out_dir;
};

// Parses "x,y,theta[,swing]" (metres, metres, degrees, degrees).
[[nodiscard]] Expected<sim::PartPose> parse_pose(const std::string& text);

// Builds the simulated cell from the configuration (loads and validates the catalogue).
[[nodiscard]] Expected<sim::SimCell> make_sim_cell(const Config& config);

// Renders every frame of the pass into a staged folder and moves it to options.out_dir when complete.
[[nodiscard]] Status write_sim_pass(const Config& config, sim::SimCell& cell, const SimOptions& options);

// The truth.yaml text of the current pass (deterministic: no wall-clock data).
[[nodiscard]] std::string truth_yaml(const Config& config, const sim::SimCell& cell, const std::vector<double>& exposures_us);

}  // namespace cellsight::app
