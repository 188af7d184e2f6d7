// `cellsight run` implementation: start-up wiring, the simulated conveyor's feed, signals and shutdown.
#include "cli/run_mode.hpp"

#include <pthread.h>
#include <signal.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <numbers>
#include <optional>
#include <random>
#include <span>
#include <string_view>
#include <thread>

#include "app/devices.hpp"
#include "app/loop_wiring.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/run_sim.hpp"
#include "app/scan_acquisition.hpp"
#include "cli/cli.hpp"
#include "cli/run_hmi.hpp"
#include "drivers/log.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "drivers/sim/sim_faults.hpp"
#include "formats/calibration_file.hpp"
#include "formats/template_file.hpp"
#include "runtime/production_loop.hpp"
#include "runtime/service_notify.hpp"

namespace cellsight::cli {

using runtime::LoopConfig;
using runtime::LoopObserver;
using runtime::LoopStats;
using runtime::PartRecord;
using runtime::ProductionLoop;
using runtime::RecogniserLoader;
using runtime::ServiceNotifier;
using runtime::TriggerSource;

const char* const kRunUsage =
    "  run [--sim] [--parts N] [--models DIR] [--calibration FILE] [--port P] [--hmi-port P | --no-hmi]\n"
    "      [--sim: --seed S --sim-parts A,B,.. --truth-log FILE --wait-plc --sim-oracle --sim-faults SPEC\n"
    "       --sim-replay K]\n"
    "        the production cell: scan, recognise, publish to the PLC over Modbus TCP until SIGTERM/SIGINT or N\n"
    "        parts; --sim runs the simulated camera, GPIO and conveyor (as fast as the CPU allows), with random\n"
    "        catalogue parts (--sim-parts: only these); --wait-plc lets\n"
    "        the simulated conveyor wait for TRIGGER_ENABLE and a free result queue; --truth-log writes the\n"
    "        simulator's truth per acquisition (JSON lines); --sim-oracle decides from that truth (runtime tests\n"
    "        without a model database, not recognition); --sim-faults KIND@EVERY[/VALUE],... injects faults into\n"
    "        every EVERY-th simulated pass (camera_stall, camera_hiccup, encoder_glitch, chatter; the soak test);\n"
    "        --sim-replay K: the conveyor brings K distinct passes over and over, each rendered once and then\n"
    "        replayed byte for byte from memory (K x one pass of frames), so the loop runs as fast as it works;\n"
    "        the operator's screen (section hmi of the config) is served unless --no-hmi; --hmi-port overrides\n"
    "        its port (0: any free port)\n";

namespace {

constexpr const char* kComponent = "run";
constexpr auto kMainWait = std::chrono::milliseconds(50);
constexpr int kPortMax = 65535;

std::atomic<int> g_stop_signal{0};
static_assert(std::atomic<int>::is_always_lock_free, "the signal handler needs a lock-free flag");

extern "C" void on_stop_signal(int signal_number) {
  g_stop_signal.store(signal_number, std::memory_order_relaxed);
}

// SIGTERM/SIGINT set a flag the main thread polls; SIGPIPE is ignored (a PLC closing its socket is no reason to die).
class SignalScope {
 public:
  SignalScope() {
    g_stop_signal.store(0);
    struct sigaction action {};
    action.sa_handler = on_stop_signal;
    sigemptyset(&action.sa_mask);
    action.sa_flags = 0;
    (void)sigaction(SIGTERM, &action, &old_term_);
    (void)sigaction(SIGINT, &action, &old_int_);
    struct sigaction ignore {};
    ignore.sa_handler = SIG_IGN;
    sigemptyset(&ignore.sa_mask);
    (void)sigaction(SIGPIPE, &ignore, &old_pipe_);
  }
  ~SignalScope() {
    (void)sigaction(SIGTERM, &old_term_, nullptr);
    (void)sigaction(SIGINT, &old_int_, nullptr);
    (void)sigaction(SIGPIPE, &old_pipe_, nullptr);
  }
  SignalScope(const SignalScope&) = delete;
  SignalScope& operator=(const SignalScope&) = delete;
  [[nodiscard]] static int caught() { return g_stop_signal.load(std::memory_order_relaxed); }

 private:
  struct sigaction old_term_ {};
  struct sigaction old_int_ {};
  struct sigaction old_pipe_ {};
};

// Threads created while this lives do not take SIGTERM/SIGINT: the signals go to the main thread, and a worker's
// blocking call (poll on the camera, the network) is never cut short by them.
class StopSignalsBlocked {
 public:
  StopSignalsBlocked() {
    sigset_t set;
    sigemptyset(&set);
    sigaddset(&set, SIGTERM);
    sigaddset(&set, SIGINT);
    (void)pthread_sigmask(SIG_BLOCK, &set, &old_);
  }
  ~StopSignalsBlocked() { (void)pthread_sigmask(SIG_SETMASK, &old_, nullptr); }
  StopSignalsBlocked(const StopSignalsBlocked&) = delete;
  StopSignalsBlocked& operator=(const StopSignalsBlocked&) = delete;

