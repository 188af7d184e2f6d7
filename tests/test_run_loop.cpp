// Tests of the production loop and `cellsight run`: the state machine on the simulated cell, the PLC handshake
// (simulated link and a real Modbus server), the hard deadline, faults and recovery, fixed memory (allocations
// counted, RSS), the systemd protocol and a clean shutdown on SIGTERM. Recognition is a scripted test double here:
// these tests are about the loop, not about recognition.
#include <arpa/inet.h>
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <catch2/catch.hpp>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <mutex>
#include <numbers>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "app/config.hpp"
#include "app/loop_wiring.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "cli/run_mode.hpp"
#include "drivers/modbus/modbus_server.hpp"
#include "drivers/modbus/register_map.hpp"
#include "drivers/modbus/sim_plc_link.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "formats/calibration_file.hpp"
#include "runtime/plc_mapping.hpp"
#include "runtime/production_loop.hpp"
#include "runtime/recogniser.hpp"
#include "runtime/service_notify.hpp"
#include "sim_test_util.hpp"
#include "tests/free_port.hpp"
#include "tests/scratch_dir.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using namespace cellsight;
using drivers::DeviceStatus;
using drivers::ErrorCode;
using drivers::ResultCode;
using runtime::LoopState;
namespace map = drivers::modbus_map;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr std::uint16_t kNoSigma = 0xFFFF;  // README: a sigma register that is not available

// Allocation counter (proves "no allocation"): operator new on every thread while the window is open, except inside
// the simulated world (the simulator's renderer and scene building, the test's PLC): those stand for the camera,
// the conveyor and the PLC, which are not the loop.
using WorldScope = test::UncountedScope;
using test::AllocationWindow;

std::int64_t monotonic_ns() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
}

template <class Predicate>
bool wait_until(Predicate predicate, int timeout_ms) {
  const auto deadline = Clock::now() + milliseconds(timeout_ms);
  while (Clock::now() < deadline) {
    if (predicate()) return true;
    std::this_thread::sleep_for(milliseconds(1));
  }
  return predicate();
}

std::uint32_t u32(const std::uint16_t* at) {
  return (std::uint32_t{at[0]} << 16) | at[1];
}
std::int32_t s32(const std::uint16_t* at) {
  return static_cast<std::int32_t>(u32(at));
}
std::uint64_t u64(const std::uint16_t* at) {
  return (std::uint64_t{u32(at)} << 32) | u32(at + 2);
}

// ------------------------------------------------------------------ a small simulated cell (fast under ASan)

// The default cell at a quarter of the camera resolution and one frame per 22 mm (30 frames a pass): the loop does
// not care about reconstruction quality, and the tests must run in seconds under the sanitizers.
app::Config small_config() {
  app::Config config = app::default_config();
  config.catalogue_path = std::string(CELLSIGHT_SOURCE_DIR) + "/config/parts.yaml";
  auto& k = config.rig.camera.intrinsics;
  constexpr double kScale = 0.25;
  k.width_px = static_cast<int>(k.width_px * kScale);
  k.height_px = static_cast<int>(k.height_px * kScale);
  k.fx_px *= kScale;
  k.fy_px *= kScale;
  k.cx_px *= kScale;
  k.cy_px *= kScale;
  config.rig.conveyor.trigger_every_counts = 220;
  config.camera.timeout_ms = 300;
  config.runtime.deadline_ms = 1000;
  config.modbus.bind_address = "127.0.0.1";
  return config;
}

runtime::LoopConfig small_loop_config(const app::Config& config) {
  runtime::LoopConfig c = app::loop_config(config);
  c.conveyor_waits_for_ready = true;  // the simulated conveyor
  c.require_trigger_enable = false;
  c.poll_slice_ms = 5;
  c.retry_interval_ms = 50;
  return c;
}

// A decision the scripted recogniser returns, and what the test expects on the wire.
struct Script {
  algo::DecisionSource source = algo::DecisionSource::kSvm;
  int part_id = 3;
  double probability = 0.875;
  double x_m = 0.012345678, y_m = -0.0045, theta_rad = 0.05;
  // The out-of-plane axes and the sigmas: NaN = not fixed / not estimated, as a planar-only recogniser says.
  double z_m = kNaN, rx_rad = kNaN, ry_rad = kNaN;
  std::array<double, algo::kPoseAxes> pose_sigma = algo::Decision::nan_array();
  int delay_ms = 0;             // how long recognise() takes
  bool honour_deadline = true;  // false: a misbehaving recogniser that ignores the deadline
};

// The recognition stage's test double: returns the scripted decision of the n-th call, after its delay.
class ScriptedRecogniser final : public runtime::Recogniser {
 public:
  static constexpr std::size_t kMaxScripts = 512;
  explicit ScriptedRecogniser(std::vector<Script> scripts) : scripts_(std::move(scripts)) {}

  algo::Decision recognise(std::span<const algo::ScanPoint> points, Clock::time_point deadline) override {
    const std::size_t n = calls_.fetch_add(1);
    const Script& s = scripts_[std::min(n, scripts_.size() - 1)];
    points_seen_.store(points.size());
    if (s.delay_ms > 0) {
      const auto until = Clock::now() + milliseconds(s.delay_ms);
      std::this_thread::sleep_until(s.honour_deadline ? std::min(until, deadline) : until);
    }
    algo::Decision d;
    if (s.honour_deadline && Clock::now() >= deadline && s.delay_ms > 0) {
      d.source = algo::DecisionSource::kTimeout;
    } else {
      d.source = s.source;
      d.class_index = d.accepted() ? s.part_id - 1 : -1;
      d.part_id = d.accepted() ? s.part_id : 0;
      d.probability = s.probability;
      d.pose_valid = d.accepted();
      d.pose = {s.x_m, s.y_m, s.theta_rad};
      d.z_m = s.z_m;
      d.rx_rad = s.rx_rad;
      d.ry_rad = s.ry_rad;
      d.pose_sigma = s.pose_sigma;
    }
    returned_.fetch_add(1);
    return d;
  }
  std::string_view class_name(int class_index) const override {
    static constexpr std::array<std::string_view, 4> kNames = {"alpha", "beta", "gamma", "delta"};
    return class_index >= 0 && class_index < 4 ? kNames[static_cast<std::size_t>(class_index)] : std::string_view{};
  }
  [[nodiscard]] std::size_t calls() const { return calls_.load(); }
  [[nodiscard]] std::size_t returned() const { return returned_.load(); }  // calls that have returned
  [[nodiscard]] std::size_t points_seen() const { return points_seen_.load(); }

 private:
  std::vector<Script> scripts_;
  std::atomic<std::size_t> calls_{0};
  std::atomic<std::size_t> returned_{0};
  std::atomic<std::size_t> points_seen_{0};
};

// The simulated devices, each call marked as "the world" for the allocation counter.
class WorldCamera final : public drivers::Camera {
 public:
  explicit WorldCamera(drivers::Camera& inner) : inner_(inner) {}
  Status start() override { return inner_.start(); }
  void stop() override { inner_.stop(); }
  DeviceStatus set_exposure_us(std::int32_t us) override {
    WorldScope world;
    return inner_.set_exposure_us(us);
  }
  DeviceStatus grab(drivers::Frame& out, int timeout_ms) override {
    WorldScope world;
    return inner_.grab(out, timeout_ms);
  }
  void release(const drivers::Frame& frame) override { inner_.release(frame); }

 private:
  drivers::Camera& inner_;
};

class WorldIo final : public drivers::DigitalIo {
 public:
  explicit WorldIo(drivers::DigitalIo& inner) : inner_(inner) {}
  Status open() override { return inner_.open(); }
  void close() override { inner_.close(); }
  DeviceStatus set(drivers::Output line, bool active) override {
    WorldScope world;
    return inner_.set(line, active);
  }
  DeviceStatus pulse(drivers::Output line, std::int32_t width_us) override { return inner_.pulse(line, width_us); }
  DeviceStatus read(drivers::Input line, bool& active) override {
    WorldScope world;
    return inner_.read(line, active);
  }
  DeviceStatus wait_edge(drivers::EdgeEvent& out, int timeout_ms) override {
    WorldScope world;  // a rising edge builds the next part's scene in the simulator
    return inner_.wait_edge(out, timeout_ms);
  }

 private:
  drivers::DigitalIo& inner_;
};

class WorldEncoder final : public drivers::Encoder {
 public:
  explicit WorldEncoder(drivers::Encoder& inner) : inner_(inner) {}
  Status open() override { return inner_.open(); }
  void close() override { inner_.close(); }
  DeviceStatus read_counts(std::int64_t& counts) override {
    WorldScope world;
    return inner_.read_counts(counts);
  }

 private:
  drivers::Encoder& inner_;
};

// Records what the loop reports, in fixed arrays (the observer runs inside the loop: no allocation).
class Recorder final : public runtime::LoopObserver {
 public:
  static constexpr std::size_t kMax = 4096;
  struct Transition {
    LoopState from, to;
    ErrorCode error;
    Clock::time_point at;
  };
  void on_state(LoopState from, LoopState to, ErrorCode error) override {
    const Clock::time_point now = Clock::now();
    std::lock_guard lock(mutex_);
    if (transitions_ < kMax) transition_[transitions_++] = {from, to, error, now};
  }
  void on_pass_started(std::uint32_t acq_id, runtime::TriggerSource /*trigger*/) override {
    last_started_.store(acq_id);
  }
  void on_frame(std::uint32_t acq_id, int frame_index) override {
    if (acq_id == stall_acq_.load() && frame_index == stall_frame_.load()) stall_line_->set_camera_stalled(true);
  }
  void on_part_done(const runtime::PartRecord& record) override {
    std::lock_guard lock(mutex_);
    if (parts_ < kMax) part_[parts_++] = record;
  }
  // Stall the simulated camera when this acquisition reaches this frame.
  void stall_at(sim::SimLine& line, std::uint32_t acq_id, int frame_index) {
    stall_line_ = &line;
    stall_frame_.store(frame_index);
    stall_acq_.store(acq_id);
  }
  std::vector<Transition> transitions() const {
    std::lock_guard lock(mutex_);
    return {transition_.begin(), transition_.begin() + static_cast<std::ptrdiff_t>(transitions_)};
  }
  std::vector<runtime::PartRecord> parts() const {
    std::lock_guard lock(mutex_);
    return {part_.begin(), part_.begin() + static_cast<std::ptrdiff_t>(parts_)};
  }
  std::size_t part_count() const {
    std::lock_guard lock(mutex_);
    return parts_;
  }

