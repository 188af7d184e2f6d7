// Conveyor encoder on two quadrature GPIO lines: a pure x4 decoder plus a libgpiod v1 edge-event backend.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <string>
#include <thread>

#include "drivers/digital_io.hpp"
#include "drivers/gpio/gpiod_api.hpp"

namespace cellsight::drivers {

// Quadrature state: (A << 1) | B. Forward (A leads B): 00 -> 10 -> 11 -> 01 -> 00, one count per transition (x4).
struct QuadratureStep {
  std::int8_t delta = 0;  // -1, 0, +1
  bool illegal = false;   // both lines changed at once: a count was missed and the direction is unknown
};

namespace detail {
constexpr QuadratureStep kQ0{0, false};
constexpr QuadratureStep kQf{+1, false};
constexpr QuadratureStep kQb{-1, false};
constexpr QuadratureStep kQx{0, true};
// Row: previous state, column: new state.
inline constexpr std::array<std::array<QuadratureStep, 4>, 4> kQuadratureTable{{
    //   to 00 to 01 to 10 to 11
    {{kQ0, kQb, kQf, kQx}},  // from 00
    {{kQf, kQ0, kQx, kQb}},  // from 01
    {{kQb, kQx, kQ0, kQf}},  // from 10
    {{kQx, kQf, kQb, kQ0}},  // from 11
}};
}  // namespace detail

[[nodiscard]] constexpr QuadratureStep quadrature_step(std::uint8_t from_ab, std::uint8_t to_ab) {
  return detail::kQuadratureTable[from_ab & 3u][to_ab & 3u];
}

// Decoder state fed either with sampled levels or with single-line edges. Pure: no I/O, no clock.
class QuadratureDecoder {
 public:
  void reset(bool a, bool b) {
    state_ = static_cast<std::uint8_t>((a ? 2u : 0u) | (b ? 1u : 0u));
    counts_ = 0;
    illegal_ = 0;
  }
  // Both levels sampled at once.
  void sample(bool a, bool b) { apply(static_cast<std::uint8_t>((a ? 2u : 0u) | (b ? 1u : 0u))); }
  // An edge on one line (line 0 = A, 1 = B) reaching `level`. An edge that does not change the state means the
  // opposite edge on that line was lost (kernel event queue overflow, or bounce faster than the interrupt):
  // counted as illegal, because the true count is off by an unknown amount.
  void edge(int line, bool level) {
    const std::uint8_t bit = line == 0 ? 2u : 1u;
    const auto next = static_cast<std::uint8_t>(level ? (state_ | bit) : (state_ & ~bit & 3u));
    if (next == state_) {
      ++illegal_;
      return;
    }
    apply(next);
  }
  [[nodiscard]] std::int64_t counts() const { return counts_; }
  [[nodiscard]] std::uint64_t illegal() const { return illegal_; }
  [[nodiscard]] std::uint8_t state() const { return state_; }

 private:
  void apply(std::uint8_t next) {
    const QuadratureStep step = quadrature_step(state_, next);
    counts_ += step.delta;
    illegal_ += step.illegal ? 1u : 0u;
    state_ = next;
  }
  std::uint8_t state_ = 0;
  std::int64_t counts_ = 0;
  std::uint64_t illegal_ = 0;
};

// Start-up settings (config/cellsight.yaml, section `gpio`).
struct GpiodEncoderConfig {
  std::string chip = "gpiochip0";  // gpio.chip
  int line_a = -1;                 // gpio.encoder_a_line
  int line_b = -1;                 // gpio.encoder_b_line
  bool reverse = false;  // gpio.encoder_reverse (proposed key): counts must grow while the conveyor runs forward
  std::string consumer = "cellsight";
};

// Encoder fed by A/B edge events on its own thread. Why a thread and not polling from read_counts(): the kernel
// keeps only 16 events per line, and the production loop may not call read_counts() for seconds (recognition
// tail), so a polled decoder would lose edges exactly when it matters; the thread blocks in the kernel between
// edges and costs nothing at conveyor speed. Sampling levels instead would need a busy loop faster than the edge
// rate. read_counts() is a lock-free atomic load and may be called from any thread.
class GpiodEncoder final : public Encoder {
 public:
  static constexpr int kWaitPeriodMs = 20;  // how long the thread blocks before looking at the stop flag

  GpiodEncoder(GpiodApi& api, GpiodEncoderConfig config);
  ~GpiodEncoder() override;

  Status open() override;
  void close() override;
  DeviceStatus read_counts(std::int64_t& counts) override;

  // Illegal transitions and lost edges seen since open(); a rising number means the counts are no longer exact.
  [[nodiscard]] std::uint64_t illegal_transitions() const { return illegal_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t events_processed() const { return events_.load(std::memory_order_acquire); }
  [[nodiscard]] std::uint64_t io_errors() const { return io_errors_.load(std::memory_order_relaxed); }

 private:
  void run();
  void release_lines();

  GpiodApi& api_;
  GpiodEncoderConfig config_;
  GpiodChip chip_;
  std::array<gpiod_line*, 2> lines_{};  // A, B
  QuadratureDecoder decoder_;           // touched only by the thread once it runs
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> lost_{false};
  std::atomic<std::int64_t> counts_{0};
  std::atomic<std::uint64_t> illegal_{0};
  std::atomic<std::uint64_t> events_{0};
  std::atomic<std::uint64_t> io_errors_{0};
  bool open_ = false;
};

}  // namespace cellsight::drivers
