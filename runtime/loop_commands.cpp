// The production loop: what the PLC's command block asks for (CONTROL bits and COMMAND), taken once per step.
#include "runtime/loop_internal.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::runtime {

void ProductionLoop::handle_commands(const drivers::PlcCommands& commands) {
  trigger_enable_ = commands.trigger_enable;
  const LoopState state = state_.load(std::memory_order_relaxed);
  if (commands.sw_triggers > 0) handle_sw_triggers(commands.sw_triggers, state);
  if (commands.clear_errors > 0) handle_clear_error(state);
  if (commands.exec_command) handle_exec(commands);
}

void ProductionLoop::handle_sw_triggers(std::uint32_t count, LoopState state) {
  if (state == LoopState::kIdle) {
    pending_sw_triggers_ += count;
  } else if (state == LoopState::kScanning || state == LoopState::kRecognising) {
    for (std::uint32_t i = 0; i < count; ++i) count_missed_trigger("SW_TRIGGER while busy");
  } else {
    CS_QLOG_WARN(log_, kComponent, "SW_TRIGGER ignored: %s", to_string(state));
  }
}

void ProductionLoop::handle_clear_error(LoopState state) {
  CS_QLOG_INFO(log_, kComponent, "CLEAR_ERROR from the PLC");
  if (state == LoopState::kFault) {
    clear_requested_ = true;
  } else {
    consecutive_timeouts_ = 0;
    if (error_ == ErrorCode::kRepeatedTimeouts) set_error(ErrorCode::kNone);
    set_warning(WarningCode::kNone);
  }
}

void ProductionLoop::handle_exec(const drivers::PlcCommands& commands) {
  using drivers::CommandCode;
  bool ok = false;
  switch (commands.command) {
    case CommandCode::kResetCounters:
      trigger_count_ = 0;
      missed_count_ = 0;
      link_.set_trigger_counters(0, 0);
      ok = true;
      break;
    case CommandCode::kSelectModels:
      // One model database per cellsight process: selecting the active one (again) retries loading it.
      ok = commands.command_arg == config_.active_models_id;
      if (ok && fault_cause_ == ErrorCode::kModelDatabaseInvalid) models_reload_requested_ = true;
      break;
    case CommandCode::kEnterTeach:
    case CommandCode::kLeaveTeach:  // teaching is `cellsight teach`, not the production loop
    case CommandCode::kNone: ok = false; break;
  }
  CS_QLOG_INFO(log_, kComponent, "command %u (arg %u) from the PLC: %s", static_cast<unsigned>(commands.command_raw),
               static_cast<unsigned>(commands.command_arg), ok ? "done" : "refused");
  link_.complete_command(ok);
}

}  // namespace cellsight::runtime
