// One part pass: frames into the scan builder with the exposure fed back, one non-blocking slice per step().
#include "runtime/pass_acquirer.hpp"

#include <thread>

namespace cellsight::runtime {

using drivers::DeviceStatus;
using drivers::ErrorCode;

drivers::ErrorCode error_code(PassAbort abort) {
  switch (abort) {
    case PassAbort::kNone: return ErrorCode::kNone;
    case PassAbort::kEncoderUnreadable: return ErrorCode::kEncoderFault;
    case PassAbort::kLaser:
    case PassAbort::kPartPresentInput:
    case PassAbort::kTooManyFrames: return ErrorCode::kIoFault;
    case PassAbort::kExposure:
    case PassAbort::kCamera: return ErrorCode::kCameraFault;
    case PassAbort::kCameraTimeout: return ErrorCode::kCameraTimeout;
  }
  return ErrorCode::kInternal;
}

PassAcquirer::PassAcquirer(drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder,
                           algo::ScanBuilder& builder, const AcquirerParams& params)
    : camera_(camera), io_(io), encoder_(encoder), builder_(builder), params_(params) {}

PassStatus PassAcquirer::fail(PassAbort abort, const char* why) {
  abort_ = abort;
  abort_reason_ = why;
  if (abort == PassAbort::kCamera || abort == PassAbort::kExposure) camera_failed_ = true;
  return PassStatus::kAborted;
}

DeviceStatus PassAcquirer::grab(drivers::Frame& frame, int timeout_ms) {
  const DeviceStatus status = camera_.grab(frame, timeout_ms);
  if (status != DeviceStatus::kOk && status != DeviceStatus::kTimeout) {
    camera_failed_ = true;
    camera_error_ = status;
  }
  return status;
}

PassStatus PassAcquirer::begin(bool software_trigger, Clock::time_point now) {
  software_trigger_ = software_trigger;
  frames_ = 0;
  frame_added_ = false;
  abort_ = PassAbort::kNone;
  abort_reason_ = "";
  last_frame_at_ = now;
  std::int64_t start_counts = 0;
  if (encoder_.read_counts(start_counts) != DeviceStatus::kOk) {
    (void)fail(PassAbort::kEncoderUnreadable, "encoder unreadable at the start of a pass");
    return PassStatus::kNotStarted;
  }
  if (io_.set(drivers::Output::kLaserEnable, true) != DeviceStatus::kOk) {
    (void)fail(PassAbort::kLaser, "cannot switch the laser on");
    return PassStatus::kNotStarted;
  }
  if (camera_.set_exposure_us(params_.start_exposure_us) != DeviceStatus::kOk) {
    (void)fail(PassAbort::kExposure, "cannot set the start exposure");
    return PassStatus::kNotStarted;
  }
  builder_.begin_pass(start_counts, params_.start_exposure_us);
  return PassStatus::kScanning;
}

PassStatus PassAcquirer::step(Clock::time_point now) {
  frame_added_ = false;
  drivers::Frame frame;
  const DeviceStatus grabbed = grab(frame, params_.poll_slice_ms);
  grab_at_ = Clock::now();
  if (grabbed == DeviceStatus::kOk) {
    if (const PassStatus s = add_frame(frame, grab_at_); s != PassStatus::kScanning) return s;
  } else if (grabbed != DeviceStatus::kTimeout) {
    return fail(PassAbort::kCamera, drivers::to_string(grabbed));
  }
  const DeviceStatus edge_status = io_.wait_edge(falling_, 0);
  if (edge_status == DeviceStatus::kOk && falling_.edge == drivers::Edge::kFalling) {
    falling_seen_ = Clock::now();
    return PassStatus::kComplete;
  }
  if (edge_status != DeviceStatus::kOk && edge_status != DeviceStatus::kTimeout) {
    return fail(PassAbort::kPartPresentInput, "part-present input failed");
  }
  if (grabbed != DeviceStatus::kTimeout) return PassStatus::kScanning;
  return after_silence(now);
}

PassStatus PassAcquirer::add_frame(const drivers::Frame& frame, Clock::time_point at) {
  std::int64_t counts = 0;
  if (encoder_.read_counts(counts) != DeviceStatus::kOk) {
    camera_.release(frame);
    return fail(PassAbort::kEncoderUnreadable, "encoder unreadable while a part passes");
  }
  const algo::FrameOutcome outcome =
      builder_.add_frame(frame.data, frame.width_px, frame.height_px, frame.stride_bytes, frame.exposure_us, counts);
  camera_.release(frame);
  last_frame_at_ = at;
  frame_added_ = true;
  ++frames_;
  if (outcome.exposure.exposure_us != frame.exposure_us &&
      camera_.set_exposure_us(outcome.exposure.exposure_us) != DeviceStatus::kOk) {
    return fail(PassAbort::kExposure, "cannot set the exposure");
  }
  if (frames_ > params_.max_frames)
    return fail(PassAbort::kTooManyFrames, "part-present never fell (photo-eye blocked?)");
  return PassStatus::kScanning;
}

// No frame in this slice and no falling edge: a camera that stopped, or a software trigger with no part at all.
PassStatus PassAcquirer::after_silence(Clock::time_point now) {
  if (grab_at_ - last_frame_at_ >= std::chrono::milliseconds(params_.frame_timeout_ms)) {
    bool present = true;
    const DeviceStatus read = io_.read(drivers::Input::kPartPresent, present);
    if (frames_ == 0 && software_trigger_ && read == DeviceStatus::kOk && !present) return PassStatus::kNoPart;
    return fail(PassAbort::kCameraTimeout, "no frame while a part is in front of the camera");
  }
  // A camera that does not wait (the simulated cell) must not make the caller's loop a busy loop.
  const Clock::time_point until = now + std::chrono::milliseconds(params_.poll_slice_ms);
  if (Clock::now() < until) std::this_thread::sleep_until(until);
  return PassStatus::kScanning;
}

bool PassAcquirer::end() {
  return io_.set(drivers::Output::kLaserEnable, false) == DeviceStatus::kOk;
}

int PassAcquirer::drain(int max_frames) {
  int drained = 0;
  while (drained < max_frames) {
    drivers::Frame frame;
    const DeviceStatus status = grab(frame, 0);
    if (status == DeviceStatus::kOk) {
      camera_.release(frame);
      ++drained;
      continue;
    }
    if (status != DeviceStatus::kTimeout) return -1;
    break;
  }
  return drained;
}

DeviceStatus PassAcquirer::probe(int timeout_ms) {
  drivers::Frame frame;
  const DeviceStatus status = grab(frame, timeout_ms);
  if (status == DeviceStatus::kOk) camera_.release(frame);
  return status;
}

}  // namespace cellsight::runtime
