// The operator's screen inside `cellsight run` (hmi/): the live feed as the loop's observer (chained before the
// simulated cell's truth log), the accounts file, the server and the status JSON it shows. A screen that cannot
// start (port taken, unreadable accounts) is logged as an error and the cell runs on: the PLC's results never
// depend on a browser.
#pragma once

#include <functional>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>

#include "app/config.hpp"
#include "app/run_options.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "hmi/jobs.hpp"
#include "hmi/live_feed.hpp"
#include "hmi/live_preview.hpp"
#include "hmi/review_api.hpp"
#include "hmi/review_store.hpp"
#include "hmi/server.hpp"
#include "runtime/production_loop.hpp"
#include "runtime/scan_keeper.hpp"

namespace cellsight::cli {

class RunHmi {
 public:
  // Before loop.start(). Sets the loop's observer (the feed chaining `next` when the screen is on, else `next`), its
  // scan keeper (unknown and teach passes for the Review page) and its preview keeper (the live picture).
  static std::unique_ptr<RunHmi> attach(const app::Config& config, const app::RunOptions& options,
                                        runtime::ProductionLoop& loop, runtime::LoopObserver* next);
  // After loop.start(): serves, or logs why not. `link` and `loop` outlive stop(). `loader` builds a recogniser from
  // the model database: after a retrain or a delete the new one is offered to the loop, which puts it in place
  // between passes; empty (--sim-oracle): the loop keeps what it has.
  void start(runtime::ProductionLoop& loop, const drivers::PlcLink& link, const std::string& models_dir,
             const std::string& calibration_path, runtime::RecogniserLoader loader);
  void stop();  // the server, then a running job (cancelled and reaped), then the writer threads; idempotent
  ~RunHmi() { stop(); }
  RunHmi(const RunHmi&) = delete;
  RunHmi& operator=(const RunHmi&) = delete;
  [[nodiscard]] std::string url() const { return serving_ ? server_->url() : std::string(); }

  RunHmi(const app::Config& config, int port);

 private:
  // After a delete or a training that succeeded (job runner's thread): a new recogniser for the loop, built here.
  void models_changed();
  // The calibration and model files the loop runs with (path, change time, CRC-32), for the Health page.
  void note_in_force();

  hmi::HmiParams params_;
  int deadline_ms_;
  hmi::LiveFeed feed_;
  std::string config_path_;  // the file `run` was started with ("" with the built-in defaults)
  algo::GridSpec grid_;
  runtime::ScanKeeper keeper_;
  runtime::ScanKeeper preview_keeper_;  // thinned copies of every recognised pass for the live picture
  runtime::ProductionLoop* loop_ = nullptr;
  runtime::RecogniserLoader loader_;
  std::string models_dir_;
  std::string calibration_path_;
  std::mutex in_force_mutex_;
  nlohmann::json in_force_;
  std::unique_ptr<hmi::ReviewStore> review_;
  std::unique_ptr<hmi::LivePreview> preview_;
  std::unique_ptr<hmi::JobRunner> jobs_;  // before server_: the routes borrow it, so it goes after the server
  std::unique_ptr<hmi::CellCommands> commands_;
  std::unique_ptr<hmi::ReviewApi> review_api_;
  std::unique_ptr<hmi::HmiServer> server_;
  bool serving_ = false;
};

}  // namespace cellsight::cli
