// Acquisition of one part pass through the device interfaces (the same code on the simulated and the real cell):
// part-present rising edge -> frames into the scan builder, exposure fed back -> falling edge.
#pragma once

#include <cstdint>

#include "algo/scan_builder.hpp"
#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"

namespace cellsight::app {

enum class [[nodiscard]] AcquireResult : std::uint8_t{
    kOk = 0,
    kNoPart,         // no rising edge within the wait
    kCameraTimeout,  // the camera stopped delivering frames mid-part
    kCameraFault,    // I/O error or the camera vanished
    kIoFault,        // digital I/O or encoder failed
    kTooManyFrames,  // the falling edge never came (photo-eye blocked?)
};

constexpr const char* to_string(AcquireResult r) {
  switch (r) {
    case AcquireResult::kOk: return "ok";
    case AcquireResult::kNoPart: return "no part";
    case AcquireResult::kCameraTimeout: return "camera stopped delivering frames";
    case AcquireResult::kCameraFault: return "camera fault";
    case AcquireResult::kIoFault: return "digital I/O or encoder fault";
    case AcquireResult::kTooManyFrames: return "part-present never fell";
  }
  return "unknown";
}

struct AcquireParams {
  int edge_wait_ms = 1000;  // for the rising edge
  int frame_timeout_ms = 1000;
  int max_frames = 4000;  // more frames than this is a stuck photo-eye
  std::int32_t start_exposure_us = 1500;
  int poll_slice_ms = 10;  // one PassAcquirer::step()
};

struct AcquireReport {
  int frames = 0;
  std::int64_t rising_ns = 0, falling_ns = 0;
};

// Waits for a part, then streams its frames into `builder` until part-present falls; the laser is on from the rising
// edge to the end of the pass. No allocation.
AcquireResult acquire_pass(drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder,
                           algo::ScanBuilder& builder, const AcquireParams& params, AcquireReport& report);

}  // namespace cellsight::app
