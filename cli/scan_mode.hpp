// `cellsight scan`: one acquisition -> point cloud (PLY), on the simulated cell or the real one.
#pragma once

#include <string>
#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"

namespace cellsight::cli {

// `cellsight calibrate support (--scan EMPTY.ply | --sim [--seed S]) [--calibration FILE]`: fits the carrier plane
// on an empty-carrier scan and stores it in calibration.yaml (after a dated backup; other sections kept).
[[nodiscard]] int run_calibrate_support(const std::vector<std::string>& args, const app::Config& config);

// One acquisition with the calibrated sensor -> PLY written atomically. Never uses the simulator's true rig for
// reconstruction: the calibration file is required.
[[nodiscard]] Expected<app::ScanSummary> run_scan(const app::Config& config, const app::ScanOptions& options);

}  // namespace cellsight::cli
