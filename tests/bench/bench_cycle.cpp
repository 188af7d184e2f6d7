// Benchmark: cycle time of the production loop on the simulated cell, from the part-present falling edge to the
// new RESULT_SEQ readable by a PLC over Modbus TCP (budget: 30 ms median for 8 classes, 3 s hard deadline).
//
// usage: bench_cycle [--parts N] [--config FILE] [--models DIR --calibration FILE] [--fake-ms T]
//                    [--hmi [--browsers B] [--unknown-every K]]
//   --hmi runs the operator's screen beside the loop as `run` does (live feed as the loop's observer, the scan
//   keeper and the Review store, the HTTP server) with B browsers watching the live stream (default 4); with the
//   stand-in every K-th part comes out unknown, so its scan is kept and stored (default 0: none). Compare the
//   medians with and without --hmi (README "Operator's screen").
//   without --models the recogniser is a stand-in that answers after T ms (default 0): the figure is then the
//   loop's own overhead (hand-over to the recognition thread, mapping, publish, Modbus presentation).
//   with --models (and the calibration it was trained with) the production recogniser is used.
#include <civetweb.h>
#include <modbus/modbus.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "../sim_test_util.hpp"
#include "app/config.hpp"
#include "app/loop_wiring.hpp"
#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "drivers/modbus/modbus_server.hpp"
#include "drivers/modbus/register_map.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "formats/calibration_file.hpp"
#include "hmi/live_feed.hpp"
#include "hmi/live_preview.hpp"
#include "hmi/review_store.hpp"
#include "hmi/server.hpp"
#include "runtime/production_loop.hpp"
#include "runtime/scan_keeper.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
using Clock = std::chrono::steady_clock;
namespace map = drivers::modbus_map;

namespace {

constexpr auto kPollPeriod = std::chrono::microseconds(200);

std::int64_t now_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

// Stand-in recogniser: a fixed decision after a fixed time.
class FixedRecogniser final : public runtime::Recogniser {
 public:
  FixedRecogniser(int delay_ms, int unknown_every) : delay_ms_(delay_ms), unknown_every_(unknown_every) {}
  algo::Decision recognise(std::span<const algo::ScanPoint> /*points*/, Clock::time_point deadline) override {
    if (delay_ms_ > 0)
      std::this_thread::sleep_until(std::min(deadline, Clock::now() + std::chrono::milliseconds(delay_ms_)));
    algo::Decision d;
    if (unknown_every_ > 0 && ++calls_ % unknown_every_ == 0) {
      d.source = algo::DecisionSource::kUnknown;
      return d;
    }
    d.source = algo::DecisionSource::kSvm;
    d.class_index = 0;
    d.part_id = 1;
    d.probability = 0.9;
    d.pose_valid = true;
    return d;
  }
  std::string_view class_name(int /*class_index*/) const override { return "stand-in"; }

