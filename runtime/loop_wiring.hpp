// Config -> the production loop's parameters, in one place: which configuration keys drive which loop setting.
#pragma once

#include "app/config.hpp"
#include "runtime/loop_types.hpp"
#include "runtime/pass_acquirer.hpp"

namespace cellsight::runtime {

// The loop settings that come from the configuration (runtime.*, camera.*, rig geometry, modbus.*, gpio.backend).
[[nodiscard]] LoopConfig loop_config(const app::Config& config);

// The acquisition of one pass (camera.*, rig geometry): the same for the production loop and the command-line modes.
[[nodiscard]] AcquirerParams acquirer_params(const app::Config& config);

}  // namespace cellsight::runtime
