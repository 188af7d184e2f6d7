// Result codes shared by every device interface; returned (never thrown) on the real-time path.
#pragma once

namespace cellsight::drivers {

enum class [[nodiscard]] DeviceStatus{
    kOk = 0,
    kTimeout,     // nothing arrived within the timeout; the device may still be fine
    kIoError,     // the kernel or peer reported an error; counted, retried by the caller's state machine
    kDeviceLost,  // the device vanished (unplugged, ENODEV); reopen needed
    kNotStarted,  // called in the wrong lifecycle state (a programming error upstream)
    kInvalidArgument,
};

constexpr const char* to_string(DeviceStatus status) {
  switch (status) {
    case DeviceStatus::kOk: return "ok";
    case DeviceStatus::kTimeout: return "timeout";
    case DeviceStatus::kIoError: return "I/O error";
    case DeviceStatus::kDeviceLost: return "device lost";
    case DeviceStatus::kNotStarted: return "not started";
    case DeviceStatus::kInvalidArgument: return "invalid argument";
  }
  return "unknown";
}

}  // namespace cellsight::drivers
