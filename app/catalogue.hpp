// Reads the simulated cell's part catalogue (config/parts.yaml): parametric sheet-metal parts as data.
#pragma once

#include <string>
#include <vector>

#include "algo/result.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::app {

[[nodiscard]] Expected<std::vector<sim::PartSpec>> load_catalogue(const std::string& path);

}  // namespace cellsight::app