 private:
  sigset_t old_{};
};

}  // namespace

Expected<app::RunOptions> parse_run_args(const std::vector<std::string>& args) {
  app::RunOptions options;
  bool seed_given = false;
  for (std::size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const bool has_value = i + 1 < args.size();
    auto need_value = [&]() -> Expected<std::string> {
      if (!has_value) return make_error(a + " needs a value");
      return args[++i];
    };
    if (a == "--sim") {
      options.sim = true;
    } else if (a == "--wait-plc") {
      options.wait_plc = true;
    } else if (a == "--sim-oracle") {
      options.sim_oracle = true;
    } else if (a == "--no-hmi") {
      options.hmi = false;
    } else if (a == "--config" || a == "--log-level") {
      if (!has_value) return make_error(a + " needs a value");
      ++i;  // handled by the front end
    } else if (a == "--parts" || a == "--seed" || a == "--port" || a == "--hmi-port" || a == "--sim-replay") {
      auto value = need_value();
      if (!value) return value.error();
      std::uint64_t number = 0;
      if (!app::parse_u64(*value, number)) return make_error(a + " '" + *value + "': expected a whole number >= 0");
      if (a == "--parts") {
        options.parts = number;
      } else if (a == "--sim-replay") {
        if (number == 0 || number > app::kPregeneratedPasses) {
          return make_error("--sim-replay " + *value + ": 1.." + std::to_string(app::kPregeneratedPasses) + " passes");
        }
        options.sim_replay = number;
      } else if (a == "--seed") {
        options.seed = number;
        seed_given = true;
      } else {
        if (number > static_cast<std::uint64_t>(kPortMax)) return make_error(a + " " + *value + ": 0..65535");
        (a == "--port" ? options.port : options.hmi_port) = static_cast<int>(number);
      }
    } else if (a == "--sim-faults") {
      auto value = need_value();
      if (!value) return value.error();
      options.sim_faults = *value;
    } else if (a == "--sim-parts") {
      auto value = need_value();
      if (!value) return value.error();
      std::size_t from = 0;
      while (from <= value->size()) {
        const std::size_t comma = std::min(value->find(',', from), value->size());
        if (comma > from) options.sim_parts.push_back(value->substr(from, comma - from));
        from = comma + 1;
      }
      if (options.sim_parts.empty()) return make_error("--sim-parts needs part names, e.g. plate_4h,tray");
    } else if (a == "--models" || a == "--calibration" || a == "--truth-log") {
      auto value = need_value();
      if (!value) return value.error();
      (a == "--models"        ? options.models_dir
       : a == "--calibration" ? options.calibration_path
                              : options.truth_log) = *value;
    } else {
      return make_error("unexpected '" + a + "' (usage:\n" + kRunUsage + ")");
    }
  }
  if (!options.sim && (seed_given || !options.truth_log.empty() || options.wait_plc || options.sim_oracle ||
                       !options.sim_parts.empty() || !options.sim_faults.empty() || options.sim_replay > 0)) {
    return make_error(
        "--seed, --sim-parts, --sim-faults, --sim-replay, --truth-log, --wait-plc and --sim-oracle apply to the "
        "simulated cell: add --sim");
  }
  if (auto plan = sim::FaultPlan::parse(options.sim_faults, {}); !plan) return plan.error();
  return options;
}

drivers::ModbusServerConfig modbus_server_config(const app::Config& config) {
  drivers::ModbusServerConfig c;
  c.bind_address = config.modbus.bind_address;
  c.port = static_cast<std::uint16_t>(std::clamp(config.modbus.port, 0, kPortMax));
  c.max_clients = config.modbus.max_clients;
  c.byte_timeout_ms = config.modbus.byte_timeout_ms;
  c.link.result_queue_capacity = static_cast<std::size_t>(std::max(1, config.modbus.result_queue_depth));
  c.link.plc_heartbeat_timeout_ms = config.modbus.plc_heartbeat_timeout_ms;
  return c;
}

namespace {

// The recogniser the loop starts with: the model database's (and a loader that retries it), or the simulator's
// oracle. An error is the user's (exit 2): with --parts there is no point in a run that cannot recognise.
struct RecogniserSetup {
  std::unique_ptr<runtime::Recogniser> recogniser;
  RecogniserLoader loader;
};

Expected<RecogniserSetup> set_up_recogniser(const app::Config& config, const app::RunOptions& options,
                                            const std::string& models_dir, const std::string& calibration_path,
                                            const app::SimRun* sim) {
  RecogniserSetup setup;
  if (options.sim_oracle) {
    CS_LOG_WARN(kComponent, "--sim-oracle: decisions come from the simulator's truth, not from recognition");
    setup.recogniser = sim->make_oracle();
    return setup;
  }
  // A database that does not fit the memory budget is refused here, whatever else: it cannot come right by
  // retrying, and a loop that paged its templates in would miss its deadlines (issue 11).
  if (auto db = app::ModelDb::open(models_dir, app::grid_spec(config), false)) {
    if (Status fits = app::check_model_budget(config, *db, app::model_footprint(*db)); !fits) return fits.error();
  }
  setup.loader = [config, models_dir, calibration_path]() {
    return app::make_recogniser(config, models_dir, calibration_path);
  };
  auto made = setup.loader();
  if (made) {
    setup.recogniser = std::move(*made);
  } else if (options.parts > 0) {
    return made.error();
  } else {
    // A service stays up and tells the PLC (ERROR_CODE model database invalid) instead of crash-looping; it
    // retries on CLEAR_ERROR, SELECT_MODELS and every few seconds.
    CS_LOG_ERROR(kComponent, "%s", made.error().message.c_str());
  }
  return setup;
}

LoopConfig run_loop_settings(const app::Config& config, const app::RunOptions& options, bool sim) {
  LoopConfig settings = app::loop_config(config);
  settings.max_parts = options.parts;
  if (sim) {
    settings.conveyor_waits_for_ready = true;
    settings.edge_timestamps_monotonic = false;  // simulated time
    // Free running unless the PLC paces the simulated line (then as DESIGN.md: TRIGGER_ENABLE, and a full result
    // queue holds the conveyor instead of losing results).
    settings.require_trigger_enable = options.wait_plc;
    settings.hold_when_queue_full = options.wait_plc;
  }
  return settings;
}

// Until SIGTERM/SIGINT or the loop's --parts (with --wait-plc: until the PLC acknowledged them all). True when the
// PLC took every result.
bool serve(ProductionLoop& loop, const drivers::ModbusServer& server, app::SimRun* sim,
           const app::RunOptions& options) {
  while (SignalScope::caught() == 0) {
    if (sim != nullptr) sim->feed(loop.finished());
    if (loop.finished()) {
      if (!options.wait_plc) return false;
      const drivers::LinkStats link = server.stats();
      // Every result presented and acknowledged: the PLC has them all.
      if (link.queue_depth == 0 && link.results_presented == link.results_published &&
          link.results_acked >= link.results_presented) {
        return true;
      }
    }
    (void)loop.wait_finished(kMainWait);
    if (loop.finished() && options.wait_plc) std::this_thread::sleep_for(kMainWait);
  }
  return false;
}

void log_run_summary(double seconds, const LoopStats& stats, const drivers::LinkStats& link,
                     const app::RunOptions& options, bool all_taken) {
  CS_LOG_INFO(kComponent,
              "stopped after %.1f s: %" PRIu64 " parts, %" PRIu64 " results (%" PRIu64 " timeouts, %" PRIu64
              " late decisions, %" PRIu64 " aborted scans, %" PRIu64 " rejected), %" PRIu64 " faults (%" PRIu64
              " recovered), %" PRIu64 " missed triggers, max cycle %.1f ms; PLC: %" PRIu64 " presented, %" PRIu64
              " acknowledged%s; Modbus clients: %" PRIu64 " accepted, %" PRIu64 " evicted, %" PRIu64
              " refused, %" PRIu64 " dropped",
              seconds, stats.triggers, stats.results, stats.timeouts, stats.late_decisions, stats.aborted_scans,
              stats.results_rejected, stats.faults, stats.recoveries, stats.missed_triggers, stats.max_cycle_ms,
              link.results_presented, link.results_acked,
              options.wait_plc && options.parts > 0 && !all_taken ? " (not all taken)" : "", link.clients_accepted,
              link.clients_evicted, link.clients_refused, link.clients_dropped);
}

// READY=1 for systemd (with the one status line `systemctl status` shows) and the log line that the run is on.
void announce_ready(ServiceNotifier& service, const std::string& address, std::uint16_t port, bool sim,
                    std::uint64_t parts) {
  char status[128];
  std::snprintf(status, sizeof status, "serving Modbus on %s:%u%s", address.c_str(), static_cast<unsigned>(port),
                sim ? " (simulated cell)" : "");
  service.ready(status);
  CS_LOG_INFO(kComponent, "running%s: Modbus %s:%u, %s%s", sim ? " the simulated cell" : "", address.c_str(),
              static_cast<unsigned>(port), parts > 0 ? "parts " : "until SIGTERM/SIGINT",
              parts > 0 ? std::to_string(parts).c_str() : "");
}

int fail(int code, const std::string& why) {
  std::fprintf(stderr, "cellsight run: %s\n", why.c_str());
  return code;
}

}  // namespace

int run_run(const std::vector<std::string>& args, const app::Config& config) {
  // First: a SIGTERM that arrives while starting up must stop the run, not kill it half-way.
  SignalScope signals;
  auto parsed = parse_run_args(args);
  if (!parsed) return fail(kExitUsage, parsed.error().message);
  const app::RunOptions options = *parsed;
  const bool sim = options.sim || config.camera.backend == "sim" || config.gpio.backend == "sim";
  if (!options.sim && sim) {
    CS_LOG_INFO(kComponent, "the configuration names simulated devices (camera.backend %s, gpio.backend %s)",
                config.camera.backend.c_str(), config.gpio.backend.c_str());
  }

  // ---- calibration: required, never the simulator's true rig ----
  const std::string calibration_path =
      options.calibration_path.empty() ? app::default_calibration_path(config) : options.calibration_path;
  auto calibration = formats::load_sensor_calibration(calibration_path);
  if (!calibration) {
    return fail(kExitUsage,
                calibration.error().message + "\n(run scripts/calibrate.sh, or cellsight calibrate, first)");
  }

  // ---- the simulated cell (run_sim.cpp): conveyor feed, faults, oracle, truth log ----
  std::unique_ptr<app::SimRun> sim_run;
  if (sim) {
    auto made = app::SimRun::create(config, options);
    if (!made) return fail(kExitUsage, made.error().message);
    sim_run = std::move(*made);
    if (auto ok = sim_run->enable_replay(); !ok) return fail(kExitFailure, ok.error().message);
  }

  // ---- devices ----
  auto devices = app::make_devices(config, sim_run ? &sim_run->line() : nullptr, options.sim);
  if (!devices) return fail(kExitUsage, devices.error().message);
  if (auto ok = devices->open(); !ok) return fail(kExitFailure, ok.error().message);
  struct DevicesCloser {
    app::Devices& devices;
    ~DevicesCloser() { devices.close(); }
  } devices_closer{*devices};

  // ---- recogniser ----
  const std::string models_dir = options.models_dir.empty() ? config.runtime.models_dir : options.models_dir;
  auto recognition = set_up_recogniser(config, options, models_dir, calibration_path, sim_run.get());
  if (!recognition) return fail(kExitUsage, recognition.error().message);

  // ---- Modbus ----
  drivers::ModbusServerConfig server_config = modbus_server_config(config);
  if (options.port >= 0) server_config.port = static_cast<std::uint16_t>(options.port);
  drivers::ModbusServer server(server_config);

  // ---- the loop ----
  ServiceNotifier service;
  ProductionLoop loop(run_loop_settings(config, options, sim), *devices->camera, *devices->io, *devices->encoder,
                      app::scan_builder_params(config), *calibration, server);
  loop.set_recogniser(std::move(recognition->recogniser));
  if (recognition->loader) loop.set_recogniser_loader(recognition->loader);
  loop.set_service(&service);
  LoopObserver* truth = sim_run ? sim_run->truth_observer(config, models_dir) : nullptr;
  const std::unique_ptr<RunHmi> hmi = RunHmi::attach(config, options, loop, truth);

  // The server starts once the loop is built (scan buffers allocated), just before the loop runs: the link's loop
  // watchdog then never sees a silent start-up.
  {
    const StopSignalsBlocked for_the_threads;
    if (auto ok = server.start(); !ok) return fail(kExitFailure, ok.error().message);
    if (auto ok = loop.start(); !ok) {
      server.stop();
      return fail(kExitFailure, ok.error().message);
    }
    // Its threads, too, leave the stop signals to this one.
    if (hmi) hmi->start(loop, server, models_dir, calibration_path, recognition->loader);
  }
  announce_ready(service, server_config.bind_address, server.bound_port(), sim, options.parts);

  const auto started = std::chrono::steady_clock::now();
  const bool all_taken = serve(loop, server, sim_run.get(), options);
  if (const int sig = SignalScope::caught(); sig != 0) {
    CS_LOG_INFO(kComponent, "%s: stopping", sig == SIGTERM ? "SIGTERM" : sig == SIGINT ? "SIGINT" : "signal");
  }
  service.stopping();
  // The loop first: it abandons the pass in flight at once. Stopping the screen's server can take up to a second
  // (civetweb joins its threads), and a pass must not be finished and published in that time after a SIGTERM.
  loop.request_stop();
  if (hmi) hmi->stop();
  loop.join();
  const LoopStats stats = loop.stats();
  const drivers::LinkStats link = server.stats();
  server.stop();
  log_run_summary(std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count(), stats, link,
                  options, all_taken);
  if (sim_run) sim_run->log_summary(*devices->io);
  return kExitOk;
}

}  // namespace cellsight::cli
