// The simulated cell's devices: camera, digital I/O and encoder behind the same interfaces as the real drivers,
// all driven by one SimLine (the conveyor bringing parts past the sensor).
#pragma once

#include <chrono>
#include <cstdint>
#include <deque>
#include <mutex>
#include <opencv2/core.hpp>
#include <utility>
#include <vector>

#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/edge_debounce.hpp"
#include "drivers/sim/frame_memo.hpp"
#include "drivers/sim/sim_cell.hpp"

namespace cellsight::sim {

// Faults of one simulated pass, for the soak and the loop's tests (`run --sim --sim-faults`); a pass without any is
// the default. Durations are wall-clock time, as the production loop's device timeouts are.
struct PassFaults {
  // The camera delivers no frame for camera_stall_ms from this frame of the pass on (-1: no stall).
  int camera_stall_frame = -1;
  int camera_stall_ms = 0;
  // The encoder cannot be read (I/O error) for encoder_glitch_ms once this frame has been taken (-1: no glitch).
  int encoder_glitch_frame = -1;
  int encoder_glitch_ms = 0;
  // Photo-eye chatter: this many extra raw edge pairs right after the part-present rising and falling edges,
  // bounce_spacing_us apart (a debounce window longer than the burst filters them).
  int bounce_pairs = 0;
  int bounce_spacing_us = 300;

  [[nodiscard]] bool any() const { return camera_stall_frame >= 0 || encoder_glitch_frame >= 0 || bounce_pairs > 0; }
};

// Conveyor timeline of the simulated cell. Time advances with the frames: each grabbed frame is one trigger
// interval of travel; a part-present rising edge opens a pass, its falling edge follows the last frame.
// Thread-safe: the acquisition thread grabs while another thread may wait for edges or read the encoder.
class SimLine {
 public:
  explicit SimLine(SimCell& cell, double gap_between_parts_m = 0.35);

  // The next part to arrive at the sensor, with the faults its pass is to suffer. memo_slot >= 0: its frames are
  // kept in (and replayed from) that slot of the frame memo; give the same pass the same slot every time.
  void enqueue(const PassSpec& pass, const PassFaults& faults = {}, std::int64_t memo_slot = -1);
  // Before the first pass: room for `slots` passes' frames (see FrameMemo).
  [[nodiscard]] Status enable_frame_memo(std::size_t slots);
  [[nodiscard]] const FrameMemo& frame_memo() const { return memo_; }
  [[nodiscard]] std::size_t queued() const;
  [[nodiscard]] std::uint64_t passes_started() const;
  // The pass currently (or last) under the sensor.
  [[nodiscard]] PassSpec current_pass() const;

  // Fault injection for tests of the production loop: the camera stops delivering frames while stalled.
  void set_camera_stalled(bool stalled);

  // Device-side calls (used by the Sim* backends below).
  // Raw part-present edges (bounces included), stamped in simulated time.
  [[nodiscard]] drivers::DeviceStatus next_edge(drivers::EdgeEvent& out);
  [[nodiscard]] drivers::DeviceStatus next_frame(cv::Mat& image, std::int32_t exposure_us, std::int64_t& timestamp_ns);
  void set_output(drivers::Output line, bool active);
  [[nodiscard]] bool output(drivers::Output line) const;
  [[nodiscard]] bool part_present() const;
  [[nodiscard]] std::int64_t encoder_counts() const;
  // False during an injected encoder glitch.
  [[nodiscard]] bool encoder_readable() const;
  // Simulated time (the conveyor's travel at its nominal speed).
  [[nodiscard]] std::int64_t now_ns() const;
  [[nodiscard]] std::uint64_t trigger_pulses() const;
  void count_trigger_pulse();

 private:
  enum class State { kIdle, kInPass };
  using WallClock = std::chrono::steady_clock;
  std::int64_t now_ns_locked() const;
  void queue_bounces_locked(bool after_level, std::int64_t edge_ns);

  mutable std::mutex mutex_;
  SimCell& cell_;
  double gap_m_;
  struct Queued {
    PassSpec pass;
    PassFaults faults;
    std::int64_t memo_slot = -1;
  };
  std::deque<Queued> queue_;
  PassFaults faults_;            // of the current pass
  std::int64_t memo_slot_ = -1;  // of the current pass
  bool scene_ready_ = false;     // cell_ holds the current pass's scene
  FrameMemo memo_;
  std::deque<drivers::EdgeEvent> bounces_;  // raw edges still to come
  WallClock::time_point stall_until_{};     // injected camera stall: no frames before this
  bool stall_started_ = false;
  WallClock::time_point encoder_ok_from_{};  // injected encoder glitch: unreadable before this
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

// Part-present edges go through the same bounce filter as the libgpiod backend's (gpio.debounce_us), on the
// line's simulated clock.
class SimDigitalIo final : public drivers::DigitalIo {
 public:
  explicit SimDigitalIo(SimLine& line, std::int32_t debounce_us = 0)
      : line_(line), debounce_(static_cast<std::int64_t>(debounce_us) * 1000) {}
  Status open() override;
  void close() override;
  drivers::DeviceStatus set(drivers::Output line, bool active) override;
  drivers::DeviceStatus pulse(drivers::Output line, std::int32_t width_us) override;
  drivers::DeviceStatus read(drivers::Input line, bool& active) override;
  drivers::DeviceStatus wait_edge(drivers::EdgeEvent& out, int timeout_ms) override;
  [[nodiscard]] std::uint64_t bounces() const { return bounces_; }  // raw edges the filter dropped

 private:
  SimLine& line_;
  drivers::EdgeDebounce debounce_;
  std::uint64_t bounces_ = 0;
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