 private:
  mutable std::mutex mutex_;
  std::array<Transition, kMax> transition_{};
  std::size_t transitions_ = 0;
  std::array<runtime::PartRecord, 512> part_{};
  std::size_t parts_ = 0;
  std::atomic<std::uint32_t> last_started_{0};
  std::atomic<std::uint32_t> stall_acq_{0};
  std::atomic<int> stall_frame_{-1};
  sim::SimLine* stall_line_ = nullptr;
};

// ------------------------------------------------------------------ the PLC (a thread driving SimPlcLink)

// A PLC program on the simulated link: advances the link's clock with the wall clock, reads STATUS, takes each
// RESULT_VALID block (checking both sequence copies) and acknowledges it, and can enable triggers, pulse
// SW_TRIGGER or CLEAR_ERROR. It plays the server's network thread, so it is "the world" for the allocation counter.
class SimPlc {
 public:
  static constexpr std::size_t kMax = 1024;
  struct Seen {
    std::array<std::uint16_t, map::kResultBlockCount> block{};
    std::uint16_t status = 0;
    std::uint16_t error_code = 0;
  };

  explicit SimPlc(drivers::SimPlcLink& link, bool ack = true) : link_(link), ack_(ack) {
    thread_ = std::thread([this] { run(); });
  }
  ~SimPlc() {
    stop_.store(true);
    thread_.join();
  }
  SimPlc(const SimPlc&) = delete;
  SimPlc& operator=(const SimPlc&) = delete;

  void set_control_bits(std::uint16_t bits) { control_.store(bits); }
  void pulse(std::uint16_t bit) { pulses_.fetch_or(bit); }
  void set_ack(bool ack) { ack_.store(ack); }

  std::size_t count() const { return count_.load(); }
  Seen seen(std::size_t i) const {
    std::lock_guard lock(mutex_);
    return seen_[i];
  }
  std::uint16_t status() const { return status_.load(); }
  std::uint16_t error_code() const { return error_code_.load(); }
  std::uint16_t warning_code() const { return warning_code_.load(); }
  std::uint32_t missed_triggers() const { return missed_.load(); }
  std::uint32_t trigger_count() const { return triggers_.load(); }
  int violations() const { return violations_.load(); }  // torn blocks, repeated or skipped sequence numbers
  // RESULT_VALID seen while ERROR was set (the link must never do that).
  int valid_during_error() const { return valid_during_error_.load(); }
  // Every ERROR_CODE value seen at least once, as bit (1 << code).
  bool saw_error(ErrorCode code) const {
    return (errors_seen_.load() & error_bit(static_cast<std::uint16_t>(code))) != 0;
  }

 private:
  void run() {
    WorldScope world;
    std::uint32_t last_seq = 0;
    enum class Phase { kWaitValid, kWaitInvalid } phase = Phase::kWaitValid;
    std::uint16_t control = 0xFFFF;
    std::uint16_t plc_heartbeat = 0;
    while (!stop_.load()) {
      link_.advance_to(monotonic_ns());
      (void)link_.plc_write_register(map::kPlcHeartbeat, ++plc_heartbeat);  // the PLC is alive
      std::uint16_t wanted = control_.load();
      const std::uint16_t pulse = pulses_.exchange(0);
      if (phase == Phase::kWaitInvalid) wanted |= map::kControlResultAck;
      if ((wanted | pulse) != control) {
        (void)link_.plc_write_register(map::kControl, static_cast<std::uint16_t>(wanted | pulse));
        control = static_cast<std::uint16_t>(wanted | pulse);
      }
      if (pulse != 0) {  // an edge: set, let the link see it, clear
        link_.advance_to(monotonic_ns());
        (void)link_.plc_write_register(map::kControl, wanted);
        control = wanted;
      }
      std::array<std::uint16_t, 10> status{};
      if (link_.plc_read(map::kStatus, status) != 0) ++link_errors_;
      status_.store(status[0]);
      error_code_.store(status[2]);
      warning_code_.store(status[3]);
      triggers_.store(u32(&status[5]));
      missed_.store(u32(&status[7]));
      const bool valid = (status[0] & map::kStatusResultValid) != 0;
      if (valid && (status[0] & map::kStatusError) != 0) ++valid_during_error_;
      errors_seen_.fetch_or(error_bit(status[2]));
      if (phase == Phase::kWaitValid && valid) {
        Seen s;
        if (link_.plc_read(map::kResultBlockFirst, s.block) != 0) ++link_errors_;
        const std::uint32_t seq = u32(&s.block[0]);
        const std::uint32_t copy = u32(&s.block[map::kResultSeqCopy - map::kResultBlockFirst]);
        const std::uint32_t copy2 = u32(&s.block[map::kResultSeqCopy2 - map::kResultBlockFirst]);
        if (copy2 != copy) ++violations_;      // both copies are written with the block: never one without the other
        if (seq == last_seq && seq == copy) {  // still the one already taken (a PLC that did not acknowledge)
          if (ack_.load()) phase = Phase::kWaitInvalid;
          std::this_thread::sleep_for(milliseconds(1));
          continue;
        }
        if (seq != copy || seq != last_seq + 1) ++violations_;
        last_seq = seq;
        s.status = status[0];
        s.error_code = status[2];
        {
          std::lock_guard lock(mutex_);
          if (count_.load() < kMax) seen_[count_.load()] = s;
        }
        count_.fetch_add(1);
        if (ack_.load()) phase = Phase::kWaitInvalid;
      } else if (phase == Phase::kWaitInvalid && !valid) {
        phase = Phase::kWaitValid;  // RESULT_ACK cleared next round: the next result may appear
      }
      std::this_thread::sleep_for(milliseconds(1));
    }
  }

  drivers::SimPlcLink& link_;
  std::atomic<bool> ack_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::atomic<std::uint16_t> control_{0};
  std::atomic<std::uint16_t> pulses_{0};
  mutable std::mutex mutex_;
  std::array<Seen, kMax> seen_{};
  std::atomic<std::size_t> count_{0};
  std::atomic<std::uint16_t> status_{0};
  std::atomic<std::uint16_t> error_code_{0};
  std::atomic<std::uint16_t> warning_code_{0};
  std::atomic<std::uint32_t> missed_{0};
  std::atomic<std::uint32_t> triggers_{0};
  std::atomic<int> violations_{0};
  std::atomic<int> valid_during_error_{0};
  std::atomic<int> link_errors_{0};
  std::atomic<std::uint32_t> errors_seen_{0};

  static std::uint32_t error_bit(std::uint16_t code) { return code < 32 ? (1u << code) : 0u; }
};

// Field accessors of a result block as the PLC read it.
struct Block {
  explicit Block(const std::array<std::uint16_t, map::kResultBlockCount>& b) : r(b) {}
  const std::array<std::uint16_t, map::kResultBlockCount>& r;
  const std::uint16_t* at(std::uint16_t address) const { return r.data() + (address - map::kResultBlockFirst); }
  std::uint32_t seq() const { return u32(at(map::kResultSeq)); }
  std::uint32_t acq_id() const { return u32(at(map::kAcqId)); }
  std::uint16_t code() const { return *at(map::kResultCode); }
  std::uint16_t part_id() const { return *at(map::kPartId); }
  std::uint16_t confidence() const { return *at(map::kConfidence); }
  std::uint16_t source() const { return *at(map::kSource); }
  std::int32_t x_um() const { return s32(at(map::kPoseX)); }
  std::int32_t y_um() const { return s32(at(map::kPoseY)); }
  std::int32_t z_um() const { return s32(at(map::kPoseZ)); }
  std::int32_t rx_mdeg() const { return s32(at(map::kPoseRx)); }
  std::int32_t ry_mdeg() const { return s32(at(map::kPoseRy)); }
  std::int32_t rz_mdeg() const { return s32(at(map::kPoseRz)); }
  std::uint64_t timestamp_us() const { return u64(at(map::kTimestamp)); }
  std::uint16_t cycle_ms() const { return *at(map::kCycleMs); }
  std::uint32_t seq_copy() const { return u32(at(map::kResultSeqCopy)); }
  std::uint32_t seq_copy2() const { return u32(at(map::kResultSeqCopy2)); }
  // The six sigma registers in PoseAxis order (x, y, z, rx, ry, rz).
  std::array<std::uint16_t, algo::kPoseAxes> sigmas() const {
    std::array<std::uint16_t, algo::kPoseAxes> out{};
    std::copy_n(at(map::kSigmaX), out.size(), out.begin());
    return out;
  }
};

// The simulated cell with the loop on top: devices, link, PLC, recogniser.
struct Cell {
  explicit Cell(const app::Config& cfg, std::vector<Script> scripts, drivers::PlcLinkConfig link_config = {})
      : config(cfg),
        sim_cell(std::move(*app::make_sim_cell(cfg))),
        line(sim_cell),
        sim_camera(line, cfg.camera.buffers, static_cast<std::int32_t>(cfg.camera.exposure_us)),
        sim_io(line),
        sim_encoder(line),
        camera(sim_camera),
        io(sim_io),
        encoder(sim_encoder),
        link(link_config) {
    REQUIRE(sim_camera.start().ok());
    REQUIRE(sim_io.open().ok());
    REQUIRE(sim_encoder.open().ok());
    // Before any PLC thread touches it (SimPlcLink: start() and the PLC side are one thread's business). The link's
    // loop watchdog may note the not-yet-running loop once ("production loop silent"): harmless here.
    REQUIRE(link.start().ok());
    recogniser_ptr = new ScriptedRecogniser(std::move(scripts));
    recogniser.reset(recogniser_ptr);
  }

  // Queues `count` passes of catalogue parts (seeded) on the simulated conveyor.
  void enqueue(int count, std::uint64_t seed = 1) {
    for (int i = 0; i < count; ++i) {
      const auto& part = sim_cell.catalogue()[static_cast<std::size_t>(i) % sim_cell.catalogue().size()];
      auto pass = sim_cell.random_pass(part.name, seed + static_cast<std::uint64_t>(i));
      REQUIRE(pass.ok());
      line.enqueue(*pass);
    }
  }

  runtime::ProductionLoop& make_loop(const runtime::LoopConfig& loop_config, drivers::PlcLink* other_link = nullptr) {
    loop.emplace(loop_config, camera, io, encoder, app::scan_builder_params(config),
                 test::true_calibration(sim_cell.rig()), other_link != nullptr ? *other_link : link);
    loop->set_recogniser(std::move(recogniser));
    loop->set_observer(&recorder);
    return *loop;
  }

  app::Config config;
  sim::SimCell sim_cell;
  sim::SimLine line;
  sim::SimCamera sim_camera;
  sim::SimDigitalIo sim_io;
  sim::SimEncoder sim_encoder;
  WorldCamera camera;
  WorldIo io;
  WorldEncoder encoder;
  drivers::SimPlcLink link;
  std::unique_ptr<runtime::Recogniser> recogniser;
  ScriptedRecogniser* recogniser_ptr = nullptr;
  Recorder recorder;
  std::optional<runtime::ProductionLoop> loop;
};

