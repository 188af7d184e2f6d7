// `cellsight run`: the production cell — devices (simulated or real), Modbus server, recogniser and the production
// loop, until SIGTERM/SIGINT or --parts results.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "app/run_options.hpp"
#include "drivers/modbus/modbus_server.hpp"

namespace cellsight::cli {

// For `cellsight help`: the run lines of the usage text.
extern const char* const kRunUsage;

// Parses the words after "run" (a "--config F" or "--log-level L" pair is skipped: the front end handles those).
[[nodiscard]] Expected<app::RunOptions> parse_run_args(const std::vector<std::string>& args);

// modbus.* of the configuration as the server's settings.
[[nodiscard]] drivers::ModbusServerConfig modbus_server_config(const app::Config& config);

// The whole mode. Exit codes (cli/cli.hpp): 0 done or stopped by SIGTERM/SIGINT; 1 a device or the Modbus port
// could not be opened, or the run failed; 2 bad arguments, configuration, calibration or (with --parts) model
// database.
[[nodiscard]] int run_run(const std::vector<std::string>& args, const app::Config& config);

}  // namespace cellsight::cli