 private:
  int delay_ms_;
  int unknown_every_;
  int calls_ = 0;
};

// The operator's screen as `run` attaches it (cli/run_hmi.cpp), with browsers watching the live stream.
struct BenchScreen {
  BenchScreen(const app::Config& config, runtime::ProductionLoop& loop, runtime::LoopObserver* next, int browser_count,
              const std::string& models)
      : feed(256, next),
        keeper(static_cast<std::size_t>(config.hmi.keep_slots), app::scan_builder_params(config).max_points),
        preview_keeper(2, 60'000),
        review((test::scratch_dir("bench-cycle") / "review").string(), config.hmi.review_keep, &keeper),
        preview(models, &preview_keeper),
        browsers_wanted(browser_count) {
    loop.set_observer(&feed);
    loop.set_keeper(&keeper, true);
    loop.set_preview(&preview_keeper);
    hmi::HmiParams params = config.hmi;
    params.port = 0;
    server = std::make_unique<hmi::HmiServer>(params, std::vector<hmi::User>{}, &feed, [&loop] {
      const runtime::LoopStats s = loop.stats();
      return nlohmann::json{{"state", runtime::to_string(s.state)}, {"results", s.results}};
    });
  }
  bool start() {
    if (!review.start() || !preview.start() || !server->start()) return false;
    for (int b = 0; b < browsers_wanted; ++b) {
      browsers.emplace_back([this] {
        char error[256] = {};
        mg_connection* conn = mg_connect_client("127.0.0.1", server->port(), 0, error, sizeof error);
        if (conn == nullptr) return;
        const std::string request = "GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n";
        mg_write(conn, request.data(), request.size());
        if (mg_get_response(conn, error, sizeof error, 5000) >= 0) {
          char buffer[4096];
          while (mg_read(conn, buffer, sizeof buffer) > 0) events_bytes.fetch_add(1);
        }
        mg_close_connection(conn);
      });
    }
    return true;
  }
  void stop() {
    server->stop();  // ends the live streams: the browsers' reads return
    for (std::thread& t : browsers) t.join();
    review.stop();
    preview.stop();
  }

  hmi::LiveFeed feed;
  runtime::ScanKeeper keeper;
  runtime::ScanKeeper preview_keeper;
  hmi::ReviewStore review;
  hmi::LivePreview preview;
  std::unique_ptr<hmi::HmiServer> server;
  int browsers_wanted;
  std::vector<std::thread> browsers;
  std::atomic<std::uint64_t> events_bytes{0};
};

struct Part {
  std::uint32_t acq_id = 0;
  std::int64_t falling_ns = 0;    // cycle start (steady clock)
  std::int64_t published_ns = 0;  // publish() returned
  std::int64_t seen_ns = 0;       // the PLC read the new RESULT_SEQ
  double recognise_ms = 0;
  std::uint32_t seq = 0;
};

class Timing final : public runtime::LoopObserver {
 public:
  explicit Timing(std::size_t parts) : parts_(parts + 1) {}
  void on_part_done(const runtime::PartRecord& r) override {
    std::lock_guard lock(mutex_);
    if (r.seq == 0 || r.seq >= parts_.size()) return;
    Part& p = parts_[r.seq];
    p.acq_id = r.acq_id;
    p.falling_ns = r.cycle_start_ns;
    p.published_ns = r.published_ns;
    p.recognise_ms = r.recognise_ms;
    p.seq = r.seq;
  }
  void seen(std::uint32_t seq, std::int64_t at_ns) {
    std::lock_guard lock(mutex_);
    if (seq < parts_.size() && parts_[seq].seen_ns == 0) parts_[seq].seen_ns = at_ns;
  }
  std::vector<Part> parts() {
    std::lock_guard lock(mutex_);
    return parts_;
  }

