// `cellsight scan`: one acquisition -> point cloud (PLY), on the simulated cell or the real one.
#pragma once

#include <string>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan_builder.hpp"
#include "app/config.hpp"

namespace cellsight::app {

// The reconstruction parameters that come from the configuration.
[[nodiscard]] algo::ScanBuilderParams scan_builder_params(const Config& config);

}  // namespace cellsight::app
