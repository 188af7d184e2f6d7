// Builds the cell's devices from the configuration: the simulated cell's, or the real V4L2 camera and libgpiod
// I/O and encoder (camera.backend, gpio.backend). The same interfaces either way.
#pragma once

#include <memory>

#include "algo/result.hpp"
#include "app/config.hpp"
#include "drivers/camera.hpp"
#include "drivers/digital_io.hpp"
#include "drivers/sim/sim_devices.hpp"

namespace cellsight::app {

struct Devices {
  // Owned seams of the real backends; declared first so they outlive the devices that use them.
  std::shared_ptr<void> seams;
  std::unique_ptr<drivers::Camera> camera;
  std::unique_ptr<drivers::DigitalIo> io;
  std::unique_ptr<drivers::Encoder> encoder;

  // Starts all three; the message names the device and the config key when one is missing.
  [[nodiscard]] Status open();
  void close();
};

// `line` is required when a backend is "sim" (or force_sim is set) and ignored otherwise.
[[nodiscard]] Expected<Devices> make_devices(const Config& config, sim::SimLine* line, bool force_sim);

}  // namespace cellsight::app