 private:
  std::mutex mutex_;
  std::vector<Part> parts_;
};

double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  int parts = 20;
  int fake_ms = 0;
  bool with_hmi = false;
  int browsers = 4, unknown_every = 0;
  std::string config_path = CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml";
  std::string models, calibration_path;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const bool value = i + 1 < argc;
    if (a == "--parts" && value) {
      parts = std::atoi(argv[++i]);
    } else if (a == "--fake-ms" && value) {
      fake_ms = std::atoi(argv[++i]);
    } else if (a == "--config" && value) {
      config_path = argv[++i];
    } else if (a == "--models" && value) {
      models = argv[++i];
    } else if (a == "--calibration" && value) {
      calibration_path = argv[++i];
    } else if (a == "--hmi") {
      with_hmi = true;
    } else if (a == "--browsers" && value) {
      browsers = std::atoi(argv[++i]);
    } else if (a == "--unknown-every" && value) {
      unknown_every = std::atoi(argv[++i]);
    } else {
      std::fprintf(stderr,
                   "usage: bench_cycle [--parts N] [--config FILE] [--models DIR --calibration FILE] [--fake-ms T]\n"
                   "                   [--hmi [--browsers B] [--unknown-every K]]\n");
      return 2;
    }
  }
  if (parts <= 0) parts = 1;
  auto config = app::load_config(config_path);
  if (!config) {
    std::fprintf(stderr, "%s\n", config.error().message.c_str());
    return 2;
  }
  auto cell = app::make_sim_cell(*config);
  if (!cell) {
    std::fprintf(stderr, "%s\n", cell.error().message.c_str());
    return 2;
  }
  algo::SensorCalibration calibration = test::true_calibration(cell->rig());
  std::unique_ptr<runtime::Recogniser> recogniser;
  if (!models.empty()) {
    if (calibration_path.empty()) calibration_path = app::default_calibration_path(*config);
    auto loaded = formats::load_sensor_calibration(calibration_path);
    if (!loaded) {
      std::fprintf(stderr, "%s\n", loaded.error().message.c_str());
      return 2;
    }
    calibration = *loaded;
    auto made = app::make_recogniser(*config, models, calibration_path);
    if (!made) {
      std::fprintf(stderr, "%s\n", made.error().message.c_str());
      return 2;
    }
    recogniser = std::move(*made);
  } else {
    recogniser = std::make_unique<FixedRecogniser>(fake_ms, unknown_every);
  }

  sim::SimLine line(*cell);
  const auto& catalogue = cell->catalogue();
  for (int k = 0; k < parts; ++k) {
    auto pass = cell->random_pass(catalogue[static_cast<std::size_t>(k) % catalogue.size()].name, 100 + k);
    if (!pass) return 1;
    line.enqueue(*pass);
  }
  sim::SimCamera camera(line, config->camera.buffers, static_cast<std::int32_t>(config->camera.exposure_us));
  sim::SimDigitalIo io(line);
  sim::SimEncoder encoder(line);
  if (!camera.start() || !io.open() || !encoder.open()) return 1;

  drivers::ModbusServerConfig server_config;
  server_config.bind_address = "127.0.0.1";
  server_config.port = 0;
  server_config.link.plc_heartbeat_timeout_ms = 0;  // this PLC only polls the result; it writes no heartbeat
  drivers::ModbusServer server(server_config);
  if (auto ok = server.start(); !ok) {
    std::fprintf(stderr, "%s\n", ok.error().message.c_str());
    return 1;
  }

  runtime::LoopConfig lc = app::loop_config(*config);
  lc.conveyor_waits_for_ready = true;
  lc.edge_timestamps_monotonic = false;
  lc.max_parts = static_cast<std::uint64_t>(parts);
  lc.require_trigger_enable = false;
  lc.hold_when_queue_full = true;
  runtime::ProductionLoop loop(lc, camera, io, encoder, app::scan_builder_params(*config), calibration, server);
  loop.set_recogniser(std::move(recogniser));
  Timing timing(static_cast<std::size_t>(parts));
  loop.set_observer(&timing);
  std::unique_ptr<BenchScreen> screen;
  if (with_hmi) {
    screen = std::make_unique<BenchScreen>(*config, loop, &timing, browsers, models);
    if (!screen->start()) {
      std::fprintf(stderr, "bench_cycle: the operator's screen did not start\n");
      return 1;
    }
  }

