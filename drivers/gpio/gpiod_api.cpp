// libgpiod v1 behind GpiodApi, plus the start-up helpers that turn failures into messages for the technician.
#include "drivers/gpio/gpiod_api.hpp"

#include <cerrno>
#include <cstring>

#include "drivers/sys_seam.hpp"

namespace cellsight::drivers {
namespace {

constexpr const char* kConfigHint = "config/cellsight.yaml";

// libgpiod reports -1 + errno; a library path that forgets errno must still read as a failure.
int failed() {
  return errno != 0 ? -errno : -EIO;
}

std::string line_name(const std::string& chip_name, int offset, const char* config_key) {
  return "line " + std::to_string(offset) + " of " + chip_name + " (" + config_key + ")";
}

std::string request_failure(const std::string& chip_name, int offset, const char* config_key, int result) {
  std::string message = "gpio: cannot request " + line_name(chip_name, offset, config_key) + ": " + errno_text(-result);
  if (result == -EBUSY) message += "; another program holds it (`gpioinfo " + chip_name + "` shows the consumer)";
  return message;
}

Expected<gpiod_line*> get_line(GpiodApi& api, const GpiodChip& chip, const std::string& chip_name, int offset,
                               const char* config_key) {
  if (offset < 0) {
    return make_error("gpio: " + std::string(config_key) + " is " + std::to_string(offset) +
                      "; give the line offset on " + chip_name + " in " + kConfigHint);
  }
  gpiod_line* line = nullptr;
  if (int result = api.chip_get_line(chip.get(), static_cast<unsigned>(offset), line); result < 0) {
    return make_error("gpio: " + chip_name + " has no line " + std::to_string(offset) + " (" + config_key + " in " +
                      kConfigHint + "; `gpioinfo " + chip_name + "` lists the lines): " + errno_text(-result));
  }
  return line;
}

}  // namespace

int RealGpiodApi::chip_open(const char* name_or_path, gpiod_chip*& chip) {
  errno = 0;
  gpiod_chip* opened =
      std::strchr(name_or_path, '/') != nullptr ? gpiod_chip_open(name_or_path) : gpiod_chip_open_by_name(name_or_path);
  if (opened == nullptr) return failed();
  chip = opened;
  return 0;
}

void RealGpiodApi::chip_close(gpiod_chip* chip) {
  gpiod_chip_close(chip);
}

int RealGpiodApi::chip_get_line(gpiod_chip* chip, unsigned int offset, gpiod_line*& line) {
  errno = 0;
  gpiod_line* found = gpiod_chip_get_line(chip, offset);
  if (found == nullptr) return failed();
  line = found;
  return 0;
}

int RealGpiodApi::line_request_output(gpiod_line* line, const char* consumer, int initial_value) {
  errno = 0;
  return gpiod_line_request_output(line, consumer, initial_value) < 0 ? failed() : 0;
}

int RealGpiodApi::line_request_both_edges_events(gpiod_line* line, const char* consumer) {
  errno = 0;
  return gpiod_line_request_both_edges_events(line, consumer) < 0 ? failed() : 0;
}

void RealGpiodApi::line_release(gpiod_line* line) {
  gpiod_line_release(line);
}

int RealGpiodApi::line_set_value(gpiod_line* line, int value) {
  errno = 0;
  return gpiod_line_set_value(line, value) < 0 ? failed() : 0;
}

int RealGpiodApi::line_get_value(gpiod_line* line) {
  errno = 0;
  int value = gpiod_line_get_value(line);
  return value < 0 ? failed() : value;
}

int RealGpiodApi::line_event_wait(gpiod_line* const* lines, unsigned count, const timespec& timeout,
                                  std::uint32_t& ready_mask) {
  if (count == 0 || count > kMaxWaitLines) return -EINVAL;
  // The bulk objects live on the stack: gpiod_line_bulk is a fixed array in v1, so waiting never allocates.
  gpiod_line_bulk bulk{};
  gpiod_line_bulk_init(&bulk);
  for (unsigned i = 0; i < count; ++i) gpiod_line_bulk_add(&bulk, lines[i]);
  gpiod_line_bulk ready{};
  gpiod_line_bulk_init(&ready);
  errno = 0;
  int result = gpiod_line_event_wait_bulk(&bulk, &timeout, &ready);
  if (result < 0) return failed();
  ready_mask = 0;
  if (result == 0) return 0;
  for (unsigned r = 0; r < gpiod_line_bulk_num_lines(&ready); ++r) {
    for (unsigned i = 0; i < count; ++i) {
      if (gpiod_line_bulk_get_line(&ready, r) == lines[i]) ready_mask |= 1u << i;
    }
  }
  return 1;
}

int RealGpiodApi::line_event_read(gpiod_line* line, gpiod_line_event& event) {
  errno = 0;
  return gpiod_line_event_read(line, &event) < 0 ? failed() : 0;
}

Expected<GpiodChip> open_gpio_chip(GpiodApi& api, const std::string& chip_name) {
  if (chip_name.empty())
    return make_error(std::string("gpio: gpio.chip is empty; name the GPIO chip in ") + kConfigHint);
  gpiod_chip* chip = nullptr;
  if (int result = api.chip_open(chip_name.c_str(), chip); result < 0) {
    std::string hint = (result == -EACCES || result == -EPERM) ? "is the user in the 'gpio' group? " : std::string("");
    return make_error("gpio: cannot open GPIO chip '" + chip_name + "': " + errno_text(-result) + " (" + hint +
                      "check gpio.chip in " + kConfigHint + "; `gpiodetect` lists the chips)");
  }
  return GpiodChip(api, chip);
}

Expected<gpiod_line*> request_gpio_output(GpiodApi& api, const GpiodChip& chip, const std::string& chip_name,
                                          int offset, const char* config_key, const char* consumer, int initial_value) {
  Expected<gpiod_line*> line = get_line(api, chip, chip_name, offset, config_key);
  if (!line.ok()) return line;
  if (int result = api.line_request_output(*line, consumer, initial_value); result < 0) {
    return make_error(request_failure(chip_name, offset, config_key, result));
  }
  return line;
}

Expected<gpiod_line*> request_gpio_edges(GpiodApi& api, const GpiodChip& chip, const std::string& chip_name, int offset,
                                         const char* config_key, const char* consumer) {
  Expected<gpiod_line*> line = get_line(api, chip, chip_name, offset, config_key);
  if (!line.ok()) return line;
  if (int result = api.line_request_both_edges_events(*line, consumer); result < 0) {
    return make_error(request_failure(chip_name, offset, config_key, result) +
                      (result == -EINVAL || result == -EIO ? "; the line may not support edge interrupts" : ""));
  }
  return line;
}

std::int64_t gpio_now_ns() {
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return to_ns(now);
}

}  // namespace cellsight::drivers
