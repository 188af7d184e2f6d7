// Tests of runtime/pass_acquirer: the one acquisition of a part pass, driven one step() at a time through scripted
// device fakes, so each policy (laser, exposure, falling edge, frame timeout, no part, blocked photo-eye, camera
// error) is observed on the pins and counters a real cell would show.
#include <catch2/catch.hpp>
#include <chrono>
#include <cstdint>
#include <string>
#include <vector>

#include "algo/scan_builder.hpp"
#include "app/acquire.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "runtime/pass_acquirer.hpp"
#include "sim_test_util.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using namespace cellsight;
using drivers::DeviceStatus;
using runtime::PassAbort;
using runtime::PassStatus;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

// A camera that answers each grab() from a script (then `otherwise`), returning at once like the simulated cell.
class ScriptedCamera final : public drivers::Camera {
 public:
  ScriptedCamera(int width_px, int height_px)
      : width_(width_px), height_(height_px), pixels_(static_cast<std::size_t>(width_px * height_px), 0) {}
  Status start() override { return {}; }
  void stop() override {}
  DeviceStatus set_exposure_us(std::int32_t exposure_us) override {
    const test::UncountedScope the_device;  // the test's record of the calls, not the code under test
    exposures.push_back(exposure_us);
    exposure_ = exposure_us;
    return exposure_status;
  }
  DeviceStatus grab(drivers::Frame& out, int /*timeout_ms*/) override {
    const DeviceStatus status = next < script.size() ? script[next++] : otherwise;
    if (status != DeviceStatus::kOk) return status;
    out.data = pixels_.data();
    out.width_px = width_;
    out.height_px = height_;
    out.stride_bytes = width_;
    out.sequence = ++delivered;
    out.exposure_us = exposure_;
    out.buffer_index = 0;
    return DeviceStatus::kOk;
  }
  void release(const drivers::Frame& /*frame*/) override { ++released; }

  std::vector<DeviceStatus> script;
  std::size_t next = 0;
  DeviceStatus otherwise = DeviceStatus::kTimeout;
  DeviceStatus exposure_status = DeviceStatus::kOk;
  std::vector<std::int32_t> exposures;
  std::uint64_t delivered = 0;
  int released = 0;

 private:
  int width_;
  int height_;
  std::vector<std::uint8_t> pixels_;
  std::int32_t exposure_ = 0;
};

// Part-present falls once the camera has delivered `falling_after` frames (-1: never); the laser pin is recorded.
class ScriptedIo final : public drivers::DigitalIo {
 public:
  explicit ScriptedIo(const ScriptedCamera& camera) : camera_(camera) {}
  Status open() override { return {}; }
  void close() override {}
  DeviceStatus set(drivers::Output line, bool active) override {
    if (line != drivers::Output::kLaserEnable) return DeviceStatus::kOk;
    if (!active && laser_off_status != DeviceStatus::kOk) return laser_off_status;  // the laser stays on
    laser = active;
    return DeviceStatus::kOk;
  }
  DeviceStatus pulse(drivers::Output /*line*/, std::int32_t /*width_us*/) override { return DeviceStatus::kOk; }
  DeviceStatus read(drivers::Input /*line*/, bool& active) override {
    ++reads;
    active = part_present;
    return DeviceStatus::kOk;
  }
  DeviceStatus wait_edge(drivers::EdgeEvent& out, int /*timeout_ms*/) override {
    if (rising_pending) {
      rising_pending = false;
      out.edge = drivers::Edge::kRising;
      out.timestamp_ns = 111;
      return DeviceStatus::kOk;
    }
    if (falling_after < 0 || fell || camera_.delivered < static_cast<std::uint64_t>(falling_after)) {
      return DeviceStatus::kTimeout;
    }
    fell = true;
    out.edge = drivers::Edge::kFalling;
    out.timestamp_ns = 777;
    return DeviceStatus::kOk;
  }

  bool laser = false;
  DeviceStatus laser_off_status = DeviceStatus::kOk;  // what set(kLaserEnable, false) answers
  bool rising_pending = false;                        // the next wait_edge() reports a rising edge
  bool part_present = true;
  int falling_after = -1;
  bool fell = false;
  int reads = 0;

 private:
  const ScriptedCamera& camera_;
};

class CountingEncoder final : public drivers::Encoder {
 public:
  Status open() override { return {}; }
  void close() override {}
  DeviceStatus read_counts(std::int64_t& counts) override {
    counts = counts_ += 220;
    return status;
  }
  DeviceStatus status = DeviceStatus::kOk;

 private:
  std::int64_t counts_ = 0;
};

