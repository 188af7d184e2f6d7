// `cellsight calibrate camera|laser|conveyor`: technician calibration from board pictures or the simulated cell.
#pragma once

#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"

namespace cellsight::cli {

// For `cellsight help`: the calibrate lines of the usage text.
extern const char* const kCalibrateUsage;

// `args` are the words after "calibrate", e.g. {"camera", "--images", "DIR"} (a "--config F" or "--log-level L"
// pair is skipped: the front end handles those). Prints the result figures on stdout and, on refusal, one line
// saying what is wrong and what to do on stderr. Returns 0 done, 2 bad input (arguments, pictures, views.yaml,
// a calibration the figures refuse, an unreadable calibration.yaml), 1 a failure while writing.
// calibration.yaml changes only on success, after a dated backup; each step replaces only its own section.
[[nodiscard]] int run_calibrate(const std::vector<std::string>& args, const app::Config& config);
// The same with explicit output streams (tests).
[[nodiscard]] int run_calibrate(const std::vector<std::string>& args, const app::Config& config, std::FILE* out,
                                std::FILE* err);

// Renders one step's board pictures on the simulated cell (config.rig), as a technician would take them, into
// the new folder out_dir: PNG files and the views.yaml that `calibrate STEP --images out_dir` reads.
[[nodiscard]] Status write_sim_calibration_views(const app::Config& config, const std::string& step,
                                                 const std::string& out_dir, std::uint64_t seed);

}  // namespace cellsight::cli
