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
  handle_screen_command();
  swap_offered_recogniser();
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
  const bool ok = execute(commands.command, commands.command_arg);
  CS_QLOG_INFO(log_, kComponent, "command %u (arg %u) from the PLC: %s", static_cast<unsigned>(commands.command_raw),
               static_cast<unsigned>(commands.command_arg), ok ? "done" : "refused");
  link_.complete_command(ok);
}

// The screen's command, taken between steps like the PLC's (see post_command).
void ProductionLoop::handle_screen_command() {
  const std::uint32_t posted = screen_posted_.load(std::memory_order_acquire);
  if (posted == screen_done_.load(std::memory_order_relaxed)) return;
  const auto command = static_cast<drivers::CommandCode>(screen_command_.load(std::memory_order_relaxed));
  const std::uint32_t arg = screen_arg_.load(std::memory_order_relaxed);
  const bool ok = execute(command, arg);
  CS_QLOG_INFO(log_, kComponent, "command %u (arg %u) from the operator's screen: %s", static_cast<unsigned>(command),
               static_cast<unsigned>(arg), ok ? "done" : "refused");
  screen_ok_.store(ok, std::memory_order_relaxed);
  screen_done_.store(posted, std::memory_order_release);
}

bool ProductionLoop::execute(drivers::CommandCode command, std::uint32_t arg) {
  using drivers::CommandCode;
  switch (command) {
    case CommandCode::kResetCounters:
      trigger_count_ = 0;
      missed_count_ = 0;
      link_.set_trigger_counters(0, 0);
      return true;
    case CommandCode::kSelectModels: {
      // One model database per cellsight process: selecting the active one (again) retries loading it.
      const bool ok = arg == config_.active_models_id;
      if (ok && fault_cause_ == ErrorCode::kModelDatabaseInvalid) models_reload_requested_ = true;
      return ok;
    }
    case CommandCode::kEnterTeach:
      // The kept scans are stored and taught by the operator's screen (hmi/): without it nobody would.
      if (keeper_ == nullptr || arg == 0 || arg > 0xFFFFu) return false;
      teach_part_id_ = static_cast<std::uint16_t>(arg);
      teaching_.store(teach_part_id_, std::memory_order_release);
      return true;
    case CommandCode::kLeaveTeach:
      teach_part_id_ = 0;
      teaching_.store(0, std::memory_order_release);
      return true;
    case CommandCode::kNone: return false;
  }
  return false;
}

bool ProductionLoop::post_command(drivers::CommandCode command, std::uint32_t arg) {
  const std::uint32_t posted = screen_posted_.load(std::memory_order_relaxed);
  if (screen_done_.load(std::memory_order_acquire) != posted) return false;
  screen_command_.store(static_cast<std::uint16_t>(command), std::memory_order_relaxed);
  screen_arg_.store(arg, std::memory_order_relaxed);
  screen_posted_.store(posted + 1, std::memory_order_release);
  return true;
}

std::unique_ptr<Recogniser> ProductionLoop::offer_recogniser(std::unique_ptr<Recogniser> recogniser) {
  return std::unique_ptr<Recogniser>(offered_.exchange(recogniser.release(), std::memory_order_acq_rel));
}

std::unique_ptr<Recogniser> ProductionLoop::take_retired_recogniser() {
  return std::unique_ptr<Recogniser>(retired_.exchange(nullptr, std::memory_order_acq_rel));
}

// Between passes only (idle, the worker idle: the loop owns the worker's slot), and only once the last replaced
// recogniser was taken away: the loop thread never destroys one (unmapping a model database takes long).
void ProductionLoop::swap_offered_recogniser() {
  if (offered_.load(std::memory_order_relaxed) == nullptr || retired_.load(std::memory_order_acquire) != nullptr)
    return;
  if (state_.load(std::memory_order_relaxed) != LoopState::kIdle || !worker_.idle()) return;
  std::unique_ptr<Recogniser> next(offered_.exchange(nullptr, std::memory_order_acq_rel));
  if (!next) return;
  worker_.swap_recogniser(next);
  retired_.store(next.release(), std::memory_order_release);
  swapped_.fetch_add(1, std::memory_order_relaxed);
  CS_QLOG_INFO(log_, kComponent, "new models in place from the next pass on");
}

ProductionLoop::CommandFate ProductionLoop::command_fate() const {
  if (screen_done_.load(std::memory_order_acquire) != screen_posted_.load(std::memory_order_acquire)) {
    return CommandFate::kPending;
  }
  return screen_ok_.load(std::memory_order_relaxed) ? CommandFate::kDone : CommandFate::kRefused;
}

}  // namespace cellsight::runtime
