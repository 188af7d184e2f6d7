// Real digital I/O backend on libgpiod v1: laser enable and camera trigger outputs, debounced part-present input.
#pragma once

#include <cstdint>
#include <string>

#include "drivers/digital_io.hpp"
#include "drivers/edge_debounce.hpp"
#include "drivers/gpio/gpiod_api.hpp"

namespace cellsight::drivers {

// One wired line. Active-low is applied here, not through GPIOD_LINE_REQUEST_FLAG_ACTIVE_LOW, so that the seam
// (and its fake) only ever sees physical pin levels and one place does the inversion for values and edges alike.
struct GpioLineConfig {
  int offset = -1;          // line offset on the chip (`gpioinfo`); -1: not wired
  bool active_low = false;  // active when the pin is low (sinking photo-eye, relay to ground)
};

// Start-up settings (config/cellsight.yaml, section `gpio`).
struct GpiodIoConfig {
  std::string chip = "gpiochip0";       // gpio.chip: a name under /dev, or a path
  GpioLineConfig laser_enable;          // gpio.laser_line, gpio.laser_active_low (proposed key)
  GpioLineConfig camera_trigger;        // gpio.trigger_line, gpio.trigger_active_low (proposed key)
  GpioLineConfig part_present;          // gpio.part_present_line, gpio.part_present_active_low
  std::int32_t trigger_pulse_us = 100;  // gpio.trigger_pulse_us: pulse() width when given width_us <= 0
  // gpio.debounce_us: an edge closer than this to the previous accepted edge is contact or photo-eye bounce.
  std::int32_t debounce_us = 5'000;
  std::string consumer = "cellsight";  // shown by `gpioinfo`
};

struct GpiodIoStats {
  std::uint64_t edges = 0;          // debounced edges delivered by wait_edge()
  std::uint64_t bounces = 0;        // raw edges ignored by the debounce
  std::uint64_t settled_edges = 0;  // edges delivered because the pin settled away from the debounced state
  std::uint64_t io_errors = 0;
};

// DigitalIo on one GPIO chip. open()/close() allocate; set/pulse/read/wait_edge do not and are called from one
// thread. Outputs start inactive at open() and are driven inactive again at close(), so the laser is never left on.
class GpiodIo final : public DigitalIo {
 public:
  static constexpr std::int32_t kMaxPulseUs = 1'000'000;
  static constexpr std::int32_t kMaxDebounceUs = 1'000'000;

  GpiodIo(GpiodApi& api, GpiodIoConfig config);
  ~GpiodIo() override;

  Status open() override;
  void close() override;

  DeviceStatus set(Output line, bool active) override;
  // Blocks for the pulse width (clock_nanosleep on an absolute deadline). width_us <= 0 uses trigger_pulse_us.
  DeviceStatus pulse(Output line, std::int32_t width_us) override;
  // The pin's present level (not debounced), active-low applied.
  DeviceStatus read(Input line, bool& active) override;
  // Debounced: the first edge after a quiet debounce_us is delivered at once, later bounces are ignored. When the
  // bounces leave the pin at the other level (a pulse shorter than the debounce), that level is delivered as an
  // edge once debounce_us has passed since the accepted edge, stamped with the time the pin got there.
  DeviceStatus wait_edge(EdgeEvent& out, int timeout_ms) override;

  [[nodiscard]] const GpiodIoStats& stats() const { return stats_; }
  [[nodiscard]] bool is_open() const { return open_; }

 private:
  struct OutputLine {
    gpiod_line* line = nullptr;
    bool active_low = false;
  };
  struct InputLine {
    gpiod_line* line = nullptr;
    bool active_low = false;
    EdgeDebounce debounce;  // active-high logic
  };

  [[nodiscard]] OutputLine* output(Output line);
  [[nodiscard]] DeviceStatus fail(int result);
  void release_lines();

  GpiodApi& api_;
  GpiodIoConfig config_;
  GpiodChip chip_;
  OutputLine laser_;
  OutputLine trigger_;
  InputLine part_present_;
  bool open_ = false;
  bool lost_ = false;
  GpiodIoStats stats_;
};

}  // namespace cellsight::drivers
