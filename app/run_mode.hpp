// `cellsight run`: the production cell — devices (simulated or real), Modbus server, recogniser and the production
// loop, until SIGTERM/SIGINT or --parts results.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "drivers/modbus/modbus_server.hpp"

namespace cellsight::app {

// For `cellsight help`: the run lines of the usage text.
extern const char* const kRunUsage;

struct RunOptions {
  bool sim = false;                    // --sim: the simulated cell's camera, GPIO and conveyor
  std::uint64_t parts = 0;             // --parts N: stop after N results (0: run until stopped)
  std::string models_dir;              // --models DIR (default runtime.models_dir)
  std::string calibration_path;        // --calibration FILE (default calibration.yaml beside the config)
  std::string truth_log;               // --truth-log FILE (--sim): one JSON line of simulator truth per acquisition
  std::uint64_t seed = 1;              // --seed S (--sim): which parts and poses arrive
  std::vector<std::string> sim_parts;  // --sim-parts A,B,... (--sim): only these catalogue parts arrive
  bool wait_plc = false;         // --wait-plc (--sim): the conveyor brings parts only while the PLC enables triggers
                                 // and has room in the result queue; with --parts, exit once it acknowledged all
  bool sim_oracle = false;       // --sim-oracle (--sim): decide from the simulator's truth instead of a model database
                                 // (tests of the runtime without a trained database; NOT recognition)
  std::uint64_t sim_replay = 0;  // --sim-replay K (--sim): K distinct passes, rendered once, replayed from memory
  std::string sim_faults;  // --sim-faults SPEC (--sim): faults injected into the simulated devices (the soak test)
  int port = -1;           // --port P: overrides modbus.port (0: any free port, printed in the log)
};

// Parses the words after "run" (a "--config F" or "--log-level L" pair is skipped: the front end handles those).
[[nodiscard]] Expected<RunOptions> parse_run_args(const std::vector<std::string>& args);

// modbus.* of the configuration as the server's settings.
[[nodiscard]] drivers::ModbusServerConfig modbus_server_config(const Config& config);

// The whole mode. Exit codes (app/cli.hpp): 0 done or stopped by SIGTERM/SIGINT; 1 a device or the Modbus port
// could not be opened, or the run failed; 2 bad arguments, configuration, calibration or (with --parts) model
// database.
[[nodiscard]] int run_run(const std::vector<std::string>& args, const Config& config);

}  // namespace cellsight::app
