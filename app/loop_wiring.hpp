// Config -> the production loop's parameters, in one place: which configuration keys drive which loop setting. In
// app/, the composition layer that knows Config: runtime/ takes its parameters as plain structs and never reads it.
#pragma once

#include "app/config.hpp"
#include "runtime/loop_types.hpp"
#include "runtime/pass_acquirer.hpp"

namespace cellsight::app {

// The loop settings that come from the configuration (runtime.*, camera.*, rig geometry, modbus.*, gpio.backend).
[[nodiscard]] runtime::LoopConfig loop_config(const Config& config);

// The acquisition of one pass (camera.*, rig geometry): the same for the production loop and the command-line modes.
[[nodiscard]] runtime::AcquirerParams acquirer_params(const Config& config);

}  // namespace cellsight::app
