// The simulated cell behind `cellsight run --sim`: the conveyor's parts (drawn once, fed in order), injected faults,
// the --sim-oracle recogniser and the --truth-log observer. Kept apart from the production start-up in run_mode.cpp:
// a real cell never builds any of this.
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <optional>
#include <string>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "app/run_options.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "drivers/sim/sim_faults.hpp"
#include "runtime/loop_types.hpp"
#include "runtime/recogniser.hpp"

namespace cellsight::app {

// --sim: the passes cycle through at most this many drawn specs (also the limit of --sim-replay).
inline constexpr std::size_t kPregeneratedPasses = 1024;

// A whole decimal number >= 0 without sign; false on anything else (overflow included).
[[nodiscard]] bool parse_u64(const std::string& text, std::uint64_t& out);

class SimRun {
 public:
  // Builds the simulated cell, draws its passes, parses the fault plan and opens the truth log (--truth-log).
  // Errors are the user's (exit 2): unknown parts, a bad fault plan, an unwritable truth log.
  [[nodiscard]] static Expected<std::unique_ptr<SimRun>> create(const Config& config, const RunOptions& options);
  ~SimRun();  // closes the truth log
  SimRun(const SimRun&) = delete;
  SimRun& operator=(const SimRun&) = delete;

  // --sim-replay: render each distinct pass once and replay it from memory (an allocation failure is exit 1).
  [[nodiscard]] Status enable_replay();
  [[nodiscard]] sim::SimLine& line() { return *line_; }
  // --sim-oracle: decisions from the simulator's truth of the pass under the sensor.
  [[nodiscard]] std::unique_ptr<runtime::Recogniser> make_oracle() const;
  // --truth-log: the loop observer that writes it (after the template truth of models_dir when not an oracle run);
  // nullptr without --truth-log.
  [[nodiscard]] runtime::LoopObserver* truth_observer(const Config& config, const std::string& models_dir);
  // Keeps a couple of parts waiting on the simulated conveyor (time only moves when the loop asks for edges or
  // frames); none once the loop has its parts.
  void feed(bool loop_finished);
  // One log line: passes started and fed, bounces filtered, frames replayed.
  void log_summary(const drivers::DigitalIo& io) const;

 private:
  SimRun() = default;

  struct State;
  std::unique_ptr<State> state_;
  sim::SimLine* line_ = nullptr;  // in state_
};

}  // namespace cellsight::app