// ================================================================== decision -> result block

TEST_CASE("mapping: each decision source becomes the documented result block", "[run][mapping]") {
  algo::Decision d;
  d.class_index = 2;
  d.part_id = 7;
  d.probability = 0.8764;
  d.pose_valid = true;
  d.pose = {0.0123456, -0.0204999, 2.0 * std::numbers::pi / 180.0};
  d.z_m = 0.0031;
  d.rx_rad = -0.5 * std::numbers::pi / 180.0;
  d.pose_sigma = {0.0004, 0.0005, 0.0021, 0.1 * std::numbers::pi / 180.0, kNaN, 0.05 * std::numbers::pi / 180.0};

  SECTION("svm and perfect match: ok, part id, per mille, um and millidegrees, sigmas; RY unfixed -> invalid") {
    for (const auto source : {algo::DecisionSource::kSvm, algo::DecisionSource::kPm}) {
      d.source = source;
      const drivers::PlcResult r = runtime::to_plc_result(d, 42, 123456789, 17.4);
      CHECK(r.acq_id == 42);
      CHECK(r.code == ResultCode::kOk);
      CHECK(r.source == (source == algo::DecisionSource::kSvm ? drivers::ResultSource::kSvm
                                                              : drivers::ResultSource::kPerfectMatch));
      CHECK(r.part_id == 7);
      CHECK(r.confidence_permille == 876);
      CHECK(r.x_um == 12346);   // 12345.6 um rounded
      CHECK(r.y_um == -20500);  // -20499.9 um rounded
      CHECK(r.z_um == 3100);
      CHECK(r.rx_mdeg == -500);
      CHECK(r.ry_mdeg == map::kInvalidS32);  // NaN: the geometry did not fix it, never 0
      CHECK(r.rz_mdeg == 2000);
      CHECK(r.timestamp_us == 123456789);
      CHECK(r.cycle_ms == 17);
      CHECK(r.sigma_x_um == 400);
      CHECK(r.sigma_y_um == 500);
      CHECK(r.sigma_z_um == 2100);
      CHECK(r.sigma_rx_mdeg == 100);
      CHECK(r.sigma_ry_mdeg == kNoSigma);
      CHECK(r.sigma_rz_mdeg == 50);
    }
  }
  SECTION("an accepted class without a usable pose is 'pose out of range', never a pose") {
    d.source = algo::DecisionSource::kPm;
    d.pose_valid = false;
    drivers::PlcResult r = runtime::to_plc_result(d, 1, 0, 1.0);
    CHECK(r.code == ResultCode::kPoseOutOfRange);
    CHECK(r.part_id == 7);
    CHECK(r.x_um == map::kInvalidS32);
    CHECK(r.z_um == map::kInvalidS32);
    CHECK(r.rz_mdeg == map::kInvalidS32);
    CHECK(r.sigma_x_um == kNoSigma);
    CHECK(r.sigma_z_um == kNoSigma);
    d.pose_valid = true;
    d.pose.x_m = std::numeric_limits<double>::quiet_NaN();
    r = runtime::to_plc_result(d, 1, 0, 1.0);
    CHECK(r.code == ResultCode::kPoseOutOfRange);
    d.pose.x_m = 5000.0;  // 5e9 um does not fit an s32
    CHECK(runtime::to_plc_result(d, 1, 0, 1.0).code == ResultCode::kPoseOutOfRange);
  }
  SECTION("unknown, timeout, bad scan, no part: their codes, no part id, no pose") {
    const std::array<std::pair<algo::DecisionSource, ResultCode>, 4> cases = {{
        {algo::DecisionSource::kUnknown, ResultCode::kUnknownPart},
        {algo::DecisionSource::kTimeout, ResultCode::kTimeout},
        {algo::DecisionSource::kBadScan, ResultCode::kBadScan},
        {algo::DecisionSource::kNoPart, ResultCode::kNoPart},
    }};
    for (const auto& [source, code] : cases) {
      d.source = source;
      const drivers::PlcResult r = runtime::to_plc_result(d, 9, 5, 3.0);
      CHECK(r.code == code);
      CHECK(r.part_id == 0);
      CHECK(r.source == drivers::ResultSource::kNone);
      CHECK(r.x_um == map::kInvalidS32);
      CHECK(r.y_um == map::kInvalidS32);
      CHECK(r.z_um == map::kInvalidS32);
      CHECK(r.rx_mdeg == map::kInvalidS32);
      CHECK(r.rz_mdeg == map::kInvalidS32);
      CHECK(r.sigma_x_um == kNoSigma);
      CHECK(r.sigma_z_um == kNoSigma);
      CHECK(r.sigma_rz_mdeg == kNoSigma);
      // The best class's probability stays visible for "unknown" only (a diagnostic, not a decision).
      CHECK(r.confidence_permille == (source == algo::DecisionSource::kUnknown ? 876 : 0));
    }
  }
  SECTION("cycle time saturates at 65535 ms and is never negative") {
    d.source = algo::DecisionSource::kSvm;
    CHECK(runtime::to_plc_result(d, 1, 0, 1e9).cycle_ms == 65535);
    CHECK(runtime::to_plc_result(d, 1, 0, -3.0).cycle_ms == 0);
    CHECK(runtime::to_plc_result(d, 1, 0, std::numeric_limits<double>::infinity()).cycle_ms == 65535);
  }
}

// ================================================================== the loop on the simulated cell

std::vector<std::pair<LoopState, LoopState>> edges_of(const std::vector<Recorder::Transition>& transitions) {
  std::vector<std::pair<LoopState, LoopState>> out;
  for (const auto& t : transitions) out.emplace_back(t.from, t.to);
  return out;
}

// A "timeout" result (DESIGN.md register map): code 6, no part, no confidence, no pose.
void check_timeout_result(const Block& block, std::uint32_t acq_id) {
  CHECK(block.acq_id() == acq_id);
  CHECK(block.code() == 6);
  CHECK(block.part_id() == 0);
  CHECK(block.confidence() == 0);
  CHECK(block.x_um() == map::kInvalidS32);
  CHECK(block.rz_mdeg() == map::kInvalidS32);
}

std::int32_t mdeg(double rad) {
  return static_cast<std::int32_t>(std::lround(rad * 180.0 / std::numbers::pi * 1000.0));
}

TEST_CASE(
    "loop: each part runs idle -> scanning -> recognising -> publishing -> idle and the PLC takes every "
    "result once, in order, through the handshake",
    "[run][loop]") {
  const app::Config config = small_config();
  Script second;
  second.source = algo::DecisionSource::kPm;
  second.part_id = 2;
  second.probability = 0.55;
  second.x_m = -0.03;
  second.y_m = 0.02;
  second.theta_rad = -0.07;
  second.z_m = 0.0042;
  second.rx_rad = 0.002;
  second.ry_rad = -0.001;
  second.pose_sigma = {0.0003, 0.0002, 0.0015, 0.004, 0.003, 0.001};
  Script third;
  third.source = algo::DecisionSource::kUnknown;
  third.probability = 0.4;
  Cell cell(config, {Script{}, second, third});
  cell.enqueue(3);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 3;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  const std::uint64_t started_us = static_cast<std::uint64_t>(monotonic_ns() / 1000);
  REQUIRE(loop.start().ok());
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 3; }, 5000));
  const std::uint64_t finished_us = static_cast<std::uint64_t>(monotonic_ns() / 1000);
  CHECK((plc.status() & map::kStatusReady) != 0);
  CHECK(plc.trigger_count() == 3);
  loop.request_stop();
  loop.join();
  CHECK(loop.state() == LoopState::kStopped);

  // The state machine, part by part.
  const auto edges = edges_of(cell.recorder.transitions());
  std::vector<std::pair<LoopState, LoopState>> expected;
  for (int i = 0; i < 3; ++i) {
    expected.emplace_back(LoopState::kIdle, LoopState::kScanning);
    expected.emplace_back(LoopState::kScanning, LoopState::kRecognising);
    expected.emplace_back(LoopState::kRecognising, LoopState::kPublishing);
    expected.emplace_back(LoopState::kPublishing, LoopState::kIdle);
  }
  expected.emplace_back(LoopState::kIdle, LoopState::kStopped);
  CHECK(edges == expected);

  // What the PLC read, against the scripted decisions mapped by hand (DESIGN.md register map).
  CHECK(plc.violations() == 0);
  const auto s0 = plc.seen(0), s1 = plc.seen(1), s2 = plc.seen(2);
  const Block b0(s0.block), b1(s1.block), b2(s2.block);
  CHECK(b0.seq() == 1);
  CHECK(b1.seq() == 2);
  CHECK(b2.seq() == 3);
  CHECK(b0.acq_id() == 1);
  CHECK(b1.acq_id() == 2);
  CHECK(b2.acq_id() == 3);
  CHECK(b0.code() == 0);
  CHECK(b0.source() == 1);
  CHECK(b0.part_id() == 3);
  CHECK(b0.confidence() == 875);
  CHECK(b0.x_um() == 12346);
  CHECK(b0.y_um() == -4500);
  CHECK(b0.z_um() == map::kInvalidS32);  // a planar decision: z, rx, ry not fixed, sent invalid, never 0
  CHECK(b0.rx_mdeg() == map::kInvalidS32);
  CHECK(b0.ry_mdeg() == map::kInvalidS32);
  CHECK(b0.rz_mdeg() == mdeg(0.05));
  CHECK(b0.sigmas() == std::array<std::uint16_t, 6>{kNoSigma, kNoSigma, kNoSigma, kNoSigma, kNoSigma, kNoSigma});
  CHECK(b1.code() == 0);
  CHECK(b1.source() == 2);
  CHECK(b1.part_id() == 2);
  CHECK(b1.confidence() == 550);
  CHECK(b1.x_um() == -30000);
  CHECK(b1.y_um() == 20000);
  CHECK(b1.rz_mdeg() == mdeg(-0.07));
  CHECK(b1.z_um() == 4200);
  CHECK(b1.rx_mdeg() == mdeg(0.002));
  CHECK(b1.ry_mdeg() == mdeg(-0.001));
  // 0.3, 0.2, 1.5 mm; 4, 3, 1 mrad = 229.18, 171.89, 57.30 mdeg
  CHECK(b1.sigmas() == std::array<std::uint16_t, 6>{300, 200, 1500, 229, 172, 57});
  CHECK(b2.code() == 2);  // unknown part
  CHECK(b2.part_id() == 0);
  CHECK(b2.confidence() == 400);
  CHECK(b2.x_um() == map::kInvalidS32);
  CHECK(b2.sigmas() == b0.sigmas());
  for (const Block* b : {&b0, &b1, &b2}) {
    CHECK(b->seq_copy() == b->seq());
    CHECK(b->seq_copy2() == b->seq());
    CHECK(b->timestamp_us() >= started_us);
    CHECK(b->timestamp_us() <= finished_us);
    CHECK(b->cycle_ms() < config.runtime.deadline_ms);
  }
  CHECK(b0.timestamp_us() < b1.timestamp_us());
  CHECK(b1.timestamp_us() < b2.timestamp_us());

  // Every frame of each simulated pass went into the scan the recogniser got. (The PLC can see a result before the
  // observer has its record: publish() hands the result block over first.)
  REQUIRE(wait_until([&] { return cell.recorder.part_count() == 3; }, 5'000));
  const auto parts = cell.recorder.parts();
  REQUIRE(parts.size() == 3);
  for (const auto& p : parts) {
    CHECK(p.frames == cell.sim_cell.rig().frames_per_pass());
    CHECK(p.points > 1000);
    CHECK(p.publish == drivers::PublishStatus::kQueued);
    CHECK(p.cycle_ms >= 0.0);
  }
  CHECK(parts[0].class_name == "gamma");
  CHECK(parts[2].points == cell.recogniser_ptr->points_seen());
  CHECK(cell.recogniser_ptr->calls() == 3);
}

TEST_CASE("loop: a recogniser past the hard deadline gives 'timeout' at the deadline, never its late answer",
          "[run][loop][deadline]") {
  app::Config config = small_config();
  config.runtime.deadline_ms = 200;
  // The loop's longest single wait, longer than the deadline: a wait for the recogniser that is not cut at the
  // deadline would publish "timeout" a whole slice late, which the bound below tells from scheduling delays.
  constexpr int kPollSliceMs = 1000;
  Script slow;
  slow.delay_ms = config.runtime.deadline_ms + kPollSliceMs + 300;  // still inside hung_grace_ms after the deadline
  SECTION("a recogniser that ignores the deadline") {
    slow.honour_deadline = false;
  }
  SECTION("a recogniser that gives up at the deadline") {
    slow.honour_deadline = true;
  }
  Cell cell(config, {Script{}, slow, Script{}});
  cell.enqueue(3);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 3;
  lc.poll_slice_ms = kPollSliceMs;
  REQUIRE(slow.delay_ms < config.runtime.deadline_ms + lc.hung_grace_ms);
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  REQUIRE(loop.start().ok());
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 3; }, 5000));
  std::this_thread::sleep_for(milliseconds(100));  // nothing more may arrive
  CHECK(plc.count() == 3);
  CHECK(plc.violations() == 0);
  const auto s1 = plc.seen(1);
  const Block timed_out(s1.block);
  check_timeout_result(timed_out, 2);
  // CYCLE_MS is the loop's own clock (part-present fall -> publish). Published at the deadline, not a poll slice
  // later and not when the recogniser came back: half a slice of margin is scheduling delay, a whole one is a bug.
  CHECK(timed_out.cycle_ms() >= config.runtime.deadline_ms);
  CHECK(timed_out.cycle_ms() <= config.runtime.deadline_ms + kPollSliceMs / 2);
  const auto s2 = plc.seen(2);
  CHECK(Block(s2.block).code() == 0);
  CHECK(Block(s2.block).acq_id() == 3);
  const runtime::LoopStats stats = loop.stats();
  CHECK(stats.timeouts == 1);
  CHECK(stats.results == 3);
  if (!slow.honour_deadline) CHECK(stats.late_decisions == 1);
}

