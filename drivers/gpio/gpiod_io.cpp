// GpiodIo: outputs with active-low, trigger pulses on an absolute deadline, and a debounced edge input.
#include "drivers/gpio/gpiod_io.hpp"

#include <algorithm>
#include <cerrno>
#include <utility>

#include "drivers/log.hpp"
#include "drivers/sys_seam.hpp"

namespace cellsight::drivers {
namespace {

constexpr const char* kComponent = "gpio";
constexpr const char* kConfigHint = "config/cellsight.yaml";
constexpr std::int64_t kNsPerUs = 1'000;
constexpr std::int64_t kNsPerMs = 1'000'000;

int physical_level(bool active, bool active_low) {
  return active != active_low ? 1 : 0;
}

}  // namespace

GpiodIo::GpiodIo(GpiodApi& api, GpiodIoConfig config) : api_(api), config_(std::move(config)) {}

GpiodIo::~GpiodIo() {
  close();
}

Status GpiodIo::open() {
  if (open_) return make_error("gpio: " + config_.chip + " is already open");
  if (config_.trigger_pulse_us <= 0 || config_.trigger_pulse_us > kMaxPulseUs || config_.debounce_us < 0 ||
      config_.debounce_us > kMaxDebounceUs) {
    return make_error("gpio: gpio.trigger_pulse_us must be 1.." + std::to_string(kMaxPulseUs) +
                      " and gpio.debounce_us 0.." + std::to_string(kMaxDebounceUs) + " (" + kConfigHint + ")");
  }
  const int offsets[] = {config_.laser_enable.offset, config_.camera_trigger.offset, config_.part_present.offset};
  if (std::all_of(std::begin(offsets), std::end(offsets), [](int offset) { return offset < 0; })) {
    return make_error(std::string("gpio: none of gpio.laser_line, gpio.trigger_line, "
                                  "gpio.part_present_line is set in ") +
                      kConfigHint);
  }
  for (std::size_t i = 0; i < std::size(offsets); ++i) {
    for (std::size_t j = i + 1; j < std::size(offsets); ++j) {
      if (offsets[i] >= 0 && offsets[i] == offsets[j]) {
        return make_error("gpio: line " + std::to_string(offsets[i]) +
                          " is configured twice among "
                          "gpio.laser_line, gpio.trigger_line and gpio.part_present_line (" +
                          kConfigHint + ")");
      }
    }
  }
  lost_ = false;
  stats_ = {};

  ScopeExit undo([this] { release_lines(); });
  Expected<GpiodChip> chip = open_gpio_chip(api_, config_.chip);
  if (!chip.ok()) return chip.error();
  chip_ = std::move(chip).value();

  struct Wanted {
    const GpioLineConfig& config;
    OutputLine& line;
    const char* key;
  };
  const Wanted outputs[] = {{config_.laser_enable, laser_, "gpio.laser_line"},
                            {config_.camera_trigger, trigger_, "gpio.trigger_line"}};
  for (const Wanted& wanted : outputs) {
    if (wanted.config.offset < 0) continue;
    // Requested at the inactive level: the laser must not flash on while the cell starts.
    Expected<gpiod_line*> line =
        request_gpio_output(api_, chip_, config_.chip, wanted.config.offset, wanted.key, config_.consumer.c_str(),
                            physical_level(false, wanted.config.active_low));
    if (!line.ok()) return line.error();
    wanted.line.line = *line;
    wanted.line.active_low = wanted.config.active_low;
  }

  if (config_.part_present.offset >= 0) {
    Expected<gpiod_line*> line = request_gpio_edges(api_, chip_, config_.chip, config_.part_present.offset,
                                                    "gpio.part_present_line", config_.consumer.c_str());
    if (!line.ok()) return line.error();
    part_present_ = InputLine{};
    part_present_.line = *line;
    part_present_.active_low = config_.part_present.active_low;
    int level = api_.line_get_value(part_present_.line);
    if (level < 0) {
      return make_error("gpio: cannot read line " + std::to_string(config_.part_present.offset) + " of " +
                        config_.chip + " (gpio.part_present_line): " + errno_text(-level));
    }
    part_present_.debounce = EdgeDebounce(config_.debounce_us * kNsPerUs);
    part_present_.debounce.reset((level != 0) != part_present_.active_low, gpio_now_ns());
  }
  undo.dismiss();
  open_ = true;
  CS_LOG_INFO(kComponent, "%s: laser %d%s, trigger %d%s, part-present %d%s, pulse %d us, debounce %d us",
              config_.chip.c_str(), config_.laser_enable.offset, config_.laser_enable.active_low ? " (active low)" : "",
              config_.camera_trigger.offset, config_.camera_trigger.active_low ? " (active low)" : "",
              config_.part_present.offset, config_.part_present.active_low ? " (active low)" : "",
              config_.trigger_pulse_us, config_.debounce_us);
  return {};
}

void GpiodIo::release_lines() {
  for (OutputLine* output_line : {&laser_, &trigger_}) {
    if (output_line->line != nullptr) api_.line_release(output_line->line);
    *output_line = OutputLine{};
  }
  if (part_present_.line != nullptr) api_.line_release(part_present_.line);
  part_present_ = InputLine{};
  chip_.reset();
}

void GpiodIo::close() {
  if (open_ && !lost_) {
    // Leave the cell safe: laser off, trigger idle, whatever state the caller left them in.
    for (const OutputLine* output_line : {&laser_, &trigger_}) {
      if (output_line->line != nullptr) {
        (void)api_.line_set_value(output_line->line, physical_level(false, output_line->active_low));
      }
    }
  }
  release_lines();
  open_ = false;
}

GpiodIo::OutputLine* GpiodIo::output(Output line) {
  switch (line) {
    case Output::kLaserEnable: return &laser_;
    case Output::kCameraTrigger: return &trigger_;
  }
  return nullptr;
}

DeviceStatus GpiodIo::fail(int result) {
  if (result == -ENODEV) {
    if (!lost_) CS_LOG_ERROR(kComponent, "%s vanished (ENODEV); reopen needed", config_.chip.c_str());
    lost_ = true;
    return DeviceStatus::kDeviceLost;
  }
  ++stats_.io_errors;
  return DeviceStatus::kIoError;
}

DeviceStatus GpiodIo::set(Output line, bool active) {
  if (!open_) return DeviceStatus::kNotStarted;
  if (lost_) return DeviceStatus::kDeviceLost;
  OutputLine* target = output(line);
  if (target == nullptr || target->line == nullptr) return DeviceStatus::kInvalidArgument;
  int result = api_.line_set_value(target->line, physical_level(active, target->active_low));
  return result < 0 ? fail(result) : DeviceStatus::kOk;
}

DeviceStatus GpiodIo::pulse(Output line, std::int32_t width_us) {
  if (width_us <= 0) width_us = config_.trigger_pulse_us;
  if (width_us > kMaxPulseUs) return DeviceStatus::kInvalidArgument;
  if (DeviceStatus status = set(line, true); status != DeviceStatus::kOk) return status;
  // Absolute deadline: a signal interrupting the sleep must not stretch the pulse.
  const timespec deadline = to_timespec(gpio_now_ns() + width_us * kNsPerUs);
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &deadline, nullptr) == EINTR) {
  }
  return set(line, false);
}

