// `cellsight run` implementation: start-up wiring, the simulated conveyor's feed, signals and shutdown.
#include "app/run_mode.hpp"

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

#include "app/calibration_file.hpp"
#include "app/cli.hpp"
#include "app/devices.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/scan_mode.hpp"
#include "app/sim_mode.hpp"
#include "app/template_file.hpp"
#include "drivers/log.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "drivers/sim/sim_faults.hpp"
#include "runtime/loop_wiring.hpp"
#include "runtime/production_loop.hpp"
#include "runtime/service_notify.hpp"

namespace cellsight::app {

using runtime::LoopConfig;
using runtime::LoopObserver;
using runtime::LoopStats;
using runtime::PartRecord;
using runtime::ProductionLoop;
using runtime::RecogniserLoader;
using runtime::ServiceNotifier;
using runtime::TriggerSource;

const char* const kRunUsage =
    "  run [--sim] [--parts N] [--models DIR] [--calibration FILE] [--port P]\n"
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
    "        replayed byte for byte from memory (K x one pass of frames), so the loop runs as fast as it works\n";

namespace {

constexpr const char* kComponent = "run";
constexpr std::size_t kPregeneratedPasses = 1024;  // --sim: the passes cycle through this many drawn specs
constexpr std::size_t kQueuedPassesAhead = 2;      // --sim: parts waiting on the simulated conveyor
constexpr std::size_t kAcqRing = 256;              // acquisition id -> simulated pass, for the truth log
constexpr auto kMainWait = std::chrono::milliseconds(50);
constexpr int kPortMax = 65535;
constexpr double kDegPerRad = 180.0 / std::numbers::pi;

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

bool parse_u64(const std::string& text, std::uint64_t& out) {
  if (text.empty() || text[0] == '-' || text[0] == '+') return false;
  char* end = nullptr;
  errno = 0;
  const unsigned long long value = std::strtoull(text.c_str(), &end, 10);
  if (*end != '\0' || errno != 0) return false;
  out = value;
  return true;
}

// The simulated conveyor's parts: drawn once at start-up, then fed in order (cycling for long runs).
struct SimFeed {
  std::vector<sim::PassSpec> passes;
  std::vector<int> part_index;  // into the catalogue, per pass
};

Expected<SimFeed> draw_passes(const sim::SimCell& cell, std::uint64_t seed, std::uint64_t parts,
                              const std::vector<std::string>& only, std::uint64_t distinct) {
  SimFeed feed;
  const std::size_t count = distinct > 0 ? distinct
                            : parts == 0 ? kPregeneratedPasses
                                         : std::min<std::uint64_t>(parts, kPregeneratedPasses);
  const auto& catalogue = cell.catalogue();
  std::vector<std::size_t> candidates;  // catalogue indices that may arrive
  for (std::size_t i = 0; i < catalogue.size(); ++i) {
    if (only.empty() || std::find(only.begin(), only.end(), catalogue[i].name) != only.end()) candidates.push_back(i);
  }
  for (const std::string& name : only) {
    if (cell.find_part(name) == nullptr) return cell.random_pass(name, 0).error();  // names the known parts
  }
  if (candidates.empty()) return make_error("the simulated cell's catalogue has no parts");
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<std::size_t> pick(0, candidates.size() - 1);
  feed.passes.reserve(count);
  feed.part_index.reserve(count);
  constexpr std::uint64_t kSeedStride = 1'000'003;  // distinct pass seeds per run seed
  for (std::size_t k = 0; k < count; ++k) {
    const std::size_t index = candidates[pick(rng)];
    auto pass = cell.random_pass(catalogue[index].name, seed * kSeedStride + k);
    if (!pass) return pass.error();
    feed.passes.push_back(std::move(*pass));
    feed.part_index.push_back(static_cast<int>(index));
  }
  return feed;
}

// --sim-oracle: the simulator's truth of the pass under the sensor as the decision, so the runtime (loop, Modbus,
// handshake, truth log) can be tested end to end before a model database exists. PLC id = catalogue index + 1.
class SimOracle final : public Recogniser {
 public:
  SimOracle(const sim::SimLine& line, const sim::SimCell& cell, const SimFeed& feed)
      : line_(line), cell_(cell), feed_(feed) {}

