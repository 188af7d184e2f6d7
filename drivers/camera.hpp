// Camera interface (DESIGN.md "drivers/camera"): mono8 frames from a driver-owned buffer pool.
#pragma once

#include <cstdint>

#include "base/result.hpp"
#include "drivers/device.hpp"

namespace cellsight::drivers {

// A borrowed view of one frame. The pixels stay valid until release(); the driver owns the memory.
struct Frame {
  const std::uint8_t* data = nullptr;  // mono8, row-major
  int width_px = 0;
  int height_px = 0;
  int stride_bytes = 0;
  std::uint64_t sequence = 0;      // driver frame counter, +1 per delivered frame
  std::int64_t timestamp_ns = 0;   // CLOCK_MONOTONIC (the simulated cell: simulated time)
  std::int32_t exposure_us = 0;    // exposure this frame was taken with
  std::int32_t buffer_index = -1;  // which pool buffer to hand back with release()
};

class Camera {
 public:
  virtual ~Camera() = default;
  Camera() = default;
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  // Start-up: allocates buffers and starts streaming; the message says which device and why it failed.
  virtual Status start() = 0;
  virtual void stop() = 0;

  // Real-time calls: no allocation, no exceptions.
  virtual DeviceStatus set_exposure_us(std::int32_t exposure_us) = 0;
  // Waits up to timeout_ms for the next frame; on kOk `out` borrows a buffer until release(out).
  virtual DeviceStatus grab(Frame& out, int timeout_ms) = 0;
  virtual void release(const Frame& frame) = 0;
};

}  // namespace cellsight::drivers
