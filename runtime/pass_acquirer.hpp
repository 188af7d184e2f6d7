// The one acquisition of a part pass (the same code for `run`, `scan`, `teach` and `calibrate support`, on the
// simulated and the real cell): laser on, start exposure, then frames into the scan builder with the exposure fed
// back, until part-present falls. step() does one slice (at most one frame) and returns, so the production loop
// can serve the PLC between frames; acquire_pass (app/acquire.hpp) is a blocking loop around it.
//
// It is also the only code that takes frames from the camera: frames outside a pass are drained here, and the
// production loop's fault probe asks here whether frames are back.
#pragma once

#include <chrono>
#include <cstdint>

#include "algo/scan_builder.hpp"
#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/modbus/plc_link.hpp"

namespace cellsight::runtime {

struct AcquirerParams {
  // No frame for this long while a part is in front of the camera: the pass is aborted.
  int frame_timeout_ms = 1000;
  int max_frames = 4000;  // more frames than this means a blocked photo-eye: aborted
  std::int32_t start_exposure_us = 1500;
  int poll_slice_ms = 10;  // longest wait of one step()
};

enum class PassStatus : std::uint8_t {
  kScanning,    // the pass goes on: call step() again
  kComplete,    // part-present fell: the scan is in the builder, falling_edge() says when
  kNoPart,      // a software trigger with nothing in front of the sensor: no frame, part-present reads clear
  kAborted,     // abort() says why; the scan in the builder is not to be used
  kNotStarted,  // begin() failed: abort() says why
};

// Why a pass could not start or was aborted.
enum class PassAbort : std::uint8_t {
  kNone = 0,
  kEncoderUnreadable,  // at the start or while the part passes
  kLaser,              // the laser could not be switched on
  kExposure,           // the camera refused an exposure
  kCamera,             // grab failed (I/O error, device gone)
  kCameraTimeout,      // no frame for frame_timeout_ms while the part is in front of the camera
  kPartPresentInput,   // the photo-eye input failed
  kTooManyFrames,      // part-present never fell
};

// The ERROR_CODE of an abort (DESIGN.md register map).
[[nodiscard]] drivers::ErrorCode error_code(PassAbort abort);

class PassAcquirer {
 public:
  using Clock = std::chrono::steady_clock;

  // Borrows the devices and the builder; allocates nothing.
  PassAcquirer(drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder, algo::ScanBuilder& builder,
               const AcquirerParams& params);

  // Starts a pass at `now`: start count of the encoder, laser on, start exposure, an empty scan. kScanning, or
  // kNotStarted with abort() set (the laser may be on: end() switches it off).
  [[nodiscard]] PassStatus begin(bool software_trigger, Clock::time_point now);
  // One slice of the pass: waits at most poll_slice_ms for one frame, adds it, then looks for the falling edge.
  [[nodiscard]] PassStatus step(Clock::time_point now);
  // Laser off. False when the output refused (the caller decides whether that matters).
  [[nodiscard]] bool end();

  [[nodiscard]] PassAbort abort() const { return abort_; }
  [[nodiscard]] const char* abort_reason() const { return abort_reason_; }
  // The camera reported an error (not a timeout): it needs a stop/start before it is used again.
  [[nodiscard]] bool camera_failed() const { return camera_failed_; }
  // What the camera last reported when it failed (for the log and the fault's reason).
  [[nodiscard]] drivers::DeviceStatus camera_error() const { return camera_error_; }
  [[nodiscard]] int frames() const { return frames_; }
  // The last step() added a frame (its index is frames() - 1).
  [[nodiscard]] bool frame_added() const { return frame_added_; }
  // kComplete: the falling edge as read, and when it was seen.
  [[nodiscard]] const drivers::EdgeEvent& falling_edge() const { return falling_; }
  [[nodiscard]] Clock::time_point falling_seen() const { return falling_seen_; }
  // When the last step() came back from the camera (kNoPart: the cycle's start).
  [[nodiscard]] Clock::time_point last_grab_at() const { return grab_at_; }

  // ---- outside a pass ----
  // Takes and drops up to max_frames frames without waiting (frames of a part that is not scanned). Returns how
  // many; -1 when the camera failed (camera_failed() is then set).
  [[nodiscard]] int drain(int max_frames);
  // Waits up to timeout_ms for one frame and drops it: is the camera delivering again?
  [[nodiscard]] drivers::DeviceStatus probe(int timeout_ms);
  void clear_camera_failed() { camera_failed_ = false; }

 private:
  // The one call of Camera::grab for everything above.
  [[nodiscard]] drivers::DeviceStatus grab(drivers::Frame& frame, int timeout_ms);
  [[nodiscard]] PassStatus add_frame(const drivers::Frame& frame, Clock::time_point at);
  [[nodiscard]] PassStatus after_silence(Clock::time_point now);
  [[nodiscard]] PassStatus fail(PassAbort abort, const char* why);

  drivers::Camera& camera_;
  drivers::DigitalIo& io_;
  drivers::Encoder& encoder_;
  algo::ScanBuilder& builder_;
  const AcquirerParams params_;

  bool software_trigger_ = false;
  int frames_ = 0;
  bool frame_added_ = false;
  bool camera_failed_ = false;
  drivers::DeviceStatus camera_error_ = drivers::DeviceStatus::kOk;
  PassAbort abort_ = PassAbort::kNone;
  const char* abort_reason_ = "";
  drivers::EdgeEvent falling_{};
  Clock::time_point falling_seen_{};
  Clock::time_point last_frame_at_{};
  Clock::time_point grab_at_{};
};

}  // namespace cellsight::runtime
