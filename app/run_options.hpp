// The options of `cellsight run`: parsed by the command line (cli/run_mode), read by the production start-up and
// by the simulated cell behind --sim (app/run_sim).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace cellsight::app {

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
  int hmi_port = -1;       // --hmi-port P: overrides hmi.port (0: any free port, printed in the log)
  bool hmi = true;         // --no-hmi: no operator's screen, whatever hmi.enabled says
};

}  // namespace cellsight::app