  // The PLC: polls RESULT_SEQ as fast as loopback allows and acknowledges each new result.
  std::atomic<bool> stop{false};
  std::atomic<int> seen_count{0};
  std::thread plc([&] {
    modbus_t* ctx = modbus_new_tcp("127.0.0.1", server.bound_port());
    if (ctx == nullptr || modbus_connect(ctx) != 0) {
      std::fprintf(stderr, "bench_cycle: cannot connect to the Modbus server\n");
      stop = true;
      return;
    }
    std::uint32_t last = 0;
    while (!stop.load()) {
      std::uint16_t regs[2];
      if (modbus_read_registers(ctx, map::kResultSeq, 2, regs) != 2) continue;
      const std::int64_t at = now_ns();
      const std::uint32_t seq = (std::uint32_t{regs[0]} << 16) | regs[1];
      if (seq == last) {
        std::this_thread::sleep_for(kPollPeriod);  // leaves the CPU to the loop; sets the figure's resolution
        continue;
      }
      last = seq;
      timing.seen(seq, at);
      seen_count.fetch_add(1);
      (void)modbus_write_register(ctx, map::kControl, map::kControlResultAck);
      std::uint16_t status = map::kStatusResultValid;
      while (!stop.load() && (status & map::kStatusResultValid) != 0) {
        if (modbus_read_registers(ctx, map::kStatus, 1, &status) != 1) break;
        if ((status & map::kStatusResultValid) != 0) std::this_thread::sleep_for(kPollPeriod);
      }
      (void)modbus_write_register(ctx, map::kControl, 0);
    }
    modbus_close(ctx);
    modbus_free(ctx);
  });

  const auto started = Clock::now();
  if (!loop.start()) return 1;
  (void)loop.wait_finished(std::chrono::minutes(30));
  const auto wait_until = Clock::now() + std::chrono::seconds(5);
  while (seen_count.load() < parts && Clock::now() < wait_until)
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  const double wall_s = std::chrono::duration<double>(Clock::now() - started).count();
  stop = true;
  plc.join();
  loop.request_stop();
  loop.join();
  server.stop();
  if (screen) screen->stop();

  std::printf(
      "cycle: part-present falling edge -> new RESULT_SEQ read by a Modbus client (127.0.0.1, polling every "
      "%lld us)\n",
      static_cast<long long>(kPollPeriod.count()));
  if (screen) {
    std::printf(
        "operator's screen: on, %d browsers on the live stream, %llu scans kept, %llu dropped, %llu stored, "
        "%llu live pictures\n",
        browsers, static_cast<unsigned long long>(screen->keeper.kept()),
        static_cast<unsigned long long>(screen->keeper.dropped()),
        static_cast<unsigned long long>(screen->review.stored()),
        static_cast<unsigned long long>(screen->preview.rendered()));
  } else {
    std::printf("operator's screen: off\n");
  }
  std::printf("recogniser: %s\n", models.empty() ? ("stand-in, " + std::to_string(fake_ms) + " ms").c_str()
                                                 : ("production, " + models).c_str());
  std::printf("%5s %6s %14s %12s %12s\n", "seq", "acq", "recognise_ms", "publish_ms", "cycle_ms");
  std::vector<double> cycle_ms, publish_ms;
  for (const Part& p : timing.parts()) {
    if (p.seq == 0) continue;
    const double to_publish = static_cast<double>(p.published_ns - p.falling_ns) * 1e-6;
    const double to_seen = p.seen_ns > 0 ? static_cast<double>(p.seen_ns - p.falling_ns) * 1e-6 : -1.0;
    std::printf("%5u %6u %14.3f %12.3f %12.3f\n", p.seq, p.acq_id, p.recognise_ms, to_publish, to_seen);
    publish_ms.push_back(to_publish);
    if (to_seen >= 0) cycle_ms.push_back(to_seen);
  }
  const double max_cycle = cycle_ms.empty() ? 0.0 : *std::max_element(cycle_ms.begin(), cycle_ms.end());
  std::printf("parts %zu seen by the PLC of %d; wall %.1f s (simulated conveyor as fast as the CPU renders)\n",
              cycle_ms.size(), parts, wall_s);
  std::printf("falling edge -> publish():      median %.3f ms\n", median(publish_ms));
  std::printf("falling edge -> RESULT_SEQ read: median %.3f ms, max %.3f ms\n", median(cycle_ms), max_cycle);
  return cycle_ms.size() == static_cast<std::size_t>(parts) ? 0 : 1;
}
