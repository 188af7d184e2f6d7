// The simulated cell as the configuration describes it: its construction and the check that its catalogue fits the
// occupancy grid. Used by the sim, scan, teach, eval and run --sim modes and by the tests.
#pragma once

#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::app {

// Builds the simulated cell from the configuration (loads and validates the catalogue).
[[nodiscard]] Expected<sim::SimCell> make_sim_cell(const Config& config);

// Fails, naming the first part and pose corner, unless every part lies inside the configured occupancy grid at all
// 64 extremes of the random pose (x, y, z, theta, swing and tilt each at +- their configured range) on the configured
// carrier.
[[nodiscard]] Status check_catalogue_fits_grid(const Config& config, const std::vector<sim::PartSpec>& parts);

}  // namespace cellsight::app
