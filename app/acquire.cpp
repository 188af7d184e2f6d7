// Blocking acquisition of one pass: a loop around the production loop's PassAcquirer.
#include "app/acquire.hpp"

#include <chrono>

#include "runtime/pass_acquirer.hpp"

namespace cellsight::app {

using drivers::DeviceStatus;
using runtime::PassAbort;
using runtime::PassStatus;

namespace {

AcquireResult result_of(PassAbort abort) {
  switch (abort) {
    case PassAbort::kCameraTimeout: return AcquireResult::kCameraTimeout;
    case PassAbort::kCamera:
    case PassAbort::kExposure: return AcquireResult::kCameraFault;
    case PassAbort::kTooManyFrames: return AcquireResult::kTooManyFrames;
    case PassAbort::kNone:
    case PassAbort::kEncoderUnreadable:
    case PassAbort::kLaser:
    case PassAbort::kPartPresentInput: return AcquireResult::kIoFault;
  }
  return AcquireResult::kIoFault;
}

}  // namespace

AcquireResult acquire_pass(drivers::Camera& camera, drivers::DigitalIo& io, drivers::Encoder& encoder,
                           algo::ScanBuilder& builder, const AcquireParams& params, AcquireReport& report) {
  using Clock = std::chrono::steady_clock;
  report = AcquireReport{};
  drivers::EdgeEvent edge;
  // Skip a stale falling edge; the pass begins at a rising one.
  do {
    const DeviceStatus s = io.wait_edge(edge, params.edge_wait_ms);
    if (s == DeviceStatus::kTimeout) return AcquireResult::kNoPart;
    if (s != DeviceStatus::kOk) return AcquireResult::kIoFault;
  } while (edge.edge != drivers::Edge::kRising);
  report.rising_ns = edge.timestamp_ns;

  runtime::PassAcquirer acquirer(camera, io, encoder, builder,
                                 runtime::AcquirerParams{params.frame_timeout_ms, params.max_frames,
                                                         params.start_exposure_us, params.poll_slice_ms});
  PassStatus status = acquirer.begin(false, Clock::now());
  while (status == PassStatus::kScanning) status = acquirer.step(Clock::now());
  const bool laser_off = acquirer.end();
  report.frames = acquirer.frames();
  if (status != PassStatus::kComplete) return result_of(acquirer.abort());
  // A laser output that refuses to switch off is a digital I/O fault even though the pass itself is whole: the
  // technician must hear of it now (scan, teach and calibrate stop), not when the next pass finds the laser on.
  if (!laser_off) return AcquireResult::kIoFault;
  report.falling_ns = acquirer.falling_edge().timestamp_ns;
  return AcquireResult::kOk;
}

}  // namespace cellsight::app