// Holds the loop thread inside its kScanning -> kRecognising transition of one pass (the job is posted by then)
// until the recogniser has answered, as a loop thread that the scheduler did not run in time would be held.
class HoldLoopUntilAnswered final : public runtime::LoopObserver {
 public:
  HoldLoopUntilAnswered(const ScriptedRecogniser& recogniser, std::size_t call)
      : recogniser_(recogniser), call_(call) {}
  void on_state(LoopState from, LoopState to, ErrorCode /*error*/) override {
    if (from != LoopState::kScanning || to != LoopState::kRecognising || ++passes_ != call_) return;
    while (recogniser_.returned() < call_) std::this_thread::sleep_for(milliseconds(1));
    // recognise() has returned; the recognition thread still stamps and hands over the answer under its lock.
    std::this_thread::sleep_for(milliseconds(50));
  }

 private:
  const ScriptedRecogniser& recogniser_;
  const std::size_t call_;
  std::size_t passes_ = 0;
};

TEST_CASE("loop: an answer that comes after the deadline but before the loop looks is 'timeout', never the answer",
          "[run][loop][deadline]") {
  app::Config config = small_config();
  config.runtime.deadline_ms = 200;
  Script late;  // an "ok" decision, delivered 100 ms after the deadline (recognition started at the fall)
  late.delay_ms = config.runtime.deadline_ms + 100;
  late.honour_deadline = false;
  Cell cell(config, {Script{}, late, Script{}});
  cell.enqueue(3);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 3;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  HoldLoopUntilAnswered hold(*cell.recogniser_ptr, 2);
  loop.set_observer(&hold);
  REQUIRE(loop.start().ok());
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 3; }, 5000));
  CHECK(plc.violations() == 0);
  // Then the second part's result is "timeout" with no part and no pose, although an answer was waiting
  const auto s1 = plc.seen(1);
  const Block held(s1.block);
  check_timeout_result(held, 2);
  CHECK(held.cycle_ms() >= config.runtime.deadline_ms);
  const auto s0 = plc.seen(0), s2 = plc.seen(2);
  CHECK(Block(s0.block).code() == 0);
  CHECK(Block(s2.block).code() == 0);
  const runtime::LoopStats stats = loop.stats();
  CHECK(stats.timeouts == 1);
  CHECK(stats.late_decisions == 1);
  CHECK(cell.recogniser_ptr->calls() == 3);
  loop.request_stop();
  loop.join();  // before `hold` goes: the loop reports its last transitions to it
}

TEST_CASE("loop: timeouts in a row raise ERROR_CODE 'repeated timeouts', a cycle inside the deadline clears it",
          "[run][loop][deadline]") {
  app::Config config = small_config();
  config.runtime.deadline_ms = 100;
  Script slow;
  slow.delay_ms = 400;
  Cell cell(config, {Script{}, slow, slow, slow, Script{}});
  cell.enqueue(5);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 5;
  lc.max_consecutive_timeouts = 3;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  REQUIRE(loop.start().ok());
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 5; }, 5000));
  CHECK(plc.saw_error(ErrorCode::kRepeatedTimeouts));
  CHECK(plc.error_code() == 0);
  CHECK(plc.valid_during_error() == 0);  // results were withheld while the error stood
  CHECK(plc.violations() == 0);
  std::array<std::uint16_t, 5> codes{};
  for (std::size_t i = 0; i < 5; ++i) codes[i] = Block(plc.seen(i).block).code();
  CHECK(codes == std::array<std::uint16_t, 5>{0, 6, 6, 6, 0});
  CHECK(loop.stats().error == ErrorCode::kNone);
}

