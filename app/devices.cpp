// Device factory: configuration -> backends.
#include "app/devices.hpp"

#include "drivers/camera/v4l2_camera.hpp"
#include "drivers/gpio/gpiod_api.hpp"
#include "drivers/gpio/gpiod_encoder.hpp"
#include "drivers/gpio/gpiod_io.hpp"
#include "drivers/sys_seam.hpp"

namespace cellsight::app {

namespace {
struct RealSeams {
  drivers::RealSys sys;
  drivers::RealGpiodApi gpiod;
};
}  // namespace

Status Devices::open() {
  if (auto ok = io->open(); !ok) return ok;
  if (auto ok = encoder->open(); !ok) {
    io->close();
    return ok;
  }
  if (auto ok = camera->start(); !ok) {
    encoder->close();
    io->close();
    return ok;
  }
  return {};
}

void Devices::close() {
  if (camera) camera->stop();
  if (encoder) encoder->close();
  if (io) io->close();
}

Expected<Devices> make_devices(const Config& config, sim::SimLine* line, bool force_sim) {
  Devices d;
  const bool sim_camera = force_sim || config.camera.backend == "sim";
  const bool sim_gpio = force_sim || config.gpio.backend == "sim";
  if ((sim_camera || sim_gpio) && line == nullptr)
    return make_error("the simulated cell is not set up (internal error)");
  auto seams = std::make_shared<RealSeams>();
  if (sim_camera) {
    d.camera = std::make_unique<sim::SimCamera>(*line, config.camera.buffers,
                                                static_cast<std::int32_t>(config.camera.exposure_us));
  } else {
    drivers::V4L2CameraConfig c;
    c.device = config.camera.device;
    c.width_px = config.rig.camera.intrinsics.width_px;
    c.height_px = config.rig.camera.intrinsics.height_px;
    c.buffer_count = config.camera.buffers;
    c.poll_timeout_ms = config.camera.timeout_ms;
    c.exposure_us = static_cast<std::int32_t>(config.camera.exposure_us + 0.5);
    c.external_trigger = config.camera.external_trigger;
    c.trigger_control_id = static_cast<std::uint32_t>(config.camera.trigger_control_id);
    c.trigger_control_value = config.camera.trigger_control_value;
    d.camera = std::make_unique<drivers::V4L2Camera>(seams->sys, c);
  }
  if (sim_gpio) {
    d.io = std::make_unique<sim::SimDigitalIo>(*line, config.gpio.debounce_us);
    d.encoder = std::make_unique<sim::SimEncoder>(*line);
  } else {
    drivers::GpiodIoConfig io;
    io.chip = config.gpio.chip;
    io.laser_enable = {config.gpio.laser_line, config.gpio.laser_active_low};
    io.camera_trigger = {config.gpio.trigger_line, config.gpio.trigger_active_low};
    io.part_present = {config.gpio.part_present_line, config.gpio.part_present_active_low};
    io.trigger_pulse_us = config.gpio.trigger_pulse_us;
    io.debounce_us = config.gpio.debounce_us;
    d.io = std::make_unique<drivers::GpiodIo>(seams->gpiod, io);
    drivers::GpiodEncoderConfig enc;
    enc.chip = config.gpio.chip;
    enc.line_a = config.gpio.encoder_a_line;
    enc.line_b = config.gpio.encoder_b_line;
    enc.reverse = config.gpio.encoder_reverse;
    d.encoder = std::make_unique<drivers::GpiodEncoder>(seams->gpiod, enc);
  }
  d.seams = seams;
  return d;
}

}  // namespace cellsight::app