  algo::Decision recognise(std::span<const algo::ScanPoint> points,
                           std::chrono::steady_clock::time_point deadline) override {
    algo::Decision d;
    if (std::chrono::steady_clock::now() > deadline) {
      d.source = algo::DecisionSource::kTimeout;
      return d;
    }
    const std::uint64_t started = line_.passes_started();
    if (started == 0 || points.empty()) {
      d.source = algo::DecisionSource::kNoPart;
      return d;
    }
    const std::size_t k = (started - 1) % feed_.passes.size();
    const sim::PassSpec& pass = feed_.passes[k];
    d.source = algo::DecisionSource::kSvm;
    d.class_index = feed_.part_index[k];
    d.part_id = d.class_index + 1;
    d.probability = 1.0;
    d.pose_valid = true;
    d.pose = {pass.pose.x_m, pass.pose.y_m, pass.pose.theta_rad};
    return d;
  }

  std::string_view class_name(int class_index) const override {
    if (class_index < 0 || static_cast<std::size_t>(class_index) >= cell_.catalogue().size()) return {};
    return cell_.catalogue()[static_cast<std::size_t>(class_index)].name;
  }

 private:
  const sim::SimLine& line_;
  const sim::SimCell& cell_;
  const SimFeed& feed_;
};

// --truth-log: one JSON line per acquisition with the simulator's truth of its pass. Runs on the loop thread; formats
// with fprintf into the FILE's buffer (no operator new).
class TruthLog final : public LoopObserver {
 public:
  TruthLog(std::FILE* file, const sim::SimLine& line, const SimFeed& feed, const sim::FaultPlan& faults,
           bool with_oracle_ids)
      : file_(file), line_(line), feed_(feed), faults_(faults), with_oracle_ids_(with_oracle_ids) {
    pass_of_acq_.fill(-1);
  }

  void on_pass_started(std::uint32_t acq_id, TriggerSource trigger) override {
    const std::uint64_t started = line_.passes_started();
    pass_of_acq_[acq_id % kAcqRing] =
        trigger == TriggerSource::kPartPresent && started > 0 ? static_cast<std::int64_t>(started - 1) : -1;
  }

  void on_part_done(const PartRecord& record) override {
    const std::int64_t pass_index = pass_of_acq_[record.acq_id % kAcqRing];
    if (pass_index < 0) {
      std::fprintf(file_, "{\"acq_id\": %" PRIu32 ", \"pass\": null}\n", record.acq_id);
      std::fflush(file_);
      return;
    }
    const std::size_t k = static_cast<std::size_t>(pass_index) % feed_.passes.size();
    const sim::PassSpec& pass = feed_.passes[k];
    std::fprintf(file_,
                 "{\"acq_id\": %" PRIu32 ", \"pass\": %" PRId64 ", \"part\": \"%s\", \"seed\": %" PRIu64
                 ", \"pose\": {\"x_m\": %.9f, \"y_m\": %.9f, \"theta_deg\": %.9f, \"swing_deg\": %.9f}, "
                 "\"coating\": \"%s\"",
                 record.acq_id, pass_index, pass.part.c_str(), pass.seed, pass.pose.x_m, pass.pose.y_m,
                 pass.pose.theta_rad * kDegPerRad, pass.pose.swing_rad * kDegPerRad, pass.coating_a.name.c_str());
    if (with_oracle_ids_) std::fprintf(file_, ", \"oracle_part_id\": %d", feed_.part_index[k] + 1);
    const std::string_view fault = faults_.kind_of(static_cast<std::uint64_t>(pass_index));
    if (!fault.empty()) std::fprintf(file_, ", \"fault\": \"%.*s\"", static_cast<int>(fault.size()), fault.data());
    std::fputs("}\n", file_);
    std::fflush(file_);
  }

