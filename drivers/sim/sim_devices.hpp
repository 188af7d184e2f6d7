// The simulated cell's devices: camera, digital I/O and encoder behind the same interfaces as the real drivers,
// all driven by one SimLine (the conveyor bringing parts past the sensor).
#pragma once

#include <cstdint>
#include <deque>
#include <mutex>
#include <opencv2/core.hpp>
#include <vector>

#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::sim {

// Conveyor timeline of the simulated cell. Time advances with the frames: each grabbed frame is one trigger
// interval of travel; a part-present rising edge opens a pass, its falling edge follows the last frame.
// Thread-safe: the acquisition thread grabs while another thread may wait for edges or read the encoder.
class SimLine {
 public:
  explicit SimLine(SimCell& cell, double gap_between_parts_m = 0.35);

  // The next part to arrive at the sensor.
  void enqueue(const PassSpec& pass);
  [[nodiscard]] std::size_t queued() const;
  [[nodiscard]] std::uint64_t passes_started() const;
  // The pass currently (or last) under the sensor.
  [[nodiscard]] PassSpec current_pass() const;

  // Fault injection for tests of the production loop: the camera stops delivering frames while stalled.
  void set_camera_stalled(bool stalled);

  // Device-side calls (used by the Sim* backends below).
  [[nodiscard]] drivers::DeviceStatus next_edge(drivers::EdgeEvent& out);
  [[nodiscard]] drivers::DeviceStatus next_frame(cv::Mat& image, std::int32_t exposure_us, std::int64_t& timestamp_ns);
  void set_output(drivers::Output line, bool active);
  [[nodiscard]] bool output(drivers::Output line) const;
  [[nodiscard]] bool part_present() const;
  [[nodiscard]] std::int64_t encoder_counts() const;
  [[nodiscard]] std::uint64_t trigger_pulses() const;
  void count_trigger_pulse();

 private:
  enum class State { kIdle, kInPass };
  std::int64_t now_ns_locked() const;

  mutable std::mutex mutex_;
  SimCell& cell_;
  double gap_m_;
  std::deque<PassSpec> queue_;
  State state_ = State::kIdle;
  int frame_ = 0;
  bool falling_pending_ = false;
  bool stalled_ = false;
  bool laser_on_ = false;
  bool trigger_level_ = false;
  std::uint64_t trigger_pulses_ = 0;
  std::uint64_t passes_ = 0;
  std::int64_t pass_start_counts_ = 0;  // encoder counts at the current pass's rising edge
  std::int64_t counts_ = 0;
  PassSpec current_;
};

class SimCamera final : public drivers::Camera {
 public:
  SimCamera(SimLine& line, int buffer_count, std::int32_t exposure_us);
  Status start() override;
  void stop() override;
  drivers::DeviceStatus set_exposure_us(std::int32_t exposure_us) override;
  drivers::DeviceStatus grab(drivers::Frame& out, int timeout_ms) override;
  void release(const drivers::Frame& frame) override;

 private:
  SimLine& line_;
  std::vector<cv::Mat> buffers_;
  std::vector<bool> in_use_;
  std::int32_t exposure_us_;
  std::uint64_t sequence_ = 0;
  bool started_ = false;
};

class SimDigitalIo final : public drivers::DigitalIo {
 public:
  explicit SimDigitalIo(SimLine& line) : line_(line) {}
  Status open() override;
  void close() override;
  drivers::DeviceStatus set(drivers::Output line, bool active) override;
  drivers::DeviceStatus pulse(drivers::Output line, std::int32_t width_us) override;
  drivers::DeviceStatus read(drivers::Input line, bool& active) override;
  drivers::DeviceStatus wait_edge(drivers::EdgeEvent& out, int timeout_ms) override;

 private:
  SimLine& line_;
  bool open_ = false;
};

class SimEncoder final : public drivers::Encoder {
 public:
  explicit SimEncoder(SimLine& line) : line_(line) {}
  Status open() override;
  void close() override;
  drivers::DeviceStatus read_counts(std::int64_t& counts) override;

 private:
  SimLine& line_;
  std::int64_t offset_ = 0;
  bool open_ = false;
};

}  // namespace cellsight::sim
