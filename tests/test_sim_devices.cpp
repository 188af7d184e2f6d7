// Simulated camera, digital I/O and encoder: the interfaces the production loop uses, on the simulated line.
#include <catch2/catch.hpp>
#include <chrono>
#include <thread>

#include "app/config.hpp"
#include "app/sim_setup.hpp"
#include "drivers/sim/sim_devices.hpp"
#include "drivers/sim/sim_faults.hpp"

using namespace cellsight;
using drivers::DeviceStatus;

namespace {

struct Cell {
  app::Config config;
  sim::SimCell cell;
};

Cell shipped() {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  auto cell = app::make_sim_cell(*cfg);
  REQUIRE(cell.ok());
  return {*cfg, std::move(*cell)};
}

}  // namespace

TEST_CASE(
    "Given two parts on the simulated line, when the devices are driven like the production loop, then each "
    "pass is a rising edge, its frames in order, then a falling edge") {
  Cell c = shipped();
  sim::SimLine line(c.cell);
  sim::SimCamera camera(line, 4, 1500);
  sim::SimDigitalIo io(line);
  sim::SimEncoder encoder(line);
  REQUIRE(camera.start().ok());
  REQUIRE(io.open().ok());
  REQUIRE(encoder.open().ok());
  REQUIRE(io.set(drivers::Output::kLaserEnable, true) == DeviceStatus::kOk);

  auto first = c.cell.random_pass("plate_4h", 1);
  auto second = c.cell.random_pass("tray", 2);
  line.enqueue(*first);
  line.enqueue(*second);
  drivers::Frame frame;
  drivers::EdgeEvent edge;
  CHECK(camera.grab(frame, 100) == DeviceStatus::kTimeout);  // nothing under the sensor yet

  const int per_pass = c.cell.frame_count();
  const auto trigger = c.config.rig.conveyor.trigger_every_counts;
  std::uint64_t expected_sequence = 0;
  for (const auto& pass : {*first, *second}) {
    REQUIRE(io.wait_edge(edge, 100) == DeviceStatus::kOk);
    CHECK(edge.edge == drivers::Edge::kRising);
    bool present = false;
    REQUIRE(io.read(drivers::Input::kPartPresent, present) == DeviceStatus::kOk);
    CHECK(present);
    CHECK(line.current_pass().part == pass.part);
    std::int64_t start_counts = 0;
    REQUIRE(encoder.read_counts(start_counts) == DeviceStatus::kOk);
    std::int64_t previous_ns = edge.timestamp_ns - 1;
    for (int i = 0; i < per_pass; ++i) {
      if (i == 10) REQUIRE(camera.set_exposure_us(900) == DeviceStatus::kOk);
      REQUIRE(camera.grab(frame, 100) == DeviceStatus::kOk);
      CHECK(frame.sequence == expected_sequence++);
      CHECK(frame.timestamp_ns > previous_ns);
      previous_ns = frame.timestamp_ns;
      CHECK(frame.exposure_us == (i < 10 ? 1500 : 900));
      std::int64_t counts = 0;
      REQUIRE(encoder.read_counts(counts) == DeviceStatus::kOk);
      CHECK(counts - start_counts == static_cast<std::int64_t>(i) * trigger);
      if (i == per_pass / 2) {  // the delivered pixels are the simulated cell's frame of this pass and travel
        Cell reference = shipped();
        REQUIRE(reference.cell.begin_pass(pass).ok());
        cv::Mat expected;
        reference.cell.render_frame(i, frame.exposure_us, expected);
        const cv::Mat got(frame.height_px, frame.width_px, CV_8UC1, const_cast<std::uint8_t*>(frame.data),
                          static_cast<std::size_t>(frame.stride_bytes));
        CHECK(cv::norm(expected, got, cv::NORM_INF) == 0);
      }
      const DeviceStatus edge_status = io.wait_edge(edge, 0);
      if (i + 1 < per_pass) {
        CHECK(edge_status == DeviceStatus::kTimeout);
      } else {
        REQUIRE(edge_status == DeviceStatus::kOk);
        CHECK(edge.edge == drivers::Edge::kFalling);
        CHECK(edge.timestamp_ns > frame.timestamp_ns);
      }
      camera.release(frame);
    }
    REQUIRE(camera.set_exposure_us(1500) == DeviceStatus::kOk);
  }
  CHECK(line.passes_started() == 2);
  CHECK(io.wait_edge(edge, 0) == DeviceStatus::kTimeout);
}

