// `cellsight classify [--json] [--svm-only|--pm-only] SCAN.ply...` and `cellsight eval --scans DIR [--json]`.
#pragma once

#include <string>
#include <vector>

#include "app/config.hpp"

namespace cellsight::cli {

[[nodiscard]] int run_classify(const std::vector<std::string>& args, const app::Config& config,
                               const std::string& models_dir);
[[nodiscard]] int run_eval(const std::vector<std::string>& args, const app::Config& config,
                           const std::string& models_dir);

}  // namespace cellsight::cli
