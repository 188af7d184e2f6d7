// `cellsight parts list | show NAME | delete NAME | rebuild [NAME...]`: the operator's and maintainer's view of the
// model database.
#pragma once

#include <string>
#include <vector>

#include "app/config.hpp"

namespace cellsight::cli {

[[nodiscard]] int run_parts(const std::vector<std::string>& args, const app::Config& config,
                            const std::string& models_dir);

}  // namespace cellsight::cli