TEST_CASE(
    "loop: the camera stalls mid-part: scan aborted, ERROR_CODE camera timeout on the PLC, recovery when "
    "frames return",
    "[run][loop][fault]") {
  const app::Config config = small_config();
  Cell cell(config, {Script{}});
  cell.enqueue(3);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 3;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  cell.recorder.stall_at(cell.line, 2, 10);
  REQUIRE(loop.start().ok());

  REQUIRE(
      wait_until([&] { return plc.error_code() == static_cast<std::uint16_t>(ErrorCode::kCameraTimeout); }, 30'000));
  CHECK((plc.status() & map::kStatusError) != 0);
  // ERROR goes out first (before the aborted part's "bad scan" result), the state follows within the step.
  CHECK(wait_until([&] { return loop.state() == LoopState::kFault; }, 1000));
  CHECK(loop.stats().aborted_scans == 1);
  // While the camera stays silent the cell stays in fault and the PLC is told so.
  std::this_thread::sleep_for(milliseconds(300));
  CHECK(loop.state() == LoopState::kFault);
  CHECK((plc.status() & map::kStatusReady) == 0);
  CHECK((plc.status() & map::kStatusTriggerReady) == 0);
  CHECK(plc.count() == 1);  // the aborted part's result waits behind the fault

  cell.line.set_camera_stalled(false);
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 3; }, 5000));
  CHECK(plc.error_code() == 0);
  CHECK(plc.valid_during_error() == 0);
  CHECK(plc.violations() == 0);
  std::array<std::uint16_t, 3> codes{};
  std::array<std::uint32_t, 3> acqs{};
  for (std::size_t i = 0; i < 3; ++i) {
    codes[i] = Block(plc.seen(i).block).code();
    acqs[i] = Block(plc.seen(i).block).acq_id();
  }
  CHECK(codes == std::array<std::uint16_t, 3>{0, 5, 0});  // ok, bad scan (aborted), ok
  CHECK(acqs == std::array<std::uint32_t, 3>{1, 2, 3});
  const runtime::LoopStats stats = loop.stats();
  CHECK(stats.faults == 1);
  CHECK(stats.recoveries == 1);
  const auto edges = edges_of(cell.recorder.transitions());
  CHECK(std::count(edges.begin(), edges.end(), std::pair{LoopState::kPublishing, LoopState::kFault}) == 1);
  CHECK(std::count(edges.begin(), edges.end(), std::pair{LoopState::kFault, LoopState::kIdle}) == 1);
  // The third part was scanned whole after the recovery (its record may follow its result by a moment).
  REQUIRE(wait_until([&] { return cell.recorder.part_count() == 3; }, 5'000));
  CHECK(cell.recorder.parts().back().frames == cell.sim_cell.rig().frames_per_pass());
}

TEST_CASE("loop: nothing is allocated inside the loop over several simulated parts", "[run][loop][alloc]") {
  const app::Config config = small_config();
  Cell cell(config, {Script{}});
  constexpr int kParts = 8;
  constexpr std::uint64_t kWarmUp = 2;
  cell.enqueue(kParts);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = kParts;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  // With the operator's screen the recognition thread also copies kept scans (here: every pass, teach mode) and a
  // thinned preview of every pass for the live picture.
  runtime::ScanKeeper keeper(kParts, 20'000);
  runtime::ScanKeeper preview(kParts, 1'000);
  bool teach = false;
  SECTION("production") {}
  SECTION("teach mode and the live picture: every pass is kept for the screen") {
    teach = true;
    loop.set_keeper(&keeper, true);
    loop.set_preview(&preview);
    REQUIRE(loop.post_command(drivers::CommandCode::kEnterTeach, 9));
  }
  REQUIRE(loop.start().ok());
  REQUIRE(wait_until([&] { return loop.stats().results >= kWarmUp; }, 60'000));
  long allocations = 0;
  std::uint64_t counted_from = 0, counted_to = 0;
  std::uint64_t frames_from = 0;
  {
    AllocationWindow window;  // every thread: loop, recognition; not the simulator or the PLC (see WorldScope)
    counted_from = loop.stats().results;
    frames_from = loop.stats().iterations;
    (void)wait_until([&] { return loop.finished(); }, 60'000);
    counted_to = loop.stats().results;
    allocations = window.count();
  }
  CHECK(allocations == 0);
  CHECK(counted_to - counted_from >= kParts - kWarmUp - 1);  // whole parts went through inside the window
  CHECK(loop.stats().iterations - frames_from > 100);
  REQUIRE(wait_until([&] { return plc.count() == kParts; }, 5000));
  CHECK(plc.violations() == 0);
  if (teach) {
    CHECK(keeper.kept() == kParts);
    CHECK(keeper.truncated() == 0);
    CHECK(preview.kept() == kParts);
    const runtime::KeptScanInfo* info = nullptr;
    std::span<const algo::ScanPoint> points;
    REQUIRE(preview.peek(info, points));
    CHECK(points.size() <= 1'000);
    CHECK(points.size() > 500);
    CHECK(points.back().frame >= 25);  // thinned evenly over the pass's 30 frames, not cut after the first 1000
  }
  loop.request_stop();
  loop.join();
}

// ------------------------------------------------------------------ a replayed line (for long runs)

// Passes rendered once by the simulator, then replayed through the three device interfaces: the device side
// allocates nothing, so RSS over hundreds of parts measures the loop alone, and fast.
class ReplayLine {
 public:
  ReplayLine(sim::SimCell& cell, int passes, std::int32_t exposure_us) {
    for (int p = 0; p < passes; ++p) {
      const auto& part = cell.catalogue()[static_cast<std::size_t>(p) % cell.catalogue().size()];
      auto pass = cell.random_pass(part.name, 500 + static_cast<std::uint64_t>(p));
      REQUIRE(pass.ok());
      REQUIRE(cell.begin_pass(*pass).ok());
      std::vector<cv::Mat> frames;
      std::vector<std::int64_t> counts;
      for (int f = 0; f < cell.frame_count(); ++f) {
        cv::Mat image;
        cell.render_frame(f, exposure_us, image);
        frames.push_back(image.clone());
        counts.push_back(cell.frame_info(f).encoder_counts);
      }
      frames_.push_back(std::move(frames));
      counts_.push_back(std::move(counts));
    }
  }
  DeviceStatus next_edge(drivers::EdgeEvent& out) {
    out.input = drivers::Input::kPartPresent;
    if (falling_pending_) {
      falling_pending_ = false;
      out.edge = drivers::Edge::kFalling;
      return DeviceStatus::kOk;
    }
    if (in_pass_) return DeviceStatus::kTimeout;
    pass_ = passes_started_++ % frames_.size();
    base_counts_ = counts_now_ + kGapCounts;
    frame_ = 0;
    in_pass_ = true;
    out.edge = drivers::Edge::kRising;
    return DeviceStatus::kOk;
  }
  DeviceStatus next_frame(drivers::Frame& out) {
    if (!in_pass_) return DeviceStatus::kTimeout;
    const cv::Mat& image = frames_[pass_][frame_];
    out.data = image.data;
    out.width_px = image.cols;
    out.height_px = image.rows;
    out.stride_bytes = static_cast<int>(image.step);
    out.sequence = sequence_++;
    out.buffer_index = 0;
    counts_now_ = base_counts_ + counts_[pass_][frame_];
    if (++frame_ == frames_[pass_].size()) {
      in_pass_ = false;
      falling_pending_ = true;
    }
    return DeviceStatus::kOk;
  }
  [[nodiscard]] bool present() const { return in_pass_ || falling_pending_; }
  [[nodiscard]] std::int64_t counts() const { return counts_now_; }

 private:
  static constexpr std::int64_t kGapCounts = 3500;
  std::vector<std::vector<cv::Mat>> frames_;
  std::vector<std::vector<std::int64_t>> counts_;
  std::size_t pass_ = 0, frame_ = 0;
  std::uint64_t passes_started_ = 0, sequence_ = 0;
  std::int64_t base_counts_ = 0, counts_now_ = 0;
  bool in_pass_ = false, falling_pending_ = false;
};

class ReplayCamera final : public drivers::Camera {
 public:
  explicit ReplayCamera(ReplayLine& line) : line_(line) {}
  Status start() override { return {}; }
  void stop() override {}
  DeviceStatus set_exposure_us(std::int32_t /*us*/) override { return DeviceStatus::kOk; }
  DeviceStatus grab(drivers::Frame& out, int /*timeout_ms*/) override { return line_.next_frame(out); }
  void release(const drivers::Frame& /*frame*/) override {}

 private:
  ReplayLine& line_;
};

class ReplayIo final : public drivers::DigitalIo {
 public:
  explicit ReplayIo(ReplayLine& line) : line_(line) {}
  Status open() override { return {}; }
  void close() override {}
  DeviceStatus set(drivers::Output /*line*/, bool /*active*/) override { return DeviceStatus::kOk; }
  DeviceStatus pulse(drivers::Output /*line*/, std::int32_t /*width_us*/) override { return DeviceStatus::kOk; }
  DeviceStatus read(drivers::Input /*line*/, bool& active) override {
    active = line_.present();
    return DeviceStatus::kOk;
  }
  DeviceStatus wait_edge(drivers::EdgeEvent& out, int /*timeout_ms*/) override { return line_.next_edge(out); }

 private:
  ReplayLine& line_;
};

class ReplayEncoder final : public drivers::Encoder {
 public:
  explicit ReplayEncoder(ReplayLine& line) : line_(line) {}
  Status open() override { return {}; }
  void close() override {}
  DeviceStatus read_counts(std::int64_t& counts) override {
    counts = line_.counts();
    return DeviceStatus::kOk;
  }

 private:
  ReplayLine& line_;
};

long resident_pages() {
  std::ifstream statm("/proc/self/statm");
  long size = 0, resident = 0;
  statm >> size >> resident;
  return resident;
}

TEST_CASE("loop: RSS after 200 parts equals RSS after 20 within a few pages", "[run][loop][memory]") {
  const app::Config config = small_config();
  auto cell = app::make_sim_cell(config);
  REQUIRE(cell.ok());
  ReplayLine line(*cell, 3, static_cast<std::int32_t>(config.camera.exposure_us));
  ReplayCamera camera(line);
  ReplayIo io(line);
  ReplayEncoder encoder(line);
  drivers::SimPlcLink link;
  runtime::LoopConfig lc = small_loop_config(config);
  constexpr std::uint64_t kFew = 20, kMany = 200;
  lc.max_parts = kMany;
  // The replayed conveyor waits for the cell, so the line is paced by its PLC: without holding, a Release build
  // scans faster than this PLC acknowledges, the link's queue fills and results are (rightly) rejected.
  lc.hold_when_queue_full = true;
  lc.result_queue_capacity = drivers::PlcLinkConfig{}.result_queue_capacity;
  runtime::ProductionLoop loop(lc, camera, io, encoder, app::scan_builder_params(config),
                               test::true_calibration(cell->rig()), link);
  loop.set_recogniser(std::make_unique<ScriptedRecogniser>(std::vector<Script>{Script{}}));
  REQUIRE(link.start().ok());
  SimPlc plc(link);
  REQUIRE(loop.start().ok());
  REQUIRE(wait_until([&] { return plc.count() >= kFew; }, 120'000));
  const long rss_few = resident_pages();
  REQUIRE(loop.wait_finished(milliseconds(300'000)));
  REQUIRE(wait_until([&] { return plc.count() == kMany; }, 10'000));
  const long rss_many = resident_pages();
  const long page_kib = sysconf(_SC_PAGESIZE) / 1024;
  INFO("RSS after " << kFew << " parts: " << rss_few * page_kib << " KiB, after " << kMany
                    << " parts: " << rss_many * page_kib << " KiB");
#if defined(__SANITIZE_THREAD__)
  WARN("RSS is not compared under ThreadSanitizer: its own history buffers grow with run time");
#elif defined(__SANITIZE_ADDRESS__)
  // ASan's RSS holds its own bookkeeping: a freed block waits in the quarantine instead of being reused and every new
  // allocation stack goes into the stack depot, so a busy machine's thread timing alone moved it by 19 pages (seen in
  // CI). The loop's own allocations are checked by the no-allocation test; RSS is compared in the Release run of this
  // binary (scripts/test.sh), where it measures the program.
  WARN("RSS is not compared under AddressSanitizer: its quarantine and stack depot grow with the other threads' work");
#else
  constexpr long kFewPages = 8;
  CHECK(rss_many - rss_few <= kFewPages);
#endif
  CHECK(plc.violations() == 0);
  CHECK(loop.stats().results_rejected == 0);
  std::printf("RSS: %ld KiB after %llu parts, %ld KiB after %llu parts (%+ld pages)\n", rss_few * page_kib,
              static_cast<unsigned long long>(kFew), rss_many * page_kib, static_cast<unsigned long long>(kMany),
              rss_many - rss_few);
}

// ------------------------------------------------------------------ triggers, commands, pacing, models

TEST_CASE("loop: parts wait for TRIGGER_ENABLE, and SW_TRIGGER with nothing in front of the sensor gives 'no part'",
          "[run][loop][handshake]") {
  const app::Config config = small_config();
  Cell cell(config, {Script{}});
  cell.enqueue(1);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.require_trigger_enable = true;
  lc.max_parts = 2;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  REQUIRE(loop.start().ok());
  std::this_thread::sleep_for(milliseconds(300));
  CHECK(loop.stats().triggers == 0);
  CHECK(cell.line.passes_started() == 0);  // the simulated conveyor waits for a ready cell
  CHECK((plc.status() & map::kStatusReady) != 0);
  CHECK((plc.status() & map::kStatusTriggerReady) == 0);

  plc.set_control_bits(map::kControlTriggerEnable);
  REQUIRE(wait_until([&] { return plc.count() == 1; }, 30'000));
  CHECK(Block(plc.seen(0).block).code() == 0);
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusTriggerReady) != 0; }, 5000));

  plc.pulse(map::kControlSwTrigger);  // the conveyor is empty now
  REQUIRE(wait_until([&] { return plc.count() == 2; }, 10'000));
  const auto s1 = plc.seen(1);
  const Block no_part(s1.block);
  CHECK(no_part.code() == 1);
  CHECK(no_part.acq_id() == 2);
  CHECK(no_part.part_id() == 0);
  CHECK(plc.trigger_count() == 2);
  CHECK(plc.error_code() == 0);
  CHECK(cell.recogniser_ptr->calls() == 1);  // nothing to recognise on an empty pass
}

TEST_CASE(
    "loop: with a PLC that does not acknowledge, a full result queue holds the line instead of losing "
    "results",
    "[run][loop][handshake]") {
  const app::Config config = small_config();
  drivers::PlcLinkConfig link_config;
  link_config.result_queue_capacity = 2;
  Cell cell(config, {Script{}}, link_config);
  constexpr int kParts = 5;
  cell.enqueue(kParts);
  SimPlc plc(cell.link, /*ack=*/false);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.hold_when_queue_full = true;
  lc.result_queue_capacity = 2;
  lc.max_parts = kParts;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  REQUIRE(loop.start().ok());
  // One result presented, two queued: the third pass is the last one taken.
  REQUIRE(wait_until([&] { return loop.stats().results == 3; }, 60'000));
  std::this_thread::sleep_for(milliseconds(400));
  CHECK(loop.stats().triggers == 3);
  CHECK(loop.stats().results_rejected == 0);
  CHECK(cell.line.queued() == kParts - 3);
  CHECK((plc.status() & map::kStatusTriggerReady) == 0);
  CHECK(plc.count() == 1);

  plc.set_ack(true);
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == kParts; }, 10'000));
  CHECK(plc.violations() == 0);
  CHECK(loop.stats().results_rejected == 0);
  CHECK(cell.link.stats().results_rejected == 0);
}

TEST_CASE(
    "loop: without a model database the PLC sees ERROR_CODE 6, CLEAR_ERROR retries loading and the cell "
    "recovers",
    "[run][loop][fault]") {
  const app::Config config = small_config();
  Cell cell(config, {Script{}});
  cell.enqueue(1);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.max_parts = 1;
  lc.models_retry_ms = 600'000;  // only CLEAR_ERROR retries in this test
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  loop.set_recogniser(nullptr);
  std::atomic<bool> database_ready{false};
  std::atomic<int> loads{0};
  loop.set_recogniser_loader([&]() -> Expected<std::unique_ptr<runtime::Recogniser>> {
    loads.fetch_add(1);
    if (!database_ready.load()) return make_error("models/manifest.yaml is not there (test)");
    return std::unique_ptr<runtime::Recogniser>(std::make_unique<ScriptedRecogniser>(std::vector<Script>{Script{}}));
  });
  REQUIRE(loop.start().ok());
  REQUIRE(wait_until([&] { return plc.error_code() == 6; }, 5000));
  CHECK((plc.status() & map::kStatusReady) == 0);
  std::this_thread::sleep_for(milliseconds(200));
  CHECK(cell.line.passes_started() == 0);
  CHECK(loads.load() == 0);

  plc.pulse(map::kControlClearError);  // still nothing there
  REQUIRE(wait_until([&] { return loads.load() == 1; }, 5000));
  std::this_thread::sleep_for(milliseconds(100));
  CHECK(plc.error_code() == 6);
  CHECK(loop.state() == LoopState::kFault);

  database_ready = true;
  plc.pulse(map::kControlClearError);
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  REQUIRE(wait_until([&] { return plc.count() == 1; }, 5000));
  CHECK(plc.error_code() == 0);
  CHECK(Block(plc.seen(0).block).code() == 0);
  CHECK(loads.load() == 2);
  loop.request_stop();
  loop.join();  // before the loader's captures go
}

// ================================================================== a real Modbus server and client

// A PLC on a libmodbus TCP client: enables triggers, takes every RESULT_VALID block and acknowledges it.
struct ModbusPlcResult {
  std::array<std::uint16_t, map::kResultBlockCount> block{};
};

TEST_CASE("loop: through a real Modbus server on 127.0.0.1 a libmodbus PLC takes every result by the handshake",
          "[run][loop][modbus]") {
  const app::Config config = small_config();
  Script second;
  second.part_id = 4;
  second.x_m = 0.0271;
  second.theta_rad = -0.031;
  second.z_m = -0.0015;
  second.pose_sigma = {0.0001, 0.0002, 0.0009, kNaN, kNaN, 0.0005};
  Cell cell(config, {Script{}, second, Script{}, second});
  constexpr int kParts = 4;
  cell.enqueue(kParts);
  drivers::ModbusServerConfig server_config;
  server_config.bind_address = "127.0.0.1";
  server_config.port = 0;  // any free port
  drivers::ModbusServer server(server_config);
  REQUIRE(server.start().ok());
  const auto server_started = Clock::now();
  runtime::LoopConfig lc = small_loop_config(config);
  lc.require_trigger_enable = true;  // DESIGN.md handshake: the PLC enables triggers
  lc.max_parts = kParts;
  runtime::ProductionLoop& loop = cell.make_loop(lc, &server);
  REQUIRE(loop.start().ok());

  std::vector<ModbusPlcResult> results;
  int errors = 0;
  std::uint16_t heartbeat_first = 0, heartbeat_last = 0;
  std::int64_t heartbeat_window_ms = 0;
  {
    modbus_t* ctx = modbus_new_tcp("127.0.0.1", server.bound_port());
    REQUIRE(ctx != nullptr);
    REQUIRE(modbus_connect(ctx) == 0);
    // The PLC's patience per request. libmodbus's default of 0.5 s is wall-clock luck under ThreadSanitizer on a
    // loaded machine (it failed so once): after one late reply every later call reads the reply to the call
    // before it (libmodbus does not resynchronise) and the PLC never sees a result. Reply time is not what this
    // test is about; a server stalled for longer than this still fails it.
    constexpr int kPlcResponseTimeoutS = 10;
    (void)modbus_set_response_timeout(ctx, kPlcResponseTimeoutS, 0);
    const auto deadline = Clock::now() + std::chrono::seconds(60);
    std::uint16_t status[2] = {0, 0};
    if (modbus_write_register(ctx, map::kControl, map::kControlTriggerEnable) != 1) ++errors;
    std::uint16_t plc_heartbeat = 0;
    while (static_cast<int>(results.size()) < kParts && Clock::now() < deadline) {
      if (modbus_write_register(ctx, map::kPlcHeartbeat, ++plc_heartbeat) != 1) ++errors;  // the PLC is alive
      if (modbus_read_registers(ctx, map::kStatus, 2, status) != 2) ++errors;
      if ((status[0] & map::kStatusResultValid) == 0) {
        std::this_thread::sleep_for(milliseconds(2));
        continue;
      }
      ModbusPlcResult r;
      if (modbus_read_registers(ctx, map::kResultBlockFirst, map::kResultBlockCount, r.block.data()) !=
          map::kResultBlockCount) {
        ++errors;
      }
      results.push_back(r);
      if (modbus_write_register(ctx, map::kControl, map::kControlTriggerEnable | map::kControlResultAck) != 1) ++errors;
      while (Clock::now() < deadline) {
        if (modbus_read_registers(ctx, map::kStatus, 1, status) != 1) ++errors;
        if ((status[0] & map::kStatusResultValid) == 0) break;
        std::this_thread::sleep_for(milliseconds(1));
      }
      if (modbus_write_register(ctx, map::kControl, map::kControlTriggerEnable) != 1) ++errors;
    }
    // The loop keeps HEARTBEAT moving (it calls PlcLink::heartbeat() every iteration). Four parts take well under
    // a heartbeat period in Release, so watch it after they are done, once the link's loop watchdog would have
    // frozen it for a loop that never called: from twice the watchdog time after start, over three periods.
    const auto watch_from = server_started + 2 * milliseconds(server_config.link.loop_watchdog_ms);
    while (Clock::now() < watch_from) {
      if (modbus_write_register(ctx, map::kPlcHeartbeat, ++plc_heartbeat) != 1) ++errors;
      std::this_thread::sleep_for(milliseconds(map::kHeartbeatPeriodMs / 2));
    }
    if (modbus_read_registers(ctx, map::kHeartbeat, 1, &heartbeat_first) != 1) ++errors;
    const auto first_read = Clock::now();
    std::this_thread::sleep_for(3 * milliseconds(map::kHeartbeatPeriodMs));
    if (modbus_write_register(ctx, map::kPlcHeartbeat, ++plc_heartbeat) != 1) ++errors;
    const auto last_sent = Clock::now();
    if (modbus_read_registers(ctx, map::kHeartbeat, 1, &heartbeat_last) != 1) ++errors;
    heartbeat_window_ms = std::chrono::duration_cast<milliseconds>(last_sent - first_read).count();
    modbus_close(ctx);
    modbus_free(ctx);
  }
  REQUIRE(loop.wait_finished(milliseconds(10'000)));
  loop.request_stop();
  loop.join();
  server.stop();
  CHECK(errors == 0);
  REQUIRE(results.size() == kParts);
  for (std::size_t i = 0; i < results.size(); ++i) {
    const Block b(results[i].block);
    const Script& expected = i % 2 == 0 ? Script{} : second;
    CHECK(b.seq() == i + 1);
    CHECK(b.seq_copy() == i + 1);
    CHECK(b.seq_copy2() == i + 1);  // the whole version-2 block came in the one read
    CHECK(b.acq_id() == i + 1);
    CHECK(b.code() == 0);
    CHECK(b.part_id() == expected.part_id);
    CHECK(b.x_um() == static_cast<std::int32_t>(std::lround(expected.x_m * 1e6)));
    CHECK(b.y_um() == static_cast<std::int32_t>(std::lround(expected.y_m * 1e6)));
    CHECK(b.rz_mdeg() == mdeg(expected.theta_rad));
    CHECK(b.z_um() == (i % 2 == 0 ? map::kInvalidS32 : -1500));
    // 0.1, 0.2, 0.9 mm; rx, ry unfixed; 0.5 mrad = 28.65 mdeg
    CHECK(b.sigmas() == (i % 2 == 0
                             ? std::array<std::uint16_t, 6>{kNoSigma, kNoSigma, kNoSigma, kNoSigma, kNoSigma, kNoSigma}
                             : std::array<std::uint16_t, 6>{100, 200, 900, kNoSigma, kNoSigma, 29}));
  }
  // Sampled at least heartbeat_window_ms apart: that many whole periods were crossed, unless HEARTBEAT was frozen.
  INFO("HEARTBEAT " << heartbeat_first << " -> " << heartbeat_last << " over at least " << heartbeat_window_ms
                    << " ms");
  CHECK(static_cast<std::uint16_t>(heartbeat_last - heartbeat_first) >= heartbeat_window_ms / map::kHeartbeatPeriodMs);
  CHECK(server.stats().results_acked == kParts);
}

// ================================================================== `cellsight run` in-process

// A calibration file with the simulator's true sensor (the production path refuses to run without one).
std::string write_true_calibration(const app::Config& config, const std::filesystem::path& dir) {
  const sim::Rig rig = sim::make_rig(config.rig);
  formats::CalibrationRecord record;
  record.has_camera = record.has_laser = record.has_conveyor = true;
  record.sensor = test::true_calibration(rig);
  record.camera_views = 12;
  record.laser_points = 1000;
  record.camera_date = record.laser_date = record.conveyor_date = "2024-01-01 00:00:00";
  record.has_support = true;  // the carrier's bars lie in the plane z = carrier.plane_z_m
  record.support.normal = Eigen::Vector3d::UnitZ();
  record.support.offset_m = config.rig.carrier.plane_z_m;
  record.support_points = 1000;
  record.support_date = record.camera_date;
  const std::string path = (dir / "calibration.yaml").string();
  auto saved = formats::save_calibration(path, record);
  REQUIRE(saved.ok());
  REQUIRE(formats::load_sensor_calibration(path).ok());
  return path;
}

std::filesystem::path fresh_dir(const std::string& name) {
  return test::scratch_dir("run-" + name);
}

// Runs `fn` with stderr going to a file; returns what was written.
template <class Fn>
std::string capture_stderr(const std::filesystem::path& file, Fn fn) {
  std::fflush(stderr);
  const int saved = dup(STDERR_FILENO);
  const int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  REQUIRE(fd >= 0);
  dup2(fd, STDERR_FILENO);
  close(fd);
  fn();
  std::fflush(stderr);
  dup2(saved, STDERR_FILENO);
  close(saved);
  std::ifstream in(file);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

TEST_CASE("run: SIGTERM or SIGINT stops a running simulated cell cleanly: exit 0, Modbus port closed",
          "[run][mode][signal]") {
  const int signal_number = GENERATE(SIGTERM, SIGINT);
  const app::Config config = small_config();
  const auto dir = fresh_dir("signal");
  const std::string calibration = write_true_calibration(config, dir);
  const int port = test::free_tcp_port();
  std::atomic<int> exit_code{-1};
  std::thread cell([&] {
    exit_code =
        cli::run_run({"--sim", "--sim-oracle", "--calibration", calibration, "--port", std::to_string(port)}, config);
  });
  // Serving means the signal handlers are in place (they are installed before the server starts).
  std::uint16_t status[2] = {0, 0};
  std::uint16_t seq[2] = {0, 0};
  bool serving = false, results = false;
  const auto deadline = Clock::now() + std::chrono::seconds(60);
  while (Clock::now() < deadline && exit_code.load() == -1 && !results) {
    modbus_t* ctx = modbus_new_tcp("127.0.0.1", port);
    if (ctx != nullptr && modbus_connect(ctx) == 0) {
      serving = modbus_read_registers(ctx, map::kStatus, 2, status) == 2;
      results = modbus_read_registers(ctx, map::kResultSeq, 2, seq) == 2 && u32(seq) > 0;
      modbus_close(ctx);
    }
    if (ctx != nullptr) modbus_free(ctx);
    std::this_thread::sleep_for(milliseconds(20));
  }
  REQUIRE(serving);
  CHECK(results);  // parts went through before the signal
  CHECK((status[0] & map::kStatusReady) != 0);
  REQUIRE(kill(getpid(), signal_number) == 0);
  const auto stop_deadline = Clock::now() + std::chrono::seconds(20);
  while (exit_code.load() == -1 && Clock::now() < stop_deadline) std::this_thread::sleep_for(milliseconds(10));
  REQUIRE(exit_code.load() != -1);  // else joining would hang: the run did not stop
  cell.join();
  CHECK(exit_code.load() == 0);
  modbus_t* ctx = modbus_new_tcp("127.0.0.1", port);
  REQUIRE(ctx != nullptr);
  CHECK(modbus_connect(ctx) == -1);  // the server is gone
  modbus_free(ctx);
  std::filesystem::remove_all(dir);
}

TEST_CASE(
    "run: real backends without /dev/video or gpiochip, bad arguments, no calibration or no model database "
    "give a clear message and an exit code, no crash",
    "[run][mode]") {
  app::Config config = small_config();
  const auto dir = fresh_dir("errors");
  const std::string calibration = write_true_calibration(config, dir);
  const auto err = dir / "stderr.txt";
  int code = -1;
  SECTION("no camera device: exit 1, the message names it") {
    config.camera.backend = "v4l2";
    config.camera.device = "/dev/video-cellsight-missing";
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run({"--calibration", calibration, "--port", "0"}, config);
    });
    CHECK(code == 1);
    CHECK(text.find("/dev/video-cellsight-missing") != std::string::npos);
  }
  SECTION("no GPIO chip: exit 1, the message names it") {
    config.gpio.backend = "gpiod";
    config.gpio.chip = "gpiochip-cellsight-missing";
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run({"--calibration", calibration, "--port", "0"}, config);
    });
    CHECK(code == 1);
    CHECK(text.find("gpiochip-cellsight-missing") != std::string::npos);
  }
  SECTION("bad arguments: exit 2") {
    const std::string text = capture_stderr(err, [&] { code = cli::run_run({"--parts", "many"}, config); });
    CHECK(code == 2);
    CHECK(text.find("--parts") != std::string::npos);
    CHECK(cli::run_run({"--truth-log", "x.jsonl"}, config) == 2);  // a --sim option without --sim
    CHECK(cli::run_run({"--bogus"}, config) == 2);
  }
  SECTION("an unknown part in --sim-parts: exit 2, the message lists the catalogue") {
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run({"--sim", "--sim-oracle", "--sim-parts", "plate_4h,no_such_part", "--calibration",
                           calibration, "--parts", "1", "--port", "0"},
                          config);
    });
    CHECK(code == 2);
    CHECK(text.find("no_such_part") != std::string::npos);
    CHECK(text.find("plate_4h") != std::string::npos);
  }
  SECTION("no calibration: exit 2, says what to run") {
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run({"--sim", "--calibration", (dir / "none.yaml").string(), "--parts", "1"}, config);
    });
    CHECK(code == 2);
    CHECK(text.find("calibrat") != std::string::npos);
  }
  SECTION("--parts with no model database: exit 2, says what to run") {
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run({"--sim", "--calibration", calibration, "--parts", "1", "--models",
                           (dir / "no-models").string(), "--port", "0"},
                          config);
    });
    CHECK(code == 2);
    CHECK(text.find("no-models") != std::string::npos);
  }
  SECTION("the Modbus port is taken: exit 1, the message says so") {
    drivers::ModbusServerConfig taken_config;
    taken_config.bind_address = "127.0.0.1";
    taken_config.port = 0;
    drivers::ModbusServer taken(taken_config);
    REQUIRE(taken.start().ok());
    const std::string text = capture_stderr(err, [&] {
      code = cli::run_run(
          {"--sim", "--sim-oracle", "--calibration", calibration, "--port", std::to_string(taken.bound_port())},
          config);
    });
    CHECK(code == 1);
    CHECK(text.find("in use") != std::string::npos);
  }
  std::filesystem::remove_all(dir);
}

TEST_CASE("run: arguments", "[run][mode]") {
  auto parsed = cli::parse_run_args({"--sim", "--parts", "20", "--seed", "7", "--sim-parts", "plate_4h,tray",
                                     "--truth-log", "t.jsonl", "--wait-plc", "--port", "0", "--config", "x.yaml"});
  REQUIRE(parsed.ok());
  CHECK(parsed->sim);
  CHECK(parsed->parts == 20);
  CHECK(parsed->seed == 7);
  CHECK(parsed->sim_parts == std::vector<std::string>{"plate_4h", "tray"});
  CHECK(parsed->truth_log == "t.jsonl");
  CHECK(parsed->wait_plc);
  CHECK(parsed->port == 0);
  CHECK_FALSE(parsed->sim_oracle);
  for (const std::vector<std::string>& bad : std::vector<std::vector<std::string>>{{"--parts", "-1"},
                                                                                   {"--parts"},
                                                                                   {"--port", "70000"},
                                                                                   {"--sim", "--sim-parts", ","},
                                                                                   {"--seed", "3"},
                                                                                   {"--sim-oracle"},
                                                                                   {"run"}}) {
    INFO(bad.front());
    CHECK_FALSE(cli::parse_run_args(bad).ok());
  }
}

TEST_CASE("run: --sim --parts N --truth-log writes the simulator's truth of every acquisition", "[run][mode]") {
  const app::Config config = small_config();
  const auto dir = fresh_dir("truth");
  const std::string calibration = write_true_calibration(config, dir);
  const std::string truth = (dir / "truth.jsonl").string();
  const int code = cli::run_run({"--sim", "--sim-oracle", "--parts", "3", "--seed", "7", "--calibration", calibration,
                                 "--truth-log", truth, "--port", "0"},
                                config);
  CHECK(code == 0);
  std::ifstream in(truth);
  std::vector<std::string> lines;
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  REQUIRE(lines.size() == 3);
  // The same parts and poses as the simulator draws for this seed (independent re-draw here).
  auto cell = app::make_sim_cell(config);
  REQUIRE(cell.ok());
  std::mt19937_64 rng(7);
  std::uniform_int_distribution<std::size_t> pick(0, cell->catalogue().size() - 1);
  for (std::size_t k = 0; k < lines.size(); ++k) {
    const std::string& name = cell->catalogue()[pick(rng)].name;
    auto pass = cell->random_pass(name, 7 * 1'000'003ULL + k);
    REQUIRE(pass.ok());
    INFO(lines[k]);
    CHECK(lines[k].find("\"acq_id\": " + std::to_string(k + 1) + ",") != std::string::npos);
    CHECK(lines[k].find("\"part\": \"" + name + "\"") != std::string::npos);
    char x[64];
    std::snprintf(x, sizeof x, "\"x_m\": %.9f", pass->pose.x_m);
    CHECK(lines[k].find(x) != std::string::npos);
  }
  std::filesystem::remove_all(dir);
}

// ================================================================== systemd protocol

TEST_CASE("service: READY=1, WATCHDOG=1 only while the loop is healthy, STOPPING=1", "[run][service]") {
  const auto dir = fresh_dir("notify");
  const std::string socket_path = (dir / "notify.sock").string();
  const int fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  REQUIRE(fd >= 0);
  sockaddr_un address{};
  address.sun_family = AF_UNIX;
  std::snprintf(address.sun_path, sizeof address.sun_path, "%s", socket_path.c_str());
  REQUIRE(bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0);
  timeval timeout{0, 20'000};
  REQUIRE(setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout) == 0);
  setenv("NOTIFY_SOCKET", socket_path.c_str(), 1);
  setenv("WATCHDOG_USEC", "100000", 1);  // systemd would kill after 100 ms without WATCHDOG=1
  setenv("WATCHDOG_PID", std::to_string(getpid()).c_str(), 1);
  struct Unset {
    ~Unset() {
      unsetenv("NOTIFY_SOCKET");  // sd_notify reads it on every call
      unsetenv("WATCHDOG_USEC");
      unsetenv("WATCHDOG_PID");
    }
  } unset_at_end;
  runtime::ServiceNotifier service;
  REQUIRE(service.watchdog_enabled());
  CHECK(service.pet_period_ns() == 50 * kNsPerMs);

  struct Message {
    std::string text;
    Clock::time_point at;
  };
  std::vector<Message> messages;
  std::mutex messages_mutex;
  std::atomic<bool> stop_reader{false};
  std::thread reader([&] {
    while (!stop_reader.load()) {
      char buffer[512];
      const ssize_t n = recv(fd, buffer, sizeof buffer, 0);
      if (n <= 0) continue;
      std::lock_guard lock(messages_mutex);
      messages.push_back({std::string(buffer, static_cast<std::size_t>(n)), Clock::now()});
    }
  });

  app::Config config = small_config();
  config.runtime.deadline_ms = 100;
  Script hang;
  hang.delay_ms = 1500;
  hang.honour_deadline = false;
  Cell cell(config, {Script{}, hang, Script{}});
  cell.enqueue(3);
  SimPlc plc(cell.link);
  runtime::LoopConfig lc = small_loop_config(config);
  lc.hung_grace_ms = 200;
  lc.max_parts = 3;
  runtime::ProductionLoop& loop = cell.make_loop(lc);
  loop.set_service(&service);
  REQUIRE(loop.start().ok());
  service.ready("test cell");
  REQUIRE(loop.wait_finished(milliseconds(60'000)));
  std::this_thread::sleep_for(milliseconds(200));
  service.stopping();
  std::this_thread::sleep_for(milliseconds(100));
  loop.request_stop();
  loop.join();
  stop_reader = true;
  reader.join();
  close(fd);

  CHECK(plc.saw_error(ErrorCode::kInternal));  // the hung recogniser was reported
  const auto transitions = cell.recorder.transitions();
  std::optional<Clock::time_point> hung_from, hung_to;
  for (const auto& t : transitions) {
    if (t.to == LoopState::kFault && t.error == ErrorCode::kInternal) hung_from = t.at;
    if (t.from == LoopState::kFault && hung_from && !hung_to) hung_to = t.at;
  }
  REQUIRE(hung_from.has_value());
  REQUIRE(hung_to.has_value());
  CHECK(*hung_to - *hung_from > milliseconds(800));
  int ready = 0, stopping = 0, before = 0, during = 0, after = 0;
  for (const auto& m : messages) {
    if (m.text.rfind("READY=1", 0) == 0) ++ready;
    if (m.text.rfind("STOPPING=1", 0) == 0) ++stopping;
    if (m.text != "WATCHDOG=1") continue;
    if (m.at < *hung_from) ++before;
    // One pet may have been on its way when the loop declared the hang.
    else if (m.at > *hung_from + milliseconds(60) && m.at < *hung_to)
      ++during;
    else if (m.at > *hung_to)
      ++after;
  }
  CHECK(ready == 1);
  CHECK(stopping == 1);
  CHECK(before >= 2);
  CHECK(during == 0);
  CHECK(after >= 2);
  CHECK(service.watchdog_pets() >= static_cast<std::uint64_t>(before + after));
  std::filesystem::remove_all(dir);
}

}  // namespace

// ================================================================== scans kept for the screen, teach mode, new models

namespace {

// Everything the keeper holds now, oldest first (the consumer's side).
std::vector<std::pair<runtime::KeptScanInfo, std::vector<algo::ScanPoint>>> drain(runtime::ScanKeeper& keeper) {
  std::vector<std::pair<runtime::KeptScanInfo, std::vector<algo::ScanPoint>>> out;
  const runtime::KeptScanInfo* info = nullptr;
  std::span<const algo::ScanPoint> points;
  while (keeper.peek(info, points)) {
    out.emplace_back(*info, std::vector<algo::ScanPoint>(points.begin(), points.end()));
    keeper.release();
  }
  return out;
}

}  // namespace

TEST_CASE(
    "loop: unknown passes and the passes of a part being taught are kept, teach mode is a command between "
    "passes and shows in STATUS",
    "[run][loop][keep]") {
  const app::Config config = small_config();
  Script unknown;
  unknown.source = algo::DecisionSource::kUnknown;
  Cell cell(config, {Script{}, unknown, Script{}, Script{}, Script{}});
  SimPlc plc(cell.link);
  runtime::ScanKeeper keeper(4, app::scan_builder_params(config).max_points);
  runtime::ProductionLoop& loop = cell.make_loop(small_loop_config(config));
  loop.set_keeper(&keeper, true);
  REQUIRE(loop.start().ok());

  // Production: only the unknown one (acq 2) is kept, with every point the recogniser saw.
  cell.enqueue(2);
  REQUIRE(wait_until([&] { return plc.count() == 2; }, 30'000));
  auto kept = drain(keeper);
  REQUIRE(kept.size() == 1);
  CHECK(kept[0].first.tag.acq_id == 2);
  CHECK_FALSE(kept[0].first.tag.teach);
  CHECK(kept[0].first.decision.source == algo::DecisionSource::kUnknown);
  // The PLC can see a result before the observer has its record (publish() hands the result block over first: the
  // sanitizer run under load once read one record here).
  REQUIRE(wait_until([&] { return cell.recorder.part_count() == 2; }, 5'000));
  const auto records = cell.recorder.parts();
  REQUIRE(records.size() == 2);
  CHECK(kept[0].second.size() == records[1].points);
  CHECK(kept[0].second.size() > 1000);
  CHECK((plc.status() & map::kStatusTeachMode) == 0);

  // Teach mode through the command path: STATUS.TEACH_MODE follows, every pass is kept (recognised ones too).
  REQUIRE(loop.post_command(drivers::CommandCode::kEnterTeach, 7));
  REQUIRE(wait_until([&] { return loop.command_fate() != runtime::ProductionLoop::CommandFate::kPending; }, 5000));
  CHECK(loop.command_fate() == runtime::ProductionLoop::CommandFate::kDone);
  CHECK(loop.teaching_part_id() == 7);
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusTeachMode) != 0; }, 5000));
  cell.enqueue(2, 11);
  REQUIRE(wait_until([&] { return plc.count() == 4; }, 30'000));
  kept = drain(keeper);
  REQUIRE(kept.size() == 2);
  for (const auto& [info, points] : kept) {
    CHECK(info.tag.teach);
    CHECK(info.tag.teach_part_id == 7);
    CHECK(info.decision.source == algo::DecisionSource::kSvm);
    CHECK(!points.empty());
  }
  CHECK(kept[0].first.tag.acq_id == 3);
  CHECK(kept[1].first.tag.acq_id == 4);

  REQUIRE(loop.post_command(drivers::CommandCode::kLeaveTeach, 0));
  REQUIRE(wait_until([&] { return loop.command_fate() == runtime::ProductionLoop::CommandFate::kDone; }, 5000));
  REQUIRE(wait_until([&] { return (plc.status() & map::kStatusTeachMode) == 0; }, 5000));
  CHECK(loop.teaching_part_id() == 0);
  // A bad argument is refused, and the mode stays as it was.
  REQUIRE(loop.post_command(drivers::CommandCode::kEnterTeach, 0));
  REQUIRE(wait_until([&] { return loop.command_fate() != runtime::ProductionLoop::CommandFate::kPending; }, 5000));
  CHECK(loop.command_fate() == runtime::ProductionLoop::CommandFate::kRefused);
  CHECK(loop.teaching_part_id() == 0);
  loop.request_stop();
  loop.join();
  CHECK(keeper.dropped() == 0);
}

TEST_CASE("loop: without a keeper ENTER_TEACH is refused, a full keeper drops the scan and never waits",
          "[run][loop][keep]") {
  const app::Config config = small_config();
  Script unknown;
  unknown.source = algo::DecisionSource::kUnknown;
  SECTION("no keeper") {
    Cell cell(config, {Script{}});
    runtime::ProductionLoop& loop = cell.make_loop(small_loop_config(config));
    REQUIRE(loop.start().ok());
    REQUIRE(loop.post_command(drivers::CommandCode::kEnterTeach, 5));
    REQUIRE(wait_until([&] { return loop.command_fate() != runtime::ProductionLoop::CommandFate::kPending; }, 5000));
    CHECK(loop.command_fate() == runtime::ProductionLoop::CommandFate::kRefused);
    CHECK(loop.teaching_part_id() == 0);
  }
  SECTION("one slot that nobody empties") {
    Cell cell(config, {unknown});
    SimPlc plc(cell.link);
    runtime::ScanKeeper keeper(1, app::scan_builder_params(config).max_points);
    runtime::ProductionLoop& loop = cell.make_loop(small_loop_config(config));
    loop.set_keeper(&keeper, true);
    REQUIRE(loop.start().ok());
    cell.enqueue(3);
    REQUIRE(wait_until([&] { return plc.count() == 3; }, 30'000));
    loop.request_stop();
    loop.join();
    CHECK(keeper.kept() == 1);
    CHECK(keeper.dropped() == 2);
    CHECK(drain(keeper).at(0).first.tag.acq_id == 1);
  }
}

TEST_CASE("loop: an offered recogniser is put in place between passes, the replaced one is handed back",
          "[run][loop][keep]") {
  const app::Config config = small_config();
  Cell cell(config, {Script{}});
  SimPlc plc(cell.link);
  runtime::ProductionLoop& loop = cell.make_loop(small_loop_config(config));
  REQUIRE(loop.start().ok());
  cell.enqueue(1);
  REQUIRE(wait_until([&] { return plc.count() == 1; }, 30'000));
  CHECK(Block(plc.seen(0).block).part_id() == 3);
  CHECK(loop.take_retired_recogniser() == nullptr);
  Script other;
  other.part_id = 2;
  CHECK(loop.offer_recogniser(std::make_unique<ScriptedRecogniser>(std::vector<Script>{other})) == nullptr);
  REQUIRE(wait_until([&] { return loop.recognisers_swapped() == 1; }, 5000));
  const std::unique_ptr<runtime::Recogniser> retired = loop.take_retired_recogniser();
  CHECK(retired.get() == static_cast<runtime::Recogniser*>(cell.recogniser_ptr));
  cell.enqueue(1, 5);
  REQUIRE(wait_until([&] { return plc.count() == 2; }, 30'000));
  CHECK(Block(plc.seen(1).block).part_id() == 2);
  loop.request_stop();
  loop.join();
}