TEST_CASE("Given the laser switched off, when a frame is grabbed, then it shows no stripe, with the laser on it does") {
  Cell c = shipped();
  sim::SimLine line(c.cell);
  sim::SimCamera camera(line, 4, 1500);
  sim::SimDigitalIo io(line);
  REQUIRE(camera.start().ok());
  REQUIRE(io.open().ok());
  auto pass = c.cell.random_pass("plate_4h", 3);
  pass->coating_a = pass->coating_b = sim::Coating{"primer", {0.55, 0.15, 20.0}, 1.0};
  line.enqueue(*pass);
  drivers::EdgeEvent edge;
  REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
  drivers::Frame frame;
  auto brightest = [&] {
    const cv::Mat img(frame.height_px, frame.width_px, CV_8UC1, const_cast<std::uint8_t*>(frame.data),
                      static_cast<std::size_t>(frame.stride_bytes));
    // Ignore isolated hot pixels: the stripe is a run of bright pixels in many rows.
    int rows_with_light = 0;
    for (int r = 0; r < img.rows; ++r) {
      int run = 0, best = 0;
      for (int x = 0; x < img.cols; ++x) {
        run = img.at<std::uint8_t>(r, x) > 100 ? run + 1 : 0;
        best = std::max(best, run);
      }
      rows_with_light += best >= 2 ? 1 : 0;
    }
    return rows_with_light;
  };
  for (int i = 0; i < 140; ++i) {  // move to the middle of the part
    REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
    camera.release(frame);
  }
  REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
  CHECK(brightest() < 5);
  camera.release(frame);
  REQUIRE(io.set(drivers::Output::kLaserEnable, true) == DeviceStatus::kOk);
  REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
  CHECK(brightest() > 300);
  camera.release(frame);
  io.close();
  CHECK_FALSE(line.output(drivers::Output::kLaserEnable));  // closing the I/O leaves the laser off
}

TEST_CASE("Given a stalled camera or held buffers, when grabbing, then the camera reports it instead of blocking") {
  Cell c = shipped();
  sim::SimLine line(c.cell);
  sim::SimCamera camera(line, 4, 1500);
  sim::SimDigitalIo io(line);
  drivers::Frame frame;
  CHECK(camera.grab(frame, 0) == DeviceStatus::kNotStarted);
  REQUIRE(camera.start().ok());
  REQUIRE(io.open().ok());
  line.enqueue(*c.cell.random_pass("tray", 4));
  drivers::EdgeEvent edge;
  REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
  line.set_camera_stalled(true);
  CHECK(camera.grab(frame, 10) == DeviceStatus::kTimeout);
  line.set_camera_stalled(false);
  drivers::Frame held[4];
  for (auto& h : held) REQUIRE(camera.grab(h, 0) == DeviceStatus::kOk);
  CHECK(camera.grab(frame, 0) == DeviceStatus::kIoError);  // all four buffers borrowed
  camera.release(held[2]);
  REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
  CHECK(frame.buffer_index == held[2].buffer_index);
  CHECK(frame.sequence == 4);
  CHECK(camera.set_exposure_us(0) == DeviceStatus::kInvalidArgument);
}

namespace {

// The simulated devices on one line, opened as the production loop opens them.
struct OpenDevices {
  sim::SimLine line;
  sim::SimCamera camera;
  sim::SimDigitalIo io;
  sim::SimEncoder encoder;
  explicit OpenDevices(sim::SimCell& cell, std::int32_t debounce_us = 0)
      : line(cell), camera(line, 4, 1500), io(line, debounce_us), encoder(line) {
    REQUIRE(camera.start().ok());
    REQUIRE(io.open().ok());
    REQUIRE(encoder.open().ok());
  }
};

// Grabs (and releases) frames until the pass ends: the number taken.
int grab_rest_of_pass(sim::SimCamera& camera) {
  drivers::Frame frame;
  int n = 0;
  while (camera.grab(frame, 0) == DeviceStatus::kOk) {
    camera.release(frame);
    ++n;
  }
  return n;
}

}  // namespace