DeviceStatus GpiodIo::read(Input line, bool& active) {
  if (!open_) return DeviceStatus::kNotStarted;
  if (lost_) return DeviceStatus::kDeviceLost;
  if (line != Input::kPartPresent || part_present_.line == nullptr) return DeviceStatus::kInvalidArgument;
  int level = api_.line_get_value(part_present_.line);
  if (level < 0) return fail(level);
  active = (level != 0) != part_present_.active_low;
  return DeviceStatus::kOk;
}

DeviceStatus GpiodIo::wait_edge(EdgeEvent& out, int timeout_ms) {
  if (!open_) return DeviceStatus::kNotStarted;
  if (lost_) return DeviceStatus::kDeviceLost;
  InputLine& input = part_present_;
  if (input.line == nullptr) return DeviceStatus::kInvalidArgument;
  const std::int64_t deadline_ns = gpio_now_ns() + std::max(0, timeout_ms) * kNsPerMs;

  auto deliver = [&](bool level, std::int64_t timestamp_ns) {
    out.input = Input::kPartPresent;
    out.edge = level ? Edge::kRising : Edge::kFalling;
    out.timestamp_ns = timestamp_ns;
    ++stats_.edges;
    return DeviceStatus::kOk;
  };

  for (;;) {
    const std::int64_t now_ns = gpio_now_ns();
    // Bounces were ignored but left the pin at the other level: once the debounce window has passed, that level
    // is the truth (a part shorter than the window must still end its pass).
    const bool unsettled = input.debounce.unsettled();
    const std::int64_t settle_ns = input.debounce.settle_at_ns();
    if (unsettled && now_ns >= settle_ns) {
      ++stats_.settled_edges;
      const std::int64_t since_ns = input.debounce.settle();
      return deliver(input.debounce.state(), since_ns);
    }
    const std::int64_t until_ns = unsettled ? std::min(deadline_ns, settle_ns) : deadline_ns;
    const timespec timeout = to_timespec(std::max<std::int64_t>(0, until_ns - now_ns));
    std::uint32_t ready = 0;
    int result = api_.line_event_wait(&input.line, 1, timeout, ready);
    if (result == -EINTR) continue;
    if (result < 0) return fail(result);
    if (result == 0) {
      if (unsettled && settle_ns <= deadline_ns) continue;  // the settle point has come: deliver it above
      return DeviceStatus::kTimeout;
    }
    gpiod_line_event event{};
    if (result = api_.line_event_read(input.line, event); result < 0) return fail(result);
    const std::int64_t timestamp_ns = to_ns(event.ts);
    const bool level = (event.event_type == GPIOD_LINE_EVENT_RISING_EDGE) != input.active_low;
    if (!input.debounce.on_edge(level, timestamp_ns)) {
      ++stats_.bounces;
      continue;
    }
    return deliver(level, timestamp_ns);
  }
}

}  // namespace cellsight::drivers
