// Reads and writes the simulated cell's part catalogue (config/parts.yaml): parametric sheet-metal parts as data.
#pragma once

#include <string>
#include <vector>

#include "algo/result.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::app {

[[nodiscard]] Expected<std::vector<sim::PartSpec>> load_catalogue(const std::string& path);

// The text of a catalogue file holding `parts` (format_version 1, the layout of config/parts.yaml), with `header`
// as comment lines on top. load_catalogue reads it back into exactly `parts`: numbers are written in their shortest
// exact form, texts double-quoted.
[[nodiscard]] std::string catalogue_yaml(const std::vector<sim::PartSpec>& parts, const std::string& header);

}  // namespace cellsight::app
