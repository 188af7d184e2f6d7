// Seam over the libgpiod v1 calls the GPIO backends use, so tests can drive them with a simulated chip.
#pragma once

#include <gpiod.h>
#include <time.h>

#include <cstdint>
#include <string>

#include "base/result.hpp"

namespace cellsight::drivers {

// libgpiod v1 reaches the kernel through its own ioctls on /dev/gpiochipN, so the seam sits one level up: one
// virtual call per gpiod_* function used. Like SysSeam, every call returns a negative errno on failure (never -1 +
// errno), and implementations must not allocate after the lines are requested. Chip and line pointers are opaque
// handles: a fake hands out its own objects cast to gpiod_chip* / gpiod_line* and casts them back.
class GpiodApi {
 public:
  virtual ~GpiodApi() = default;
  GpiodApi() = default;
  GpiodApi(const GpiodApi&) = delete;
  GpiodApi& operator=(const GpiodApi&) = delete;

  // `name_or_path`: "gpiochip0" (gpiod_chip_open_by_name) or "/dev/gpiochip0" (gpiod_chip_open). 0 or -errno.
  [[nodiscard]] virtual int chip_open(const char* name_or_path, gpiod_chip*& chip) = 0;
  // Releases every line still requested on the chip (libgpiod v1 semantics).
  virtual void chip_close(gpiod_chip* chip) = 0;
  [[nodiscard]] virtual int chip_get_line(gpiod_chip* chip, unsigned int offset, gpiod_line*& line) = 0;
  // Values here are physical pin levels: the backends apply active-low themselves (see gpiod_io.hpp).
  [[nodiscard]] virtual int line_request_output(gpiod_line* line, const char* consumer, int initial_value) = 0;
  [[nodiscard]] virtual int line_request_both_edges_events(gpiod_line* line, const char* consumer) = 0;
  virtual void line_release(gpiod_line* line) = 0;
  [[nodiscard]] virtual int line_set_value(gpiod_line* line, int value) = 0;
  // 0 or 1, or -errno.
  [[nodiscard]] virtual int line_get_value(gpiod_line* line) = 0;
  // Waits for an edge event on any of `lines` (count <= kMaxWaitLines): 0 on timeout; 1 with bit i of ready_mask
  // set for each lines[i] that has an event queued; or -errno.
  static constexpr unsigned kMaxWaitLines = 32;
  [[nodiscard]] virtual int line_event_wait(gpiod_line* const* lines, unsigned count, const timespec& timeout,
                                            std::uint32_t& ready_mask) = 0;
  // Reads the oldest queued event (blocks when none: call after line_event_wait). 0 or -errno.
  [[nodiscard]] virtual int line_event_read(gpiod_line* line, gpiod_line_event& event) = 0;
};

// Forwards to libgpiod v1 (Debian 12: 1.6).
class RealGpiodApi final : public GpiodApi {
 public:
  int chip_open(const char* name_or_path, gpiod_chip*& chip) override;
  void chip_close(gpiod_chip* chip) override;
  int chip_get_line(gpiod_chip* chip, unsigned int offset, gpiod_line*& line) override;
  int line_request_output(gpiod_line* line, const char* consumer, int initial_value) override;
  int line_request_both_edges_events(gpiod_line* line, const char* consumer) override;
  void line_release(gpiod_line* line) override;
  int line_set_value(gpiod_line* line, int value) override;
  int line_get_value(gpiod_line* line) override;
  int line_event_wait(gpiod_line* const* lines, unsigned count, const timespec& timeout,
                      std::uint32_t& ready_mask) override;
  int line_event_read(gpiod_line* line, gpiod_line_event& event) override;
};

// Owns an open chip; closing it releases its lines. Move-only.
class GpiodChip {
 public:
  GpiodChip() = default;
  GpiodChip(GpiodApi& api, gpiod_chip* chip) : api_(&api), chip_(chip) {}
  ~GpiodChip() { reset(); }
  GpiodChip(GpiodChip&& other) noexcept : api_(other.api_), chip_(other.chip_) { other.chip_ = nullptr; }
  GpiodChip& operator=(GpiodChip&& other) noexcept {
    if (this != &other) {
      reset();
      api_ = other.api_;
      chip_ = other.chip_;
      other.chip_ = nullptr;
    }
    return *this;
  }
  GpiodChip(const GpiodChip&) = delete;
  GpiodChip& operator=(const GpiodChip&) = delete;

  [[nodiscard]] gpiod_chip* get() const { return chip_; }
  void reset() {
    if (chip_ != nullptr) api_->chip_close(chip_);
    chip_ = nullptr;
  }

 private:
  GpiodApi* api_ = nullptr;
  gpiod_chip* chip_ = nullptr;
};

// Start-up helpers shared by the GPIO backends. Each message names the chip, the line and the config key.
[[nodiscard]] Expected<GpiodChip> open_gpio_chip(GpiodApi& api, const std::string& chip_name);
// Gets line `offset` and requests it as an output at physical level `initial_value`.
[[nodiscard]] Expected<gpiod_line*> request_gpio_output(GpiodApi& api, const GpiodChip& chip,
                                                        const std::string& chip_name, int offset,
                                                        const char* config_key, const char* consumer,
                                                        int initial_value);
// Gets line `offset` and requests edge events on both edges.
[[nodiscard]] Expected<gpiod_line*> request_gpio_edges(GpiodApi& api, const GpiodChip& chip,
                                                       const std::string& chip_name, int offset, const char* config_key,
                                                       const char* consumer);

// CLOCK_MONOTONIC now, and the helpers to move between it, event timespecs and timeouts.
[[nodiscard]] std::int64_t gpio_now_ns();
[[nodiscard]] inline std::int64_t to_ns(const timespec& time) {
  return static_cast<std::int64_t>(time.tv_sec) * 1'000'000'000 + time.tv_nsec;
}
[[nodiscard]] inline timespec to_timespec(std::int64_t ns) {
  timespec time{};
  time.tv_sec = static_cast<time_t>(ns / 1'000'000'000);
  time.tv_nsec = static_cast<long>(ns % 1'000'000'000);
  return time;
}

}  // namespace cellsight::drivers
