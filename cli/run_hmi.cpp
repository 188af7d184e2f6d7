#include "cli/run_hmi.hpp"

#include <chrono>
#include <filesystem>
#include <thread>

#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "base/crc32.hpp"
#include "base/file_read.hpp"
#include "drivers/log.hpp"
#include "hmi/parts_api.hpp"

namespace cellsight::cli {
namespace {

constexpr const char* kComponent = "run";
// Results the screen may fall behind by (its pump takes them every 50 ms; parts come at most a few per second).
constexpr std::size_t kFeedCapacity = 256;
// The live picture: a thinned copy of each pass (60 k points, ~1 MB, copied in ~0.2 ms by the recognition thread);
// two slots, so the picture of one part is rendered while the next is handed over.
constexpr std::size_t kPreviewSlots = 2;
constexpr std::size_t kPreviewPoints = 60'000;

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

// What the Health page shows of a file in force (the calibration, the model database's manifest and SVM): path,
// last change and CRC-32 of its bytes, so a technician can tell which one the cell runs with.
nlohmann::json file_in_force(const std::string& path) {
  constexpr std::size_t kMaxBytes = std::size_t{64} << 20;
  nlohmann::json j = {{"file", path}};
  std::error_code ec;
  const auto changed = std::filesystem::last_write_time(path, ec);
  if (ec) {
    j["error"] = ec.message();
    return j;
  }
  const auto since_epoch =
      std::chrono::duration_cast<std::chrono::seconds>(std::chrono::file_clock::to_sys(changed).time_since_epoch());
  j["modified_unix_s"] = since_epoch.count();
  if (auto bytes = base::read_file(path, kMaxBytes)) {
    char crc[16];
    std::snprintf(crc, sizeof crc, "%08x", base::crc32(*bytes));
    j["crc32"] = crc;
    j["bytes"] = bytes->size();
  }
  return j;
}

// The newest svm-*.model of the model database (the one `train` wrote last), or "".
std::string newest_svm(const std::string& models_dir) {
  std::string best;
  std::filesystem::file_time_type best_time{};
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(models_dir, ec)) {
    const std::string name = e.path().filename().string();
    if (name.rfind("svm-", 0) != 0 || e.path().extension() != ".model") continue;
    const auto t = e.last_write_time(ec);
    if (best.empty() || t > best_time) best = e.path().string(), best_time = t;
  }
  return best;
}

// The screen's commands go through the loop's mailbox (ProductionLoop::post_command), as the PLC's do.
class LoopCommands final : public hmi::CellCommands {
 public:
  explicit LoopCommands(runtime::ProductionLoop& loop) : loop_(loop) {}
  bool post(drivers::CommandCode command, std::uint32_t arg) override { return loop_.post_command(command, arg); }
  [[nodiscard]] Fate fate() const override {
    switch (loop_.command_fate()) {
      case runtime::ProductionLoop::CommandFate::kPending: return Fate::kPending;
      case runtime::ProductionLoop::CommandFate::kDone: return Fate::kDone;
      case runtime::ProductionLoop::CommandFate::kRefused: break;
    }
    return Fate::kRefused;
  }
  [[nodiscard]] std::uint16_t teaching_part_id() const override { return loop_.teaching_part_id(); }

 private:
  runtime::ProductionLoop& loop_;
};

}  // namespace

RunHmi::RunHmi(const app::Config& config, int port)
    : params_(config.hmi),
      deadline_ms_(config.runtime.deadline_ms),
      feed_(kFeedCapacity),
      config_path_(config.source.empty() || config.source.front() == '(' ? std::string() : config.source),
      grid_(app::grid_spec(config)),
      keeper_(static_cast<std::size_t>(config.hmi.keep_slots), app::scan_builder_params(config).max_points),
      preview_keeper_(kPreviewSlots, kPreviewPoints) {
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
  loop.set_keeper(&hmi->keeper_, config.hmi.review_unknown);
  loop.set_preview(&hmi->preview_keeper_);
  return hmi;
}

