// GpiodEncoder: A/B edge events merged in kernel-timestamp order and fed to the x4 quadrature decoder.
#include "drivers/gpio/gpiod_encoder.hpp"

#include <cerrno>
#include <system_error>
#include <utility>

#include "drivers/log.hpp"
#include "drivers/sys_seam.hpp"

namespace cellsight::drivers {
namespace {

constexpr const char* kComponent = "encoder";
constexpr const char* kConfigHint = "config/cellsight.yaml";
constexpr std::int64_t kNsPerMs = 1'000'000;
constexpr const char* kLineKeys[2] = {"gpio.encoder_a_line", "gpio.encoder_b_line"};

}  // namespace

GpiodEncoder::GpiodEncoder(GpiodApi& api, GpiodEncoderConfig config) : api_(api), config_(std::move(config)) {}

GpiodEncoder::~GpiodEncoder() {
  close();
}

Status GpiodEncoder::open() {
  if (open_) return make_error("encoder: " + config_.chip + " is already open");
  if (config_.line_a < 0 || config_.line_b < 0 || config_.line_a == config_.line_b) {
    return make_error("encoder: gpio.encoder_a_line and gpio.encoder_b_line must be two different lines of " +
                      config_.chip + " (they are " + std::to_string(config_.line_a) + " and " +
                      std::to_string(config_.line_b) + " in " + kConfigHint + ")");
  }
  ScopeExit undo([this] { release_lines(); });
  Expected<GpiodChip> chip = open_gpio_chip(api_, config_.chip);
  if (!chip.ok()) return chip.error();
  chip_ = std::move(chip).value();

  const int offsets[2] = {config_.line_a, config_.line_b};
  bool levels[2] = {false, false};
  for (int i = 0; i < 2; ++i) {
    Expected<gpiod_line*> line =
        request_gpio_edges(api_, chip_, config_.chip, offsets[i], kLineKeys[i], config_.consumer.c_str());
    if (!line.ok()) return line.error();
    lines_[static_cast<std::size_t>(i)] = *line;
    int level = api_.line_get_value(*line);
    if (level < 0) {
      return make_error("encoder: cannot read line " + std::to_string(offsets[i]) + " of " + config_.chip + " (" +
                        kLineKeys[i] + "): " + errno_text(-level));
    }
    levels[i] = level != 0;
  }
  // An edge between the request and this read shows up later as a lost edge (one illegal count), never as drift.
  decoder_.reset(levels[0], levels[1]);
  counts_.store(0);
  illegal_.store(0);
  events_.store(0);
  io_errors_.store(0);
  lost_.store(false);
  stop_.store(false);
  try {
    thread_ = std::thread([this] { run(); });
  } catch (const std::system_error& error) {
    return make_error(std::string("encoder: cannot start the decoding thread: ") + error.what());
  }
  undo.dismiss();
  open_ = true;
  CS_LOG_INFO(kComponent, "%s lines A %d, B %d%s", config_.chip.c_str(), config_.line_a, config_.line_b,
              config_.reverse ? " (reversed)" : "");
  return {};
}

void GpiodEncoder::release_lines() {
  for (gpiod_line*& line : lines_) {
    if (line != nullptr) api_.line_release(line);
    line = nullptr;
  }
  chip_.reset();
}

void GpiodEncoder::close() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
  if (open_) {
    CS_LOG_INFO(kComponent, "%s closed: %lld counts, %llu events, %llu illegal transitions, %llu I/O errors",
                config_.chip.c_str(), static_cast<long long>(counts_.load()),
                static_cast<unsigned long long>(events_.load()), static_cast<unsigned long long>(illegal_.load()),
                static_cast<unsigned long long>(io_errors_.load()));
  }
  release_lines();
  open_ = false;
}

DeviceStatus GpiodEncoder::read_counts(std::int64_t& counts) {
  if (!open_) return DeviceStatus::kNotStarted;
  counts = counts_.load(std::memory_order_relaxed);
  return lost_.load(std::memory_order_relaxed) ? DeviceStatus::kDeviceLost : DeviceStatus::kOk;
}

// Each line has its own kernel event queue, so the two streams are merged: one event of look-ahead per line, and
// the older of the two heads goes first. A head is only decoded alone when the other line had nothing queued.
void GpiodEncoder::run() {
  struct Pending {
    bool valid = false;
    gpiod_line_event event{};
  };
  std::array<Pending, 2> pending{};
  const auto lost = [this](int result) {
    if (result != -ENODEV) return false;
    CS_LOG_ERROR(kComponent, "%s vanished (ENODEV); counts frozen, reopen needed", config_.chip.c_str());
    lost_.store(true);
    return true;
  };
  const auto pause = [] {
    // A failing wait would otherwise spin; the error is counted and retried at the wait period.
    const timespec period = to_timespec(kWaitPeriodMs * kNsPerMs);
    clock_nanosleep(CLOCK_MONOTONIC, 0, &period, nullptr);
  };

  while (!stop_.load(std::memory_order_relaxed)) {
    const bool holding = pending[0].valid || pending[1].valid;
    std::uint32_t ready = 0;
    int result = api_.line_event_wait(lines_.data(), 2, to_timespec(holding ? 0 : kWaitPeriodMs * kNsPerMs), ready);
    if (result == -EINTR) continue;
    if (result < 0) {
      if (lost(result)) return;
      io_errors_.fetch_add(1, std::memory_order_relaxed);
      pause();
      continue;
    }
    for (std::size_t i = 0; i < 2; ++i) {
      if (pending[i].valid || (ready & (1u << i)) == 0) continue;
      if (int read = api_.line_event_read(lines_[i], pending[i].event); read < 0) {
        if (lost(read)) return;
        io_errors_.fetch_add(1, std::memory_order_relaxed);
        continue;
      }
      pending[i].valid = true;
    }
    std::size_t next = 0;
    if (pending[0].valid && pending[1].valid) {
      next = to_ns(pending[1].event.ts) < to_ns(pending[0].event.ts) ? 1 : 0;
    } else if (pending[1].valid) {
      next = 1;
    } else if (!pending[0].valid) {
      continue;
    }
    decoder_.edge(static_cast<int>(next), pending[next].event.event_type == GPIOD_LINE_EVENT_RISING_EDGE);
    pending[next].valid = false;
    counts_.store(config_.reverse ? -decoder_.counts() : decoder_.counts(), std::memory_order_relaxed);
    illegal_.store(decoder_.illegal(), std::memory_order_relaxed);
    events_.fetch_add(1, std::memory_order_release);  // publishes counts_ to a reader that acquires events_
  }
}

}  // namespace cellsight::drivers