// The shipped cell: the acquirer does not care about the image content (the frames here are blank).
app::Config cell_config() {
  app::Config config = app::default_config();
  config.catalogue_path = std::string(CELLSIGHT_SOURCE_DIR) + "/config/parts.yaml";
  return config;
}

// Given the cell's scan builder and the three fakes.
struct Rig {
  app::Config config = cell_config();
  sim::SimCell cell = std::move(*app::make_sim_cell(config));
  algo::ScanBuilder builder{app::scan_builder_params(config), test::true_calibration(cell.rig())};
  ScriptedCamera camera{config.rig.camera.intrinsics.width_px, config.rig.camera.intrinsics.height_px};
  ScriptedIo io{camera};
  CountingEncoder encoder;
  runtime::AcquirerParams params{/*frame_timeout_ms=*/60, /*max_frames=*/50, /*start_exposure_us=*/1234,
                                 /*poll_slice_ms=*/10};

  runtime::PassAcquirer acquirer() { return runtime::PassAcquirer(camera, io, encoder, builder, params); }
};

PassStatus run_to_end(runtime::PassAcquirer& acquirer, int max_steps = 1000) {
  PassStatus status = PassStatus::kScanning;
  for (int i = 0; i < max_steps && status == PassStatus::kScanning; ++i) status = acquirer.step(Clock::now());
  return status;
}

TEST_CASE("pass acquirer: laser on for the pass, start exposure, every frame in the scan, done at the falling edge",
          "[pass_acquirer]") {
  Rig rig;
  rig.camera.otherwise = DeviceStatus::kOk;
  rig.io.falling_after = 5;
  auto acquirer = rig.acquirer();
  REQUIRE(acquirer.begin(false, Clock::now()) == PassStatus::kScanning);
  CHECK(rig.io.laser);
  REQUIRE_FALSE(rig.camera.exposures.empty());
  CHECK(rig.camera.exposures.front() == 1234);
  CHECK(run_to_end(acquirer) == PassStatus::kComplete);
  CHECK(acquirer.frames() == 5);
  CHECK(rig.builder.stats().frames == 5);
  CHECK(rig.camera.released == 5);  // every frame handed back to the driver
  CHECK(acquirer.falling_edge().timestamp_ns == 777);
  CHECK(rig.io.laser);  // until the caller ends the pass
  CHECK(acquirer.end());
  CHECK_FALSE(rig.io.laser);
}

TEST_CASE("pass acquirer: one step waits at most one poll slice, a silent camera aborts after the frame timeout",
          "[pass_acquirer]") {
  Rig rig;  // the camera returns "timeout" at once, like the simulated cell
  auto acquirer = rig.acquirer();
  const auto begun = Clock::now();
  REQUIRE(acquirer.begin(false, begun) == PassStatus::kScanning);
  PassStatus status = PassStatus::kScanning;
  int steps = 0;
  auto longest = Clock::duration::zero();
  while (status == PassStatus::kScanning && steps < 100) {
    const auto t = Clock::now();
    status = acquirer.step(t);
    longest = std::max(longest, Clock::now() - t);
    ++steps;
  }
  CHECK(status == PassStatus::kAborted);
  CHECK(acquirer.abort() == PassAbort::kCameraTimeout);
  CHECK(runtime::error_code(acquirer.abort()) == drivers::ErrorCode::kCameraTimeout);
  CHECK(longest < milliseconds(10 + 40));           // a slice, with room for a loaded machine
  CHECK(Clock::now() - begun >= milliseconds(60));  // not before the frame timeout...
  CHECK(steps >= 4);                                // ...and by sleeping the slices, not by spinning
  CHECK(rig.io.reads == 1);                         // part-present was asked once, at the timeout
}

TEST_CASE("pass acquirer: a software trigger with nothing in front of the sensor is 'no part', not a fault",
          "[pass_acquirer]") {
  Rig rig;
  rig.io.part_present = false;
  SECTION("software trigger: no part") {
    auto acquirer = rig.acquirer();
    REQUIRE(acquirer.begin(true, Clock::now()) == PassStatus::kScanning);
    CHECK(run_to_end(acquirer) == PassStatus::kNoPart);
    CHECK(acquirer.frames() == 0);
  }
  SECTION("part-present trigger: the same silence is a camera timeout") {
    auto acquirer = rig.acquirer();
    REQUIRE(acquirer.begin(false, Clock::now()) == PassStatus::kScanning);
    CHECK(run_to_end(acquirer) == PassStatus::kAborted);
    CHECK(acquirer.abort() == PassAbort::kCameraTimeout);
  }
}

