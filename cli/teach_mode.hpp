// `cellsight teach --part NAME [--id N] (--sim --count K [--seed S] | SCAN.ply...)` and `cellsight parts
// list|show NAME|delete NAME`: the operator's side of the model database.
#pragma once

#include <string>
#include <vector>

#include "app/config.hpp"

namespace cellsight::cli {

[[nodiscard]] int run_teach(const std::vector<std::string>& args, const app::Config& config,
                            const std::string& models_dir);
[[nodiscard]] int run_parts(const std::vector<std::string>& args, const app::Config& config,
                            const std::string& models_dir);

}  // namespace cellsight::cli
