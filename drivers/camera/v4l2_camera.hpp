// Real camera backend: a V4L2 capture device streamed through mmap buffers, behind the SysSeam kernel seam.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "drivers/camera.hpp"
#include "drivers/sys_seam.hpp"

struct v4l2_buffer;  // <linux/videodev2.h>, included by the implementation only

namespace cellsight::drivers {

// Start-up settings (config/cellsight.yaml: section `camera`, the size from `rig.camera`).
struct V4L2CameraConfig {
  std::string device = "/dev/video0";  // camera.device
  int width_px = 1024;                 // rig.camera.width_px: the calibration is only valid at this size
  int height_px = 768;                 // rig.camera.height_px
  int buffer_count = 4;                // camera.buffers: at least kMinBuffers
  int poll_timeout_ms = 200;           // camera.timeout_ms: used when grab() is given a negative timeout
  std::int32_t exposure_us = 0;        // camera.exposure_us: initial exposure; 0 keeps the device's current one
  // External trigger (camera.external_trigger, proposed key): V4L2 has no standard control for it, so it is a
  // driver-private control. trigger_control_id != 0 names it; 0 looks for the first control whose name contains
  // "trigger". The device must offer it when requested, otherwise start() fails (a free-running camera would silently
  // break the pairing of frames and trigger pulses).
  bool external_trigger = false;
  std::uint32_t trigger_control_id = 0;  // camera.trigger_control_id (proposed key)
  // camera.trigger_control_value (proposed key): the value that selects external trigger.
  std::int32_t trigger_control_value = 1;
};

// Counters for the operator and the driver state machine; read them from the grabbing thread.
struct V4L2CameraStats {
  std::uint64_t frames = 0;  // delivered by grab()
  std::uint64_t timeouts = 0;
  std::uint64_t io_errors = 0;       // DQBUF EIO, error-flagged or truncated buffers, starved queue
  std::uint64_t dropped_frames = 0;  // gaps in the kernel's frame sequence (the queue ran empty)
  std::uint64_t release_errors = 0;  // release() of a foreign buffer or a failed QBUF
};

// Streams one V4L2 single-planar capture device. start()/stop() allocate and may log; grab()/release()/
// set_exposure_us() do neither and are called from one thread (the acquisition loop). Frames borrow driver
// buffers until release(); stop() invalidates every borrowed frame.
class V4L2Camera final : public Camera {
 public:
  static constexpr int kMinBuffers = 4;  // fewer starves the stream while one frame is being processed
  static constexpr int kMaxBuffers = 32;
  static constexpr std::int32_t kExposureUnitUs = 100;  // V4L2_CID_EXPOSURE_ABSOLUTE counts 100 µs

  V4L2Camera(SysSeam& sys, V4L2CameraConfig config);
  ~V4L2Camera() override;

  Status start() override;
  void stop() override;

  // Converts to 100 µs units (nearest), clamps to the control's range and step; frames report what was applied.
  DeviceStatus set_exposure_us(std::int32_t exposure_us) override;
  // timeout_ms < 0 uses config.poll_timeout_ms (never an infinite wait).
  DeviceStatus grab(Frame& out, int timeout_ms) override;
  void release(const Frame& frame) override;

  [[nodiscard]] const V4L2CameraStats& stats() const { return stats_; }
  [[nodiscard]] bool started() const { return started_; }
  // True when the device only offered YUYV and grab() converts to mono8 (costs one pass over the frame).
  [[nodiscard]] bool converts_yuyv() const { return yuyv_; }
  [[nodiscard]] int buffer_count() const { return static_cast<int>(buffers_.size()); }
  // Exposure range in µs as the device reports it (0, 0 when the device has no exposure control).
  [[nodiscard]] std::int32_t exposure_min_us() const { return units_to_us(exposure_min_); }
  [[nodiscard]] std::int32_t exposure_max_us() const { return units_to_us(exposure_max_); }

 private:
  struct Buffer {
    void* mapping = nullptr;
    std::size_t length = 0;
    bool queued = false;  // owned by the kernel (between QBUF and DQBUF)
  };
  // One applied exposure and when it took effect, so a frame captured before a change reports the old value.
  struct ExposureChange {
    std::int64_t since_ns = 0;
    std::int32_t exposure_us = 0;
  };
  static constexpr std::size_t kExposureHistory = 8;

  [[nodiscard]] static std::int32_t units_to_us(std::int32_t units);
  [[nodiscard]] std::int32_t units_for_us(std::int32_t exposure_us) const;
  Status open_device();
  Status negotiate_format();
  Status setup_exposure();
  Status setup_trigger();
  Status allocate_buffers();
  Status queue_all_and_stream();
  void teardown();

  [[nodiscard]] DeviceStatus requeue(std::uint32_t index);
  // grab()'s steps: wait until the device is readable, take a filled buffer from the kernel (an empty one that came
  // with EIO goes back), count the frames the kernel dropped before it, convert to mono when the format is YUYV.
  [[nodiscard]] DeviceStatus wait_for_frame(int timeout_ms, short& revents);
  [[nodiscard]] DeviceStatus dequeue(short revents, v4l2_buffer& buffer);
  [[nodiscard]] DeviceStatus hand_back_empty(std::uint32_t index);
  void count_dropped_frames(std::uint32_t kernel_sequence);
  [[nodiscard]] const std::uint8_t* mono_pixels(std::uint32_t index, int& stride_bytes);
  [[nodiscard]] DeviceStatus lose_device();
  void record_exposure(std::int32_t exposure_us, std::int64_t since_ns);
  [[nodiscard]] std::int32_t exposure_at(std::int64_t timestamp_ns) const;
  [[nodiscard]] std::string where() const;

  SysSeam& sys_;
  V4L2CameraConfig config_;
  int fd_ = -1;
  bool started_ = false;
  bool streaming_ = false;
  bool buffers_requested_ = false;
  bool lost_ = false;
  bool yuyv_ = false;
  std::uint32_t bytes_per_line_ = 0;
  std::uint32_t image_bytes_ = 0;  // what a complete frame occupies in a driver buffer
  std::vector<Buffer> buffers_;
  std::vector<std::uint8_t> mono_;  // YUYV only: one converted width x height image per driver buffer
  int queued_count_ = 0;
  bool has_exposure_ = false;
  std::int32_t exposure_min_ = 0;  // control units (100 µs)
  std::int32_t exposure_max_ = 0;
  std::int32_t exposure_step_ = 1;
  std::array<ExposureChange, kExposureHistory> exposure_history_{};
  std::size_t exposure_history_count_ = 0;  // valid entries, newest at (head - 1)
  std::size_t exposure_history_head_ = 0;
  bool have_sequence_ = false;
  std::uint32_t last_kernel_sequence_ = 0;
  std::uint64_t next_sequence_ = 0;
  V4L2CameraStats stats_;
};

}  // namespace cellsight::drivers