TEST_CASE(
    "Given photo-eye chatter inside the debounce window, when a pass goes by, then the input delivers one "
    "rising and one falling edge and counts the bounces, without a window every bounce is an edge") {
  Cell c = shipped();
  sim::PassFaults chatter;
  chatter.bounce_pairs = 3;
  chatter.bounce_spacing_us = 300;  // 1.8 ms of bouncing after each edge
  drivers::EdgeEvent edge;

  SECTION("gpio.debounce_us 2000: the bounces are filtered") {
    OpenDevices d(c.cell, 2000);
    auto& [line, camera, io, encoder] = d;
    line.enqueue(*c.cell.random_pass("tray", 4), chatter);
    REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
    CHECK(edge.edge == drivers::Edge::kRising);
    CHECK(io.wait_edge(edge, 0) == DeviceStatus::kTimeout);  // the six bounces after it were swallowed
    CHECK(io.bounces() == 6);
    CHECK(grab_rest_of_pass(camera) == c.cell.frame_count());
    REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
    CHECK(edge.edge == drivers::Edge::kFalling);
    CHECK(io.wait_edge(edge, 0) == DeviceStatus::kTimeout);
    CHECK(io.bounces() == 12);
    CHECK(line.passes_started() == 1);
  }
  SECTION("no debounce window: the loop would see every bounce") {
    sim::SimLine line(c.cell);
    sim::SimDigitalIo io(line, 0);
    REQUIRE(io.open().ok());
    line.enqueue(*c.cell.random_pass("tray", 4), chatter);
    int edges = 0;
    std::int64_t previous_ns = -1;
    while (io.wait_edge(edge, 0) == DeviceStatus::kOk) {
      CHECK(edge.edge == (edges % 2 == 0 ? drivers::Edge::kRising : drivers::Edge::kFalling));
      CHECK(edge.timestamp_ns > previous_ns);
      previous_ns = edge.timestamp_ns;
      ++edges;
    }
    CHECK(edges == 7);
    CHECK(io.bounces() == 0);
  }
}

TEST_CASE(
    "Given an injected camera stall and encoder glitch, when the pass reaches their frames, then the camera "
    "delivers nothing and the encoder reads fail for their wall-clock time, then both work again") {
  Cell c = shipped();
  OpenDevices d(c.cell);
  auto& [line, camera, io, encoder] = d;
  sim::PassFaults faults;
  faults.camera_stall_frame = 3;
  faults.camera_stall_ms = 150;
  faults.encoder_glitch_frame = 5;
  faults.encoder_glitch_ms = 150;
  line.enqueue(*c.cell.random_pass("tray", 4), faults);
  drivers::EdgeEvent edge;
  REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
  drivers::Frame frame;
  std::int64_t counts = 0;
  for (int i = 0; i < 3; ++i) {
    REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
    camera.release(frame);
  }
  const auto stalled_at = std::chrono::steady_clock::now();
  CHECK(camera.grab(frame, 0) == DeviceStatus::kTimeout);
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  CHECK(camera.grab(frame, 0) == DeviceStatus::kTimeout);
  while (camera.grab(frame, 0) == DeviceStatus::kTimeout) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  CHECK(std::chrono::steady_clock::now() - stalled_at >= std::chrono::milliseconds(150));
  CHECK(frame.sequence == 3);  // no frame was lost: the stall delays the pass
  camera.release(frame);
  REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);  // frame 4
  camera.release(frame);
  CHECK(encoder.read_counts(counts) == DeviceStatus::kOk);
  REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);  // frame 5: the glitch starts
  camera.release(frame);
  CHECK(encoder.read_counts(counts) == DeviceStatus::kIoError);
  std::this_thread::sleep_for(std::chrono::milliseconds(170));
  CHECK(encoder.read_counts(counts) == DeviceStatus::kOk);
  // Once only: the next pass of the same faults would stall again, this one goes on.
  CHECK(grab_rest_of_pass(camera) == c.cell.frame_count() - 6);
}

