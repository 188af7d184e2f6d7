// Acquisition loop of one pass.
#include "app/acquire.hpp"

namespace cellsight::app {

using drivers::DeviceStatus;

AcquireResult acquire_pass(drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder,
                           algo::ScanBuilder& builder, const AcquireParams& params, AcquireReport& report) {
  report = AcquireReport{};
  drivers::EdgeEvent edge;
  // Skip a stale falling edge; the pass begins at a rising one.
  do {
    const DeviceStatus s = io.wait_edge(edge, params.edge_wait_ms);
    if (s == DeviceStatus::kTimeout) return AcquireResult::kNoPart;
    if (s != DeviceStatus::kOk) return AcquireResult::kIoFault;
  } while (edge.edge != drivers::Edge::kRising);
  report.rising_ns = edge.timestamp_ns;
  std::int64_t start_counts = 0;
  if (encoder.read_counts(start_counts) != DeviceStatus::kOk) return AcquireResult::kIoFault;
  builder.begin_pass(start_counts, params.start_exposure_us);
  if (camera.set_exposure_us(params.start_exposure_us) != DeviceStatus::kOk) return AcquireResult::kCameraFault;

  while (report.frames < params.max_frames) {
    drivers::Frame frame;
    const DeviceStatus grabbed = camera.grab(frame, params.frame_timeout_ms);
    if (grabbed == DeviceStatus::kTimeout) {
      // A finished pass looks like a silent camera: the falling edge tells them apart.
      const DeviceStatus e = io.wait_edge(edge, 0);
      if (e == DeviceStatus::kOk && edge.edge == drivers::Edge::kFalling) {
        report.falling_ns = edge.timestamp_ns;
        return AcquireResult::kOk;
      }
      return AcquireResult::kCameraTimeout;
    }
    if (grabbed != DeviceStatus::kOk) return AcquireResult::kCameraFault;
    std::int64_t counts = 0;
    if (encoder.read_counts(counts) != DeviceStatus::kOk) {
      camera.release(frame);
      return AcquireResult::kIoFault;
    }
    const algo::FrameOutcome outcome =
        builder.add_frame(frame.data, frame.width_px, frame.height_px, frame.stride_bytes, frame.exposure_us, counts);
    camera.release(frame);
    ++report.frames;
    if (outcome.exposure.exposure_us != frame.exposure_us &&
        camera.set_exposure_us(outcome.exposure.exposure_us) != DeviceStatus::kOk) {
      return AcquireResult::kCameraFault;
    }
    const DeviceStatus e = io.wait_edge(edge, 0);
    if (e == DeviceStatus::kOk && edge.edge == drivers::Edge::kFalling) {
      report.falling_ns = edge.timestamp_ns;
      return AcquireResult::kOk;
    }
    if (e != DeviceStatus::kOk && e != DeviceStatus::kTimeout) return AcquireResult::kIoFault;
  }
  return AcquireResult::kTooManyFrames;
}

}  // namespace cellsight::app
