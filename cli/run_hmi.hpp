// The operator's screen inside `cellsight run` (hmi/): the live feed as the loop's observer (chained before the
// simulated cell's truth log), the accounts file, the server and the status JSON it shows. A screen that cannot
// start (port taken, unreadable accounts) is logged as an error and the cell runs on: the PLC's results never
// depend on a browser.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "app/config.hpp"
#include "app/run_options.hpp"
#include "drivers/modbus/plc_link.hpp"
#include "hmi/jobs.hpp"
#include "hmi/live_feed.hpp"
#include "hmi/server.hpp"
#include "runtime/production_loop.hpp"

namespace cellsight::cli {

class RunHmi {
 public:
  // Before loop.start(). Sets the loop's observer: the feed chaining `next` when the screen is on, else `next`.
  static std::unique_ptr<RunHmi> attach(const app::Config& config, const app::RunOptions& options,
                                        runtime::ProductionLoop& loop, runtime::LoopObserver* next);
  // After loop.start(): serves, or logs why not. `link` and `loop` outlive stop().
  void start(const runtime::ProductionLoop& loop, const drivers::PlcLink& link, const std::string& models_dir);
  void stop();
  // Before start(): what the Parts page calls after a delete or a training that succeeded (on the job runner's
  // thread), so that the loop loads the changed database. Until set: a log line only.
  void set_models_changed(std::function<void()> fn) { models_changed_ = std::move(fn); }
  [[nodiscard]] std::string url() const { return serving_ ? server_->url() : std::string(); }

  RunHmi(const app::Config& config, int port);

 private:
  hmi::HmiParams params_;
  int deadline_ms_;
  hmi::LiveFeed feed_;
  std::string config_path_;  // the file `run` was started with ("" with the built-in defaults)
  algo::GridSpec grid_;
  std::function<void()> models_changed_;
  std::unique_ptr<hmi::JobRunner> jobs_;  // before server_: the routes borrow it, so it goes after the server
  std::unique_ptr<hmi::HmiServer> server_;
  bool serving_ = false;
};

}  // namespace cellsight::cli
