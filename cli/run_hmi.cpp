#include "cli/run_hmi.hpp"

#include "app/recognition.hpp"
#include "drivers/log.hpp"
#include "hmi/parts_api.hpp"

namespace cellsight::cli {
namespace {

constexpr const char* kComponent = "run";
// Results the screen may fall behind by (its pump takes them every 50 ms; parts come at most a few per second).
constexpr std::size_t kFeedCapacity = 256;

nlohmann::json status_of(const runtime::ProductionLoop& loop, const drivers::PlcLink& link, int deadline_ms,
                         const std::string& models_dir) {
  const runtime::LoopStats s = loop.stats();
  const drivers::LinkStats l = link.stats();
  return {
      {"state", runtime::to_string(s.state)},
      {"error", drivers::to_string(s.error)},
      {"warning", drivers::to_string(s.warning)},
      {"counters",
       {{"triggers", s.triggers},
        {"results", s.results},
        {"results_rejected", s.results_rejected},
        {"timeouts", s.timeouts},
        {"aborted_scans", s.aborted_scans},
        {"missed_triggers", s.missed_triggers},
        {"faults", s.faults},
        {"recoveries", s.recoveries},
        {"late_decisions", s.late_decisions},
        {"log_lines_dropped", s.log_lines_dropped}}},
      {"cycle", {{"last_ms", s.last_cycle_ms}, {"max_ms", s.max_cycle_ms}, {"deadline_ms", deadline_ms}}},
      {"realtime", {{"applied", s.realtime_applied}, {"memory_locked", s.memory_locked}}},
      {"plc",
       {{"clients_connected", l.clients_connected},
        {"results_published", l.results_published},
        {"results_presented", l.results_presented},
        {"results_acked", l.results_acked},
        {"queue_depth", l.queue_depth},
        {"last_seq", l.last_seq},
        {"requests_served", l.requests_served},
        {"clients_accepted", l.clients_accepted},
        {"clients_refused", l.clients_refused},
        {"clients_evicted", l.clients_evicted},
        {"clients_dropped", l.clients_dropped},
        {"heartbeat_losses", l.heartbeat_losses},
        {"loop_stalls", l.loop_stalls}}},
      {"models", {{"dir", models_dir}}},
  };
}

}  // namespace

RunHmi::RunHmi(const app::Config& config, int port)
    : params_(config.hmi),
      deadline_ms_(config.runtime.deadline_ms),
      feed_(kFeedCapacity),
      config_path_(config.source.empty() || config.source.front() == '(' ? std::string() : config.source),
      grid_(app::grid_spec(config)) {
  if (port >= 0) params_.port = port;
}

std::unique_ptr<RunHmi> RunHmi::attach(const app::Config& config, const app::RunOptions& options,
                                       runtime::ProductionLoop& loop, runtime::LoopObserver* next) {
  if (!config.hmi.enabled || !options.hmi) {
    if (next != nullptr) loop.set_observer(next);
    return nullptr;
  }
  auto hmi = std::make_unique<RunHmi>(config, options.hmi_port);
  hmi->feed_.set_next(next);
  loop.set_observer(&hmi->feed_);
  return hmi;
}

void RunHmi::start(const runtime::ProductionLoop& loop, const drivers::PlcLink& link, const std::string& models_dir) {
  auto users = hmi::load_users(params_.users_file);
  if (!users) {
    CS_LOG_ERROR(kComponent, "operator's screen without accounts (viewing from this machine only): %s",
                 users.error().message.c_str());
  }
  const int deadline_ms = deadline_ms_;
  server_ = std::make_unique<hmi::HmiServer>(
      params_, users ? std::move(*users) : std::vector<hmi::User>{}, &feed_,
      [&loop, &link, deadline_ms, models_dir] { return status_of(loop, link, deadline_ms, models_dir); });
  // The Parts and Debug pages: their long actions are this binary's own commands, run as child processes. By
  // /proc/self/exe, not its path: an update that replaced the file still starts the program that is running.
  jobs_ = std::make_unique<hmi::JobRunner>("/proc/self/exe", config_path_, models_dir);
  std::function<void()> changed = models_changed_;
  if (!changed) {  // TODO(issue 14, review/loop wiring): set_models_changed() from run_mode with the loop's reload
    changed = [] { CS_LOG_INFO(kComponent, "the model database changed; the loop uses it from its next start"); };
  }
  server_->add_routes(hmi::parts_routes(*jobs_, {models_dir, grid_, std::move(changed)}));
  if (auto ok = server_->start(); !ok) {
    CS_LOG_ERROR(kComponent, "no operator's screen: %s; the cell runs on without it", ok.error().message.c_str());
    server_.reset();
    jobs_.reset();
    return;
  }
  serving_ = true;
}

void RunHmi::stop() {
  if (server_) server_->stop();
  jobs_.reset();  // cancels a running job and reaps it
  serving_ = false;
}

}  // namespace cellsight::cli