void RunHmi::start(runtime::ProductionLoop& loop, const drivers::PlcLink& link, const std::string& models_dir,
                   const std::string& calibration_path, runtime::RecogniserLoader loader) {
  auto users = hmi::load_users(params_.users_file);
  if (!users) {
    CS_LOG_ERROR(kComponent, "operator's screen without accounts (viewing from this machine only): %s",
                 users.error().message.c_str());
  }
  loop_ = &loop;
  loader_ = std::move(loader);
  // The Parts, Review and Debug pages: their long actions are this binary's own commands, run as child processes.
  // By /proc/self/exe, not its path: an update that replaced the file still starts the program that is running.
  jobs_ = std::make_unique<hmi::JobRunner>("/proc/self/exe", config_path_, models_dir);
  jobs_->set_calibration(std::filesystem::absolute(calibration_path).string());
  review_ = std::make_unique<hmi::ReviewStore>((std::filesystem::path(models_dir) / "review").string(),
                                               params_.review_keep, &keeper_);
  preview_ = std::make_unique<hmi::LivePreview>(models_dir, &preview_keeper_);
  commands_ = std::make_unique<LoopCommands>(loop);
  review_api_ = std::make_unique<hmi::ReviewApi>(*review_, *jobs_, *commands_);
  const int deadline_ms = deadline_ms_;
  hmi::ReviewApi* review_api = review_api_.get();
  models_dir_ = models_dir;
  calibration_path_ = calibration_path;
  note_in_force();
  server_ = std::make_unique<hmi::HmiServer>(params_, users ? std::move(*users) : std::vector<hmi::User>{}, &feed_,
                                             [this, &loop, &link, deadline_ms, models_dir, review_api] {
                                               nlohmann::json status = status_of(loop, link, deadline_ms, models_dir);
                                               status["teach"] = review_api->teach_json();
                                               const std::lock_guard<std::mutex> lock(in_force_mutex_);
                                               status["in_force"] = in_force_;
                                               return status;
                                             });
  server_->add_routes(hmi::parts_routes(*jobs_, {models_dir, grid_, [this] { models_changed(); }}));
  server_->add_routes(review_api_->routes());
  server_->add_routes(preview_->routes());
  if (auto ok = review_->start(); !ok) {
    CS_LOG_ERROR(kComponent, "review: %s; unknown scans are not kept", ok.error().message.c_str());
  }
  if (auto ok = preview_->start(); !ok) CS_LOG_ERROR(kComponent, "live picture: %s", ok.error().message.c_str());
  if (auto ok = server_->start(); !ok) {
    CS_LOG_ERROR(kComponent, "no operator's screen: %s; the cell runs on without it", ok.error().message.c_str());
    server_.reset();
    return;
  }
  serving_ = true;
}

void RunHmi::note_in_force() {
  nlohmann::json facts = {
      {"calibration", file_in_force(calibration_path_)},
      {"manifest", file_in_force((std::filesystem::path(models_dir_) / "manifest.yaml").string())},
  };
  if (const std::string svm = newest_svm(models_dir_); !svm.empty()) facts["svm"] = file_in_force(svm);
  facts["since_unix_s"] =
      std::chrono::duration_cast<std::chrono::seconds>(std::chrono::system_clock::now().time_since_epoch()).count();
  const std::lock_guard<std::mutex> lock(in_force_mutex_);
  in_force_ = std::move(facts);
}

void RunHmi::models_changed() {
  if (!loader_ || loop_ == nullptr) {
    CS_LOG_INFO(kComponent, "the model database changed; the loop uses it from its next start");
    return;
  }
  auto made = loader_();
  if (!made || *made == nullptr) {
    CS_LOG_ERROR(kComponent, "the model database changed but cannot be loaded (%s); the loop keeps its models",
                 made ? "no recogniser" : made.error().message.c_str());
    return;
  }
  // An earlier offer the loop has not taken yet comes back and is destroyed here; the replaced recogniser comes
  // back once the loop has swapped, to be destroyed on this thread, never the loop's.
  (void)loop_->offer_recogniser(std::move(*made));
  if (preview_) preview_->forget_outlines();
  for (int i = 0; i < 600 && loop_->take_retired_recogniser() == nullptr; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  note_in_force();
  CS_LOG_INFO(kComponent, "the loop recognises with the new model database");
}

void RunHmi::stop() {
  if (server_) server_->stop();
  jobs_.reset();  // cancels a running job and reaps it (its hooks use the review store: before it stops)
  if (review_) review_->stop();
  if (preview_) preview_->stop();
  serving_ = false;
}

}  // namespace cellsight::cli
