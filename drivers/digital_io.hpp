// Digital I/O and encoder interfaces (DESIGN.md "GPIO lines"): laser, trigger, part-present, conveyor encoder.
#pragma once

#include <cstdint>

#include "base/result.hpp"
#include "drivers/device.hpp"

namespace cellsight::drivers {

enum class Output : std::uint8_t { kLaserEnable = 0, kCameraTrigger = 1 };
enum class Input : std::uint8_t { kPartPresent = 0 };
enum class Edge : std::uint8_t { kRising, kFalling };

struct EdgeEvent {
  Input input = Input::kPartPresent;
  Edge edge = Edge::kRising;
  std::int64_t timestamp_ns = 0;  // CLOCK_MONOTONIC (simulated time in the simulated cell)
};

class DigitalIo {
 public:
  virtual ~DigitalIo() = default;
  DigitalIo() = default;
  DigitalIo(const DigitalIo&) = delete;
  DigitalIo& operator=(const DigitalIo&) = delete;

  virtual Status open() = 0;
  virtual void close() = 0;

  virtual DeviceStatus set(Output line, bool active) = 0;
  // Drives the line active for width_us, then inactive (camera trigger).
  virtual DeviceStatus pulse(Output line, std::int32_t width_us) = 0;
  virtual DeviceStatus read(Input line, bool& active) = 0;
  // Waits up to timeout_ms for a debounced edge on any input.
  virtual DeviceStatus wait_edge(EdgeEvent& out, int timeout_ms) = 0;
};

class Encoder {
 public:
  virtual ~Encoder() = default;
  Encoder() = default;
  Encoder(const Encoder&) = delete;
  Encoder& operator=(const Encoder&) = delete;

  virtual Status open() = 0;
  virtual void close() = 0;
  // Conveyor position in counts since open(); monotonic while the conveyor runs forward.
  virtual DeviceStatus read_counts(std::int64_t& counts) = 0;
};

}  // namespace cellsight::drivers