TEST_CASE(
    "Given a fault schedule, when it is parsed, then every EVERY-th pass gets its kind, the first rule listed "
    "wins, defaults follow camera.timeout_ms and gpio.debounce_us, and a bad spec is refused") {
  const sim::FaultDefaults defaults{800, 2000};
  auto plan = sim::FaultPlan::parse("camera_stall@10,encoder_glitch@5/250,camera_hiccup@3,chatter@2/4", defaults);
  REQUIRE(plan.ok());
  CHECK(plan->kind_of(9) == "camera_stall");
  CHECK(plan->kind_of(19) == "camera_stall");  // also every 5th: the first rule wins
  CHECK(plan->kind_of(4) == "encoder_glitch");
  CHECK(plan->kind_of(2) == "camera_hiccup");
  CHECK(plan->kind_of(1) == "chatter");
  CHECK(plan->kind_of(0).empty());
  const sim::PassFaults stall = plan->for_pass(9, 296);
  CHECK(stall.camera_stall_ms == 1600);  // twice the camera timeout: the loop must give the pass up
  CHECK(stall.camera_stall_frame == 0);
  CHECK(plan->for_pass(19, 296).camera_stall_frame == 97);  // the next one elsewhere in the pass
  CHECK(plan->for_pass(2, 296).camera_stall_ms == 200);     // a hiccup: a quarter of the timeout
  CHECK(plan->for_pass(4, 296).encoder_glitch_ms == 250);
  const sim::PassFaults chatter = plan->for_pass(1, 296);
  CHECK(chatter.bounce_pairs == 4);
  CHECK(chatter.bounce_spacing_us * (2 * chatter.bounce_pairs) < defaults.debounce_us);  // inside the window
  CHECK_FALSE(plan->for_pass(0, 296).any());
  CHECK(sim::FaultPlan::parse("", defaults)->empty());
  for (const char* bad : {"camera_stall", "flood@3", "chatter@0", "chatter@x", "encoder_glitch@3/0", "chatter@3/"}) {
    INFO(bad);
    CHECK_FALSE(sim::FaultPlan::parse(bad, defaults).ok());
  }
}

TEST_CASE(
    "Given the frame memo, when a pass comes again, then its frames are replayed byte for byte as rendered, "
    "and a frame asked for at another exposure is rendered afresh") {
  Cell c = shipped();
  OpenDevices d(c.cell);
  auto& [line, camera, io, encoder] = d;
  REQUIRE(line.enable_frame_memo(1).ok());
  REQUIRE(io.set(drivers::Output::kLaserEnable, true) == DeviceStatus::kOk);
  const auto pass = c.cell.random_pass("plate_4h", 3);
  std::vector<cv::Mat> first;
  drivers::EdgeEvent edge;
  drivers::Frame frame;
  for (int round = 0; round < 2; ++round) {
    line.enqueue(*pass, {}, 0);
    REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
    for (int i = 0; i < c.cell.frame_count(); ++i) {
      if (round == 1 && i == 100) REQUIRE(camera.set_exposure_us(1200) == DeviceStatus::kOk);
      REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
      const cv::Mat got(frame.height_px, frame.width_px, CV_8UC1, const_cast<std::uint8_t*>(frame.data),
                        static_cast<std::size_t>(frame.stride_bytes));
      if (round == 0 && i < 100) {
        first.push_back(got.clone());
      } else if (round == 1 && i < 100) {
        CHECK(cv::norm(first[static_cast<std::size_t>(i)], got, cv::NORM_INF) == 0);
      }
      camera.release(frame);
    }
    REQUIRE(io.wait_edge(edge, 0) == DeviceStatus::kOk);
  }
  const auto frames = static_cast<std::uint64_t>(c.cell.frame_count());
  CHECK(line.frame_memo().hits() == 100);
  CHECK(line.frame_memo().stores() == frames + (frames - 100));
  // The replayed frames are what the renderer makes of that pass and frame
  Cell reference = shipped();
  REQUIRE(reference.cell.begin_pass(*pass).ok());
  cv::Mat expected;
  reference.cell.render_frame(42, 1500, expected);
  CHECK(cv::norm(expected, first[42], cv::NORM_INF) == 0);
}