 private:
  std::FILE* file_;
  const sim::SimLine& line_;
  const SimFeed& feed_;
  const sim::FaultPlan& faults_;
  bool with_oracle_ids_;
  std::array<std::int64_t, kAcqRing> pass_of_acq_{};
};

// --truth-log with a model database: one line per taught part with the truth of its template scan, so a test can
// turn the simulator's poses into DESIGN.md's pose (the displacement from the template about its centroid c):
// for template pose (t_t, theta_t), scan pose (t_s, theta_s) and nominal centre C0 of the simulator,
// theta = theta_s - theta_t and t = t_s - t_t + (I - R(theta)) (C0 + t_t - c). Parts whose template did not come
// from the simulated cell ("sim seed N") get "seed": null.
void write_template_truth(std::FILE* file, const Config& config, const sim::SimCell& cell,
                          const std::string& models_dir) {
  auto db = ModelDb::open(models_dir, grid_spec(config), false);
  if (!db) {
    CS_LOG_WARN(kComponent, "truth log: no template truth: %s", db.error().message.c_str());
    return;
  }
  constexpr std::string_view kSimSeed = "sim seed ";
  for (const PartEntry& part : db->manifest().parts) {
    std::fprintf(file, "{\"template\": \"%s\", \"part_id\": %d", part.name.c_str(), part.id);
    const sim::PartSpec* spec = cell.find_part(part.name);
    std::uint64_t seed = 0;
    const ScanEntry* source = part.template_scan_entry();  // the pass the template was built from
    const bool from_sim = spec != nullptr && source != nullptr && source->source.rfind(kSimSeed, 0) == 0 &&
                          parse_u64(source->source.substr(kSimSeed.size()), seed);
    auto pass = from_sim ? cell.random_pass(part.name, seed) : Expected<sim::PassSpec>(make_error("not simulated"));
    auto info = read_template_info(db->path_of(part.template_file));
    if (pass && info) {
      const Eigen::Vector3d c0 = cell.nominal_centre(*spec);
      std::fprintf(file,
                   ", \"seed\": %" PRIu64
                   ", \"pose\": {\"x_m\": %.9f, \"y_m\": %.9f, \"theta_deg\": %.9f, "
                   "\"swing_deg\": %.9f}, \"nominal_centre_m\": [%.9f, %.9f], \"centroid_m\": [%.9f, %.9f]}\n",
                   seed, pass->pose.x_m, pass->pose.y_m, pass->pose.theta_rad * kDegPerRad,
                   pass->pose.swing_rad * kDegPerRad, c0.x(), c0.y(), info->centroid_m.x(), info->centroid_m.y());
    } else {
      std::fputs(", \"seed\": null}\n", file);
    }
  }
  std::fflush(file);
}

}  // namespace

Expected<RunOptions> parse_run_args(const std::vector<std::string>& args) {
  RunOptions options;
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
    } else if (a == "--config" || a == "--log-level") {
      if (!has_value) return make_error(a + " needs a value");
      ++i;  // handled by the front end
    } else if (a == "--parts" || a == "--seed" || a == "--port" || a == "--sim-replay") {
      auto value = need_value();
      if (!value) return value.error();
      std::uint64_t number = 0;
      if (!parse_u64(*value, number)) return make_error(a + " '" + *value + "': expected a whole number >= 0");
      if (a == "--parts") {
        options.parts = number;
      } else if (a == "--sim-replay") {
        if (number == 0 || number > kPregeneratedPasses) {
          return make_error("--sim-replay " + *value + ": 1.." + std::to_string(kPregeneratedPasses) + " passes");
        }
        options.sim_replay = number;
      } else if (a == "--seed") {
        options.seed = number;
        seed_given = true;
      } else {
        if (number > static_cast<std::uint64_t>(kPortMax)) return make_error("--port " + *value + ": 0..65535");
        options.port = static_cast<int>(number);
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

drivers::ModbusServerConfig modbus_server_config(const Config& config) {
  drivers::ModbusServerConfig c;
  c.bind_address = config.modbus.bind_address;
  c.port = static_cast<std::uint16_t>(std::clamp(config.modbus.port, 0, kPortMax));
  c.max_clients = config.modbus.max_clients;
  c.byte_timeout_ms = config.modbus.byte_timeout_ms;
  c.link.result_queue_capacity = static_cast<std::size_t>(std::max(1, config.modbus.result_queue_depth));
  c.link.plc_heartbeat_timeout_ms = config.modbus.plc_heartbeat_timeout_ms;
  return c;
}

int run_run(const std::vector<std::string>& args, const Config& config) {
  auto fail = [](int code, const std::string& why) {
    std::fprintf(stderr, "cellsight run: %s\n", why.c_str());
    return code;
  };
  // First: a SIGTERM that arrives while starting up must stop the run, not kill it half-way.
  SignalScope signals;
  auto parsed = parse_run_args(args);
  if (!parsed) return fail(kExitUsage, parsed.error().message);
  const RunOptions options = *parsed;
  const bool sim = options.sim || config.camera.backend == "sim" || config.gpio.backend == "sim";
  if (!options.sim && sim) {
    CS_LOG_INFO(kComponent, "the configuration names simulated devices (camera.backend %s, gpio.backend %s)",
                config.camera.backend.c_str(), config.gpio.backend.c_str());
  }

  // ---- calibration: required, never the simulator's true rig ----
  const std::string calibration_path =
      options.calibration_path.empty() ? default_calibration_path(config) : options.calibration_path;
  auto calibration = load_sensor_calibration(calibration_path);
  if (!calibration) {
    return fail(kExitUsage,
                calibration.error().message + "\n(run scripts/calibrate.sh, or cellsight calibrate, first)");
  }

  // ---- the simulated cell ----
  std::optional<sim::SimCell> cell;
  std::optional<sim::SimLine> line;
  SimFeed feed;
  auto parsed_faults = sim::FaultPlan::parse(options.sim_faults, {config.camera.timeout_ms, config.gpio.debounce_us});
  if (!parsed_faults) return fail(kExitUsage, parsed_faults.error().message);
  const sim::FaultPlan faults = std::move(*parsed_faults);
  if (!faults.empty()) {
    CS_LOG_WARN(kComponent, "--sim-faults %s: faults are injected into the simulated devices",
                options.sim_faults.c_str());
  }
  if (sim) {
    auto made = make_sim_cell(config);
    if (!made) return fail(kExitUsage, made.error().message);
    cell.emplace(std::move(*made));
    line.emplace(*cell);
    auto drawn = draw_passes(*cell, options.seed, options.parts, options.sim_parts, options.sim_replay);
    if (!drawn) return fail(kExitUsage, drawn.error().message);
    feed = std::move(*drawn);
    if (options.sim_replay > 0) {
      if (auto ok = line->enable_frame_memo(options.sim_replay); !ok) return fail(kExitFailure, ok.error().message);
      CS_LOG_WARN(kComponent, "--sim-replay %" PRIu64 ": %" PRIu64
                  " distinct passes, each rendered once and then replayed from memory",
                  options.sim_replay, options.sim_replay);
    }
  }
  std::FILE* truth_file = nullptr;
  if (!options.truth_log.empty()) {
    truth_file = std::fopen(options.truth_log.c_str(), "w");
    if (truth_file == nullptr) {
      return fail(kExitUsage, options.truth_log + ": cannot write the truth log: " + std::strerror(errno));
    }
  }
  struct FileCloser {
    std::FILE* file;
    ~FileCloser() {
      if (file != nullptr) std::fclose(file);
    }
  } truth_closer{truth_file};

  // ---- devices ----
  auto devices = make_devices(config, line ? &*line : nullptr, options.sim);
  if (!devices) return fail(kExitUsage, devices.error().message);
  if (auto ok = devices->open(); !ok) return fail(kExitFailure, ok.error().message);
  struct DevicesCloser {
    Devices& devices;
    ~DevicesCloser() { devices.close(); }
  } devices_closer{*devices};

  // ---- recogniser ----
  const std::string models_dir = options.models_dir.empty() ? config.runtime.models_dir : options.models_dir;
  std::unique_ptr<Recogniser> recogniser;
  RecogniserLoader loader;
  if (options.sim_oracle) {
    CS_LOG_WARN(kComponent, "--sim-oracle: decisions come from the simulator's truth, not from recognition");
    recogniser = std::make_unique<SimOracle>(*line, *cell, feed);
  } else {
    loader = [config, models_dir, calibration_path]() { return make_recogniser(config, models_dir, calibration_path); };
    auto made = loader();
    if (made) {
      recogniser = std::move(*made);
    } else if (options.parts > 0) {
      return fail(kExitUsage, made.error().message);
    } else {
      // A service stays up and tells the PLC (ERROR_CODE model database invalid) instead of crash-looping; it
      // retries on CLEAR_ERROR, SELECT_MODELS and every few seconds.
      CS_LOG_ERROR(kComponent, "%s", made.error().message.c_str());
    }
  }

  // ---- Modbus ----
  drivers::ModbusServerConfig server_config = modbus_server_config(config);
  if (options.port >= 0) server_config.port = static_cast<std::uint16_t>(options.port);
  drivers::ModbusServer server(server_config);

  // ---- the loop ----
  LoopConfig loop_settings = runtime::loop_config(config);
  loop_settings.max_parts = options.parts;
  if (sim) {
    loop_settings.conveyor_waits_for_ready = true;
    loop_settings.edge_timestamps_monotonic = false;  // simulated time
    // Free running unless the PLC paces the simulated line (then as DESIGN.md: TRIGGER_ENABLE, and a full result
    // queue holds the conveyor instead of losing results).
    loop_settings.require_trigger_enable = options.wait_plc;
    loop_settings.hold_when_queue_full = options.wait_plc;
  }
  ServiceNotifier service;
  ProductionLoop loop(loop_settings, *devices->camera, *devices->io, *devices->encoder, scan_builder_params(config),
                      *calibration, server);
  loop.set_recogniser(std::move(recogniser));
  if (loader) loop.set_recogniser_loader(loader);
  loop.set_service(&service);
  std::optional<TruthLog> truth;
  if (truth_file != nullptr && line) {
    if (!options.sim_oracle) write_template_truth(truth_file, config, *cell, models_dir);
    truth.emplace(truth_file, *line, feed, faults, options.sim_oracle);
    loop.set_observer(&*truth);
  }

  // The server starts once the loop is built (scan buffers allocated), just before the loop runs: the link's loop
  // watchdog then never sees a silent start-up.
  {
    const StopSignalsBlocked for_the_threads;
    if (auto ok = server.start(); !ok) return fail(kExitFailure, ok.error().message);
    if (auto ok = loop.start(); !ok) {
      server.stop();
      return fail(kExitFailure, ok.error().message);
    }
  }
  char status[128];
  std::snprintf(status, sizeof status, "serving Modbus on %s:%u%s", server_config.bind_address.c_str(),
                static_cast<unsigned>(server.bound_port()), sim ? " (simulated cell)" : "");
  service.ready(status);
  CS_LOG_INFO(kComponent, "running%s: Modbus %s:%u, %s%s", sim ? " the simulated cell" : "",
              server_config.bind_address.c_str(), static_cast<unsigned>(server.bound_port()),
              options.parts > 0 ? "parts " : "until SIGTERM/SIGINT",
              options.parts > 0 ? std::to_string(options.parts).c_str() : "");

  const auto started = std::chrono::steady_clock::now();
  std::uint64_t fed = 0;
  bool all_taken = false;
  while (SignalScope::caught() == 0) {
    if (line) {
      // The simulated conveyor: a couple of parts waiting; time only moves when the loop asks for edges or frames.
      // Fed until the loop has its parts (an aborted pass does not count, so N passes may not be enough).
      while (!loop.finished() && line->queued() < kQueuedPassesAhead) {
        const std::uint64_t k = fed % feed.passes.size();
        line->enqueue(feed.passes[k], faults.for_pass(fed, cell->frame_count()),
                      options.sim_replay > 0 ? static_cast<std::int64_t>(k) : -1);
        ++fed;
      }
    }
    if (loop.finished()) {
      if (!options.wait_plc) break;
      const drivers::LinkStats link = server.stats();
      // Every result presented and acknowledged: the PLC has them all.
      if (link.queue_depth == 0 && link.results_presented == link.results_published &&
          link.results_acked >= link.results_presented) {
        all_taken = true;
        break;
      }
    }
    (void)loop.wait_finished(kMainWait);
    if (loop.finished() && options.wait_plc) std::this_thread::sleep_for(kMainWait);
  }
  if (const int sig = SignalScope::caught(); sig != 0) {
    CS_LOG_INFO(kComponent, "%s: stopping", sig == SIGTERM ? "SIGTERM" : sig == SIGINT ? "SIGINT" : "signal");
  }
  service.stopping();
  loop.request_stop();
  loop.join();
  const LoopStats stats = loop.stats();
  const drivers::LinkStats link = server.stats();
  server.stop();
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
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
  if (line) {
    const auto* sim_io = dynamic_cast<const sim::SimDigitalIo*>(devices->io.get());
    CS_LOG_INFO(kComponent, "simulated line: %" PRIu64 " passes started, %" PRIu64 " fed, %" PRIu64
                " part-present bounces filtered, %" PRIu64 " frames replayed, %" PRIu64 " rendered into the memo",
                line->passes_started(), fed, sim_io != nullptr ? sim_io->bounces() : 0, line->frame_memo().hits(),
                line->frame_memo().stores());
  }
  return kExitOk;
}

}  // namespace cellsight::app