TEST_CASE("pass acquirer: part-present that never falls aborts after max_frames + 1 frames", "[pass_acquirer]") {
  Rig rig;
  rig.params.max_frames = 3;
  rig.camera.otherwise = DeviceStatus::kOk;
  auto acquirer = rig.acquirer();
  REQUIRE(acquirer.begin(false, Clock::now()) == PassStatus::kScanning);
  CHECK(run_to_end(acquirer) == PassStatus::kAborted);
  CHECK(acquirer.abort() == PassAbort::kTooManyFrames);
  CHECK(runtime::error_code(acquirer.abort()) == drivers::ErrorCode::kIoFault);
  CHECK(acquirer.frames() == 4);
}

TEST_CASE("pass acquirer: a camera error aborts the pass and marks the camera for a reopen", "[pass_acquirer]") {
  Rig rig;
  rig.camera.script = {DeviceStatus::kOk, DeviceStatus::kIoError};
  auto acquirer = rig.acquirer();
  REQUIRE(acquirer.begin(false, Clock::now()) == PassStatus::kScanning);
  CHECK(run_to_end(acquirer) == PassStatus::kAborted);
  CHECK(acquirer.abort() == PassAbort::kCamera);
  CHECK(acquirer.camera_failed());
  CHECK(acquirer.frames() == 1);
  acquirer.clear_camera_failed();
  rig.camera.otherwise = DeviceStatus::kIoError;
  CHECK(acquirer.drain(8) == -1);  // outside a pass too
  CHECK(acquirer.camera_failed());
  CHECK(acquirer.camera_error() == DeviceStatus::kIoError);
}

TEST_CASE("pass acquirer: an encoder that cannot be read refuses the pass before the laser goes on",
          "[pass_acquirer]") {
  Rig rig;
  rig.encoder.status = DeviceStatus::kIoError;
  auto acquirer = rig.acquirer();
  CHECK(acquirer.begin(false, Clock::now()) == PassStatus::kNotStarted);
  CHECK(acquirer.abort() == PassAbort::kEncoderUnreadable);
  CHECK_FALSE(rig.io.laser);
}

TEST_CASE("pass acquirer: frames outside a pass are drained without waiting, at most the batch asked for",
          "[pass_acquirer]") {
  Rig rig;
  rig.camera.script = {DeviceStatus::kOk, DeviceStatus::kOk, DeviceStatus::kOk};
  auto acquirer = rig.acquirer();
  CHECK(acquirer.drain(2) == 2);
  CHECK(acquirer.drain(8) == 1);
  CHECK(acquirer.drain(8) == 0);
  CHECK(rig.camera.released == 3);
  CHECK(rig.builder.stats().frames == 0);  // drained frames never reach a scan
}

TEST_CASE("pass acquirer: a whole pass allocates nothing", "[pass_acquirer][alloc]") {
  Rig rig;
  rig.camera.otherwise = DeviceStatus::kOk;
  rig.io.falling_after = 20;
  auto acquirer = rig.acquirer();
  long allocations = 0;
  PassStatus status = PassStatus::kScanning;
  {
    const test::AllocationWindow window;
    if (acquirer.begin(false, Clock::now()) == PassStatus::kScanning) status = run_to_end(acquirer);
    (void)acquirer.end();
    allocations = window.count();
  }
  CHECK(status == PassStatus::kComplete);
  CHECK(acquirer.frames() == 20);
  CHECK(allocations == 0);
}

// The blocking loop of scan, teach and calibrate support around the same acquirer.
TEST_CASE("acquire_pass: a whole pass is ok and leaves the laser off, a laser that will not switch off is an I/O fault",
          "[pass_acquirer]") {
  Rig rig;
  rig.camera.otherwise = DeviceStatus::kOk;
  rig.io.falling_after = 4;
  rig.io.rising_pending = true;
  app::AcquireParams params;
  app::AcquireReport report;
  SECTION("the laser obeys") {
    CHECK(app::acquire_pass(rig.camera, rig.io, rig.encoder, rig.builder, params, report) == app::AcquireResult::kOk);
    CHECK_FALSE(rig.io.laser);
  }
  SECTION("the laser output refuses to switch off") {
    rig.io.laser_off_status = DeviceStatus::kIoError;
    CHECK(app::acquire_pass(rig.camera, rig.io, rig.encoder, rig.builder, params, report) ==
          app::AcquireResult::kIoFault);
    CHECK(rig.io.laser);
  }
  CHECK(report.frames == 4);
  CHECK(report.rising_ns == 111);
}

}  // namespace
