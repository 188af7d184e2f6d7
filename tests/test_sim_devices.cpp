// Simulated camera, digital I/O and encoder: the interfaces the production loop uses, on the simulated line.
#include <catch2/catch.hpp>

#include "app/config.hpp"
#include "app/sim_mode.hpp"
#include "drivers/sim/sim_devices.hpp"

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

TEST_CASE("Given two parts on the simulated line, when the devices are driven like the production loop, then each "
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

TEST_CASE("Given the laser switched off, when a frame is grabbed, then it shows no stripe; with the laser on it does") {
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
