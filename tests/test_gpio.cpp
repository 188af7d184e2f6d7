// GpiodIo and GpiodEncoder against a simulated GPIO chip behind GpiodApi, plus the pure quadrature decoder.
#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <deque>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "drivers/gpio/gpiod_api.hpp"
#include "drivers/gpio/gpiod_encoder.hpp"
#include "drivers/gpio/gpiod_io.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using cellsight::Status;
using cellsight::drivers::DeviceStatus;
using cellsight::drivers::Edge;
using cellsight::drivers::EdgeEvent;
using cellsight::drivers::GpiodApi;
using cellsight::drivers::GpiodEncoder;
using cellsight::drivers::GpiodEncoderConfig;
using cellsight::drivers::GpiodIo;
using cellsight::drivers::GpiodIoConfig;
using cellsight::drivers::Input;
using cellsight::drivers::Output;
using cellsight::drivers::quadrature_step;
using cellsight::drivers::QuadratureDecoder;
using cellsight::drivers::RealGpiodApi;

constexpr std::int64_t kNsPerUs = 1'000;
constexpr std::int64_t kNsPerMs = 1'000'000;

std::int64_t now_ns() {
  return cellsight::drivers::gpio_now_ns();
}

// A GPIO chip as the kernel shows it through libgpiod: lines with physical levels, one owner each, and a queue of
// edge events per line requested for events. Thread-safe: the encoder reads it from its own thread.
class FakeChip final : public GpiodApi {
 public:
  enum class Mode { kFree, kOutput, kEvents };
  struct Change {
    std::int64_t time_ns;
    int level;
  };

  FakeChip(std::string name, unsigned line_count) : name_(std::move(name)), lines_(line_count) {
    for (Line& line : lines_) line.history.reserve(4096);  // set_value must not allocate inside a counted window
  }

  // ---- the outside world ----

  // The signal on `offset` goes to `level` at `time_ns`; a line requested for events queues the edge.
  void drive(unsigned offset, int level, std::int64_t time_ns) {
    std::lock_guard lock(mutex_);
    Line& line = lines_.at(offset);
    if (line.value == level) return;
    line.value = level;
    if (line.mode == Mode::kEvents) queue_locked(line, level, time_ns);
    changed_.notify_all();
  }
  // An edge event without the matching level history (what the kernel reports when an edge was missed).
  void queue_event(unsigned offset, int level, std::int64_t time_ns) {
    std::lock_guard lock(mutex_);
    Line& line = lines_.at(offset);
    line.value = level;
    queue_locked(line, level, time_ns);
    changed_.notify_all();
  }
  // The pin moves but no event is queued: an edge the kernel missed.
  void set_level_silently(unsigned offset, int level) {
    std::lock_guard lock(mutex_);
    lines_.at(offset).value = level;
  }
  void vanish() {
    std::lock_guard lock(mutex_);
    vanished_ = true;
    changed_.notify_all();
  }

  [[nodiscard]] int level(unsigned offset) const {
    std::lock_guard lock(mutex_);
    return lines_.at(offset).value;
  }
  [[nodiscard]] Mode mode(unsigned offset) const {
    std::lock_guard lock(mutex_);
    return lines_.at(offset).mode;
  }
  [[nodiscard]] std::vector<Change> history(unsigned offset) const {
    std::lock_guard lock(mutex_);
    return lines_.at(offset).history;
  }
  [[nodiscard]] bool chip_open() const {
    std::lock_guard lock(mutex_);
    return open_;
  }
  [[nodiscard]] bool all_free() const {
    std::lock_guard lock(mutex_);
    return std::all_of(lines_.begin(), lines_.end(), [](const Line& line) { return line.mode == Mode::kFree; });
  }
  void occupy(unsigned offset) {
    std::lock_guard lock(mutex_);
    lines_.at(offset).foreign = true;
  }

  // ---- GpiodApi ----

  int chip_open(const char* name_or_path, gpiod_chip*& chip) override {
    std::lock_guard lock(mutex_);
    if (name_ != name_or_path && "/dev/" + name_ != name_or_path) return -ENOENT;
    if (open_) return -EBUSY;
    open_ = true;
    chip = reinterpret_cast<gpiod_chip*>(this);
    return 0;
  }
  void chip_close(gpiod_chip* chip) override {
    std::lock_guard lock(mutex_);
    if (chip != reinterpret_cast<gpiod_chip*>(this)) misuse("chip_close of a foreign chip");
    for (Line& line : lines_) release_locked(line);  // libgpiod v1 releases what is left
    open_ = false;
  }
  int chip_get_line(gpiod_chip* chip, unsigned int offset, gpiod_line*& line) override {
    std::lock_guard lock(mutex_);
    if (chip != reinterpret_cast<gpiod_chip*>(this) || !open_) return -EBADF;
    if (offset >= lines_.size()) return -EINVAL;
    line = reinterpret_cast<gpiod_line*>(&lines_[offset]);
    return 0;
  }
  int line_request_output(gpiod_line* handle, const char* consumer, int initial_value) override {
    std::lock_guard lock(mutex_);
    Line& line = from(handle);
    if (line.mode != Mode::kFree || line.foreign) return -EBUSY;
    if (consumer == nullptr || *consumer == '\0') return -EINVAL;
    line.mode = Mode::kOutput;
    line.value = initial_value;
    line.history.push_back({now_ns(), initial_value});
    return 0;
  }
  int line_request_both_edges_events(gpiod_line* handle, const char* consumer) override {
    std::lock_guard lock(mutex_);
    Line& line = from(handle);
    if (line.mode != Mode::kFree || line.foreign) return -EBUSY;
    if (consumer == nullptr || *consumer == '\0') return -EINVAL;
    line.mode = Mode::kEvents;
    return 0;
  }
  void line_release(gpiod_line* handle) override {
    std::lock_guard lock(mutex_);
    release_locked(from(handle));
  }
  int line_set_value(gpiod_line* handle, int value) override {
    std::lock_guard lock(mutex_);
    if (vanished_) return -ENODEV;
    Line& line = from(handle);
    if (line.mode != Mode::kOutput) return -EPERM;
    line.value = value;
    line.history.push_back({now_ns(), value});
    return 0;
  }
  int line_get_value(gpiod_line* handle) override {
    std::lock_guard lock(mutex_);
    if (vanished_) return -ENODEV;
    Line& line = from(handle);
    if (line.mode == Mode::kFree) return -EPERM;
    return line.value;
  }
  int line_event_wait(gpiod_line* const* handles, unsigned count, const timespec& timeout,
                      std::uint32_t& ready_mask) override {
    std::unique_lock lock(mutex_);
    auto ready = [&] {
      ready_mask = 0;
      for (unsigned i = 0; i < count; ++i) {
        if (!from(handles[i]).events.empty()) ready_mask |= 1u << i;
      }
      return vanished_ || ready_mask != 0;
    };
    const auto wait = std::chrono::nanoseconds(cellsight::drivers::to_ns(timeout));
    if (!changed_.wait_for(lock, wait, ready)) return 0;
    return vanished_ ? -ENODEV : 1;
  }
  int line_event_read(gpiod_line* handle, gpiod_line_event& event) override {
    std::lock_guard lock(mutex_);
    if (vanished_) return -ENODEV;
    Line& line = from(handle);
    if (line.mode != Mode::kEvents) return -EPERM;
    if (line.events.empty()) misuse("line_event_read with nothing queued would block forever");
    event = line.events.front();
    line.events.pop_front();
    return 0;
  }

 private:
  struct Line {
    Mode mode = Mode::kFree;
    bool foreign = false;  // held by another program
    int value = 0;
    std::vector<Change> history;
    std::deque<gpiod_line_event> events;
  };

  Line& from(gpiod_line* handle) {
    auto* line = reinterpret_cast<Line*>(handle);
    if (line < lines_.data() || line >= lines_.data() + lines_.size()) misuse("a line handle this chip never gave");
    return *line;
  }
  // A driver bug the fake cannot answer sensibly; Catch's macros are not thread-safe, so stop loudly here.
  [[noreturn]] static void misuse(const char* what) {
    std::fprintf(stderr, "FakeChip misuse: %s\n", what);
    std::abort();
  }
  static void queue_locked(Line& line, int level, std::int64_t time_ns) {
    gpiod_line_event event{};
    event.ts = cellsight::drivers::to_timespec(time_ns);
    event.event_type = level != 0 ? GPIOD_LINE_EVENT_RISING_EDGE : GPIOD_LINE_EVENT_FALLING_EDGE;
    line.events.push_back(event);
  }
  static void release_locked(Line& line) {
    line.mode = Mode::kFree;
    line.events.clear();
  }

  std::string name_;
  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::vector<Line> lines_;
  bool open_ = false;
  bool vanished_ = false;
};

constexpr unsigned kLaser = 3;
constexpr unsigned kTrigger = 5;
constexpr unsigned kPartPresent = 7;
constexpr unsigned kEncoderA = 10;
constexpr unsigned kEncoderB = 11;

GpiodIoConfig io_config() {
  GpiodIoConfig config;
  config.chip = "gpiochip-fake";
  config.laser_enable.offset = kLaser;
  config.camera_trigger.offset = kTrigger;
  config.part_present.offset = kPartPresent;
  config.trigger_pulse_us = 300;
  config.debounce_us = 2'000;
  return config;
}

GpiodEncoderConfig encoder_config() {
  GpiodEncoderConfig config;
  config.chip = "gpiochip-fake";
  config.line_a = kEncoderA;
  config.line_b = kEncoderB;
  return config;
}

// The physical encoder: quarter-step phase p -> (A, B) levels; forward runs 00, 10, 11, 01.
bool level_a(std::int64_t position) {
  return ((position % 4) + 4) % 4 == 1 || ((position % 4) + 4) % 4 == 2;
}
bool level_b(std::int64_t position) {
  return ((position % 4) + 4) % 4 >= 2;
}
std::uint8_t state_of(std::int64_t position) {
  return static_cast<std::uint8_t>((level_a(position) ? 2u : 0u) | (level_b(position) ? 1u : 0u));
}

// Waits (bounded) until the encoder thread has decoded `events` events.
bool wait_processed(const GpiodEncoder& encoder, std::uint64_t events) {
  const std::int64_t deadline = now_ns() + 10'000 * kNsPerMs;
  while (encoder.events_processed() < events) {
    if (now_ns() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  return true;
}

}  // namespace

SCENARIO("outputs reach the expected pin levels, active-low inverted", "[gpio]") {
  GIVEN("a laser line (active high) and a trigger line (active low)") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIoConfig config = io_config();
    config.camera_trigger.active_low = true;
    GpiodIo io(chip, config);
    REQUIRE(io.open().ok());

    THEN("both start inactive: laser pin low, trigger pin high") {
      CHECK(chip.level(kLaser) == 0);
      CHECK(chip.level(kTrigger) == 1);
      CHECK(chip.mode(kLaser) == FakeChip::Mode::kOutput);
      CHECK(chip.history(kLaser).size() == 1);  // requested at the inactive level, never flashed on
    }
    WHEN("each output is set active and inactive") {
      REQUIRE(io.set(Output::kLaserEnable, true) == DeviceStatus::kOk);
      const int laser_on = chip.level(kLaser);
      REQUIRE(io.set(Output::kCameraTrigger, true) == DeviceStatus::kOk);
      const int trigger_on = chip.level(kTrigger);
      REQUIRE(io.set(Output::kLaserEnable, false) == DeviceStatus::kOk);
      REQUIRE(io.set(Output::kCameraTrigger, false) == DeviceStatus::kOk);
      THEN("the pins follow, the active-low one inverted") {
        CHECK(laser_on == 1);
        CHECK(trigger_on == 0);
        CHECK(chip.level(kLaser) == 0);
        CHECK(chip.level(kTrigger) == 1);
      }
    }
    WHEN("the laser is left on and the I/O is closed") {
      REQUIRE(io.set(Output::kLaserEnable, true) == DeviceStatus::kOk);
      io.close();
      THEN("the laser is switched off and every line and the chip are released") {
        CHECK(chip.level(kLaser) == 0);
        CHECK(chip.level(kTrigger) == 1);
        CHECK(chip.all_free());
        CHECK_FALSE(chip.chip_open());
        CHECK(io.set(Output::kLaserEnable, true) == DeviceStatus::kNotStarted);
      }
    }
  }
  GIVEN("an I/O without a trigger line") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIoConfig config = io_config();
    config.camera_trigger.offset = -1;
    GpiodIo io(chip, config);
    REQUIRE(io.open().ok());
    THEN("driving the missing line is refused") {
      CHECK(io.set(Output::kCameraTrigger, true) == DeviceStatus::kInvalidArgument);
      CHECK(io.pulse(Output::kCameraTrigger, 10) == DeviceStatus::kInvalidArgument);
    }
  }
}

SCENARIO("a trigger pulse goes active for its width, then inactive", "[gpio]") {
  for (bool active_low : {false, true}) {
    GIVEN(std::string("a trigger line, active ") + (active_low ? "low" : "high")) {
      FakeChip chip("gpiochip-fake", 16);
      GpiodIoConfig config = io_config();
      config.camera_trigger.active_low = active_low;
      GpiodIo io(chip, config);
      REQUIRE(io.open().ok());
      const int active = active_low ? 0 : 1;

      WHEN("a 500 µs pulse and a default-width pulse are sent") {
        REQUIRE(io.pulse(Output::kCameraTrigger, 500) == DeviceStatus::kOk);
        REQUIRE(io.pulse(Output::kCameraTrigger, 0) == DeviceStatus::kOk);
        const std::vector<FakeChip::Change> history = chip.history(kTrigger);
        THEN("the pin went active then inactive twice, each time for at least the width") {
          REQUIRE(history.size() == 5);  // inactive at request, then on/off, on/off
          CHECK(history[0].level == 1 - active);
          CHECK(history[1].level == active);
          CHECK(history[2].level == 1 - active);
          CHECK(history[3].level == active);
          CHECK(history[4].level == 1 - active);
          CHECK(history[2].time_ns - history[1].time_ns >= 500 * kNsPerUs);
          CHECK(history[4].time_ns - history[3].time_ns >= 300 * kNsPerUs);
          CHECK(chip.level(kTrigger) == 1 - active);
        }
      }
      WHEN("a pulse longer than the limit is asked for") {
        THEN("it is refused without touching the pin") {
          CHECK(io.pulse(Output::kCameraTrigger, GpiodIo::kMaxPulseUs + 1) == DeviceStatus::kInvalidArgument);
          CHECK(chip.history(kTrigger).size() == 1);
        }
      }
    }
  }
}

SCENARIO("part-present edges are debounced", "[gpio]") {
  GIVEN("a photo-eye input with a 2 ms debounce, currently inactive") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIo io(chip, io_config());
    REQUIRE(io.open().ok());
    EdgeEvent edge;

    WHEN("the part arrives with a bounce train that ends high") {
      const std::int64_t t0 = now_ns();
      const int levels[] = {1, 0, 1, 0, 1, 0, 1};
      for (int i = 0; i < 7; ++i) chip.drive(kPartPresent, levels[i], t0 + 50 * kNsPerUs * i);
      const DeviceStatus first = io.wait_edge(edge, 50);
      const EdgeEvent rising = edge;
      const DeviceStatus second = io.wait_edge(edge, 20);
      THEN("exactly one rising edge is delivered, stamped with the first transition") {
        CHECK(first == DeviceStatus::kOk);
        CHECK(rising.edge == Edge::kRising);
        CHECK(rising.input == Input::kPartPresent);
        CHECK(rising.timestamp_ns == t0);
        CHECK(second == DeviceStatus::kTimeout);
        CHECK(io.stats().edges == 1);
        CHECK(io.stats().bounces == 6);
      }
      AND_WHEN("the part leaves 80 ms later, bouncing again") {
        for (int i = 0; i < 5; ++i)
          chip.drive(kPartPresent, i % 2 == 0 ? 0 : 1, t0 + 80 * kNsPerMs + 30 * kNsPerUs * i);
        chip.drive(kPartPresent, 0, t0 + 80 * kNsPerMs + 200 * kNsPerUs);
        const DeviceStatus leave = io.wait_edge(edge, 50);
        const EdgeEvent falling = edge;
        const DeviceStatus after = io.wait_edge(edge, 20);
        THEN("one falling edge follows") {
          CHECK(leave == DeviceStatus::kOk);
          CHECK(falling.edge == Edge::kFalling);
          CHECK(falling.timestamp_ns == t0 + 80 * kNsPerMs);
          CHECK(after == DeviceStatus::kTimeout);
          CHECK(io.stats().edges == 2);
        }
      }
    }
    WHEN("a pulse shorter than the debounce window comes and goes") {
      const std::int64_t t0 = now_ns();
      chip.drive(kPartPresent, 1, t0);
      chip.drive(kPartPresent, 0, t0 + 300 * kNsPerUs);
      const DeviceStatus first = io.wait_edge(edge, 50);
      const EdgeEvent rising = edge;
      const DeviceStatus second = io.wait_edge(edge, 50);
      const std::int64_t delivered_at = now_ns();
      THEN("the rising edge is delivered at once and the falling one when the window has passed") {
        CHECK(first == DeviceStatus::kOk);
        CHECK(rising.edge == Edge::kRising);
        CHECK(second == DeviceStatus::kOk);
        CHECK(edge.edge == Edge::kFalling);
        CHECK(edge.timestamp_ns == t0 + 300 * kNsPerUs);
        CHECK(delivered_at >= t0 + 2'000 * kNsPerUs);
        CHECK(io.stats().settled_edges == 1);
      }
    }
    WHEN("two clean edges are further apart than the window") {
      const std::int64_t t0 = now_ns();
      chip.drive(kPartPresent, 1, t0);
      chip.drive(kPartPresent, 0, t0 + 2'000 * kNsPerUs);
      const DeviceStatus first = io.wait_edge(edge, 50);
      const Edge first_edge = edge.edge;
      const DeviceStatus second = io.wait_edge(edge, 50);
      THEN("both are delivered") {
        CHECK(first == DeviceStatus::kOk);
        CHECK(first_edge == Edge::kRising);
        CHECK(second == DeviceStatus::kOk);
        CHECK(edge.edge == Edge::kFalling);
        CHECK(io.stats().settled_edges == 0);
      }
    }
  }
  GIVEN("an active-low photo-eye (the pin idles high)") {
    FakeChip chip("gpiochip-fake", 16);
    chip.drive(kPartPresent, 1, 0);
    GpiodIoConfig config = io_config();
    config.part_present.active_low = true;
    GpiodIo io(chip, config);
    REQUIRE(io.open().ok());
    bool idle_active = true;
    REQUIRE(io.read(Input::kPartPresent, idle_active) == DeviceStatus::kOk);
    WHEN("the pin is pulled low") {
      chip.drive(kPartPresent, 0, now_ns());
      EdgeEvent edge;
      const DeviceStatus status = io.wait_edge(edge, 50);
      bool active = false;
      REQUIRE(io.read(Input::kPartPresent, active) == DeviceStatus::kOk);
      THEN("the part is present: a rising edge and an active level") {
        CHECK_FALSE(idle_active);
        CHECK(status == DeviceStatus::kOk);
        CHECK(edge.edge == Edge::kRising);
        CHECK(active);
      }
    }
  }
}

SCENARIO("GPIO faults and configuration mistakes give clear errors, never a crash", "[gpio]") {
  GIVEN("the real libgpiod and a chip name that cannot exist") {
    RealGpiodApi api;
    GpiodIoConfig config = io_config();
    config.chip = "gpiochip-cellsight-absent";
    GpiodIo io(api, config);
    Status status = io.open();
    THEN("open() names the chip, the reason and the config key") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("'gpiochip-cellsight-absent'") &&
                                             Catch::Contains("No such file or directory") &&
                                             Catch::Contains("gpio.chip"));
      CHECK(io.set(Output::kLaserEnable, true) == DeviceStatus::kNotStarted);
      io.close();
    }
    AND_THEN("the encoder on that chip fails the same way") {
      GpiodEncoderConfig encoder_settings = encoder_config();
      encoder_settings.chip = "/dev/gpiochip-cellsight-absent";
      GpiodEncoder encoder(api, encoder_settings);
      Status encoder_status = encoder.open();
      REQUIRE_FALSE(encoder_status.ok());
      CHECK_THAT(encoder_status.error().message,
                 Catch::Contains("/dev/gpiochip-cellsight-absent") && Catch::Contains("gpio.chip"));
      std::int64_t counts = 0;
      CHECK(encoder.read_counts(counts) == DeviceStatus::kNotStarted);
    }
  }
  GIVEN("a part-present line beyond the chip's lines") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIoConfig config = io_config();
    config.part_present.offset = 99;
    GpiodIo io(chip, config);
    Status status = io.open();
    THEN("open() names the line and key, and the lines already requested are released") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("no line 99") && Catch::Contains("gpio.part_present_line"));
      CHECK(chip.all_free());
      CHECK_FALSE(chip.chip_open());
    }
  }
  GIVEN("a trigger line held by another program") {
    FakeChip chip("gpiochip-fake", 16);
    chip.occupy(kTrigger);
    GpiodIo io(chip, io_config());
    Status status = io.open();
    THEN("open() says so and tells how to find the holder") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message,
                 Catch::Contains("line 5") && Catch::Contains("gpio.trigger_line") && Catch::Contains("gpioinfo"));
      CHECK(chip.all_free());
      CHECK_FALSE(chip.chip_open());
    }
  }
  GIVEN("two functions configured on the same line") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIoConfig config = io_config();
    config.part_present.offset = kLaser;
    GpiodIo io(chip, config);
    Status status = io.open();
    THEN("open() refuses before touching the chip") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("configured twice"));
      CHECK_FALSE(chip.chip_open());
    }
  }
  GIVEN("an open I/O whose chip vanishes") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIo io(chip, io_config());
    REQUIRE(io.open().ok());
    chip.vanish();
    EdgeEvent edge;
    bool active = false;
    THEN("every call reports the device lost, and close() is safe") {
      CHECK(io.set(Output::kLaserEnable, true) == DeviceStatus::kDeviceLost);
      CHECK(io.read(Input::kPartPresent, active) == DeviceStatus::kDeviceLost);
      CHECK(io.wait_edge(edge, 10) == DeviceStatus::kDeviceLost);
      io.close();
      CHECK_FALSE(chip.chip_open());
    }
  }
}

SCENARIO("the x4 quadrature decoder matches the physical encoder", "[gpio][encoder]") {
  GIVEN("every phase and every move of -1, 0, +1 or 2 quarter steps") {
    THEN("the table gives the move, and flags the 2-step jumps whose direction cannot be known") {
      for (std::int64_t phase = 0; phase < 4; ++phase) {
        for (std::int64_t move : {-1, 0, 1, 2}) {
          const auto step = quadrature_step(state_of(phase), state_of(phase + move));
          INFO("phase " << phase << " move " << move);
          CHECK(step.illegal == (move == 2));
          CHECK(step.delta == (move == 2 ? 0 : move));
        }
      }
    }
  }
  GIVEN("a random walk of the shaft sampled 20 000 times, sometimes too slowly") {
    std::mt19937 random(7);
    std::discrete_distribution<int> moves({10, 20, 60, 5, 5});  // -1, 0, +1, +2, -2
    const std::int64_t move_of[] = {-1, 0, 1, 2, -2};
    std::int64_t position = 12345;  // anywhere: the decoder starts from the levels it sees
    QuadratureDecoder decoder;
    decoder.reset(level_a(position), level_b(position));
    std::int64_t exact = 0;
    std::uint64_t jumps = 0;
    for (int i = 0; i < 20'000; ++i) {
      const std::int64_t move = move_of[moves(random)];
      position += move;
      if (move == 2 || move == -2) {
        ++jumps;  // a sampler cannot tell +2 from -2: the model expects no count and one illegal transition
      } else {
        exact += move;
      }
      decoder.sample(level_a(position), level_b(position));
    }
    THEN("the count equals every single step, and every jump is flagged") {
      CHECK(decoder.counts() == exact);
      CHECK(decoder.illegal() == jumps);
      CHECK(jumps > 0);
    }
  }
  GIVEN("single-line edges of a walk, one of which is lost") {
    QuadratureDecoder decoder;
    decoder.reset(false, false);
    std::int64_t position = 0;
    int lost = 0;
    for (int i = 0; i < 40; ++i) {
      const std::int64_t next = position + (i < 30 ? 1 : -1);
      const int line = level_a(next) != level_a(position) ? 0 : 1;
      const bool level = line == 0 ? level_a(next) : level_b(next);
      position = next;
      if (i == 17) {
        ++lost;
        continue;
      }
      decoder.edge(line, level);
    }
    THEN("the loss is flagged") {
      CHECK(lost == 1);
      CHECK(decoder.illegal() >= 1);
    }
  }
}

SCENARIO("the encoder backend counts edge events from the chip exactly", "[gpio][encoder]") {
  for (bool reverse : {false, true}) {
    GIVEN(std::string("an encoder on two lines") + (reverse ? ", reversed" : "")) {
      FakeChip chip("gpiochip-fake", 16);
      std::int64_t position = 2;  // A high, B high at open
      chip.drive(kEncoderA, level_a(position), 0);
      chip.drive(kEncoderB, level_b(position), 0);
      GpiodEncoderConfig config = encoder_config();
      config.reverse = reverse;
      GpiodEncoder encoder(chip, config);
      REQUIRE(encoder.open().ok());

      WHEN("the conveyor jitters back and forth and runs forward, all edges queued at once") {
        std::mt19937 random(99);
        std::discrete_distribution<int> moves({25, 75});
        const std::int64_t start = position;
        std::int64_t time_ns = now_ns();
        std::uint64_t events = 0;
        for (int i = 0; i < 3'000; ++i) {
          const std::int64_t next = position + (moves(random) == 0 ? -1 : 1);
          time_ns += 37 * kNsPerUs;
          // Exactly one line changes per quarter step; both lines' queues fill before the thread drains them.
          if (level_a(next) != level_a(position)) chip.drive(kEncoderA, level_a(next), time_ns);
          if (level_b(next) != level_b(position)) chip.drive(kEncoderB, level_b(next), time_ns);
          position = next;
          ++events;
        }
        REQUIRE(wait_processed(encoder, events));
        std::int64_t counts = 0;
        REQUIRE(encoder.read_counts(counts) == DeviceStatus::kOk);
        THEN("the counts equal the shaft's travel in quarter steps, with no illegal transition") {
          CHECK(counts == (reverse ? -(position - start) : position - start));
          CHECK(encoder.illegal_transitions() == 0);
        }
      }
      WHEN("an edge is lost between the kernel and the decoder") {
        std::int64_t time_ns = now_ns();
        for (int i = 0; i < 8; ++i) {
          const std::int64_t next = position + 1;
          time_ns += 50 * kNsPerUs;
          const unsigned line = level_a(next) != level_a(position) ? kEncoderA : kEncoderB;
          const bool level = line == kEncoderA ? level_a(next) : level_b(next);
          position = next;
          if (i == 3) {
            chip.set_level_silently(line, level);  // the pin moves...
            continue;
          }
          chip.queue_event(line, level, time_ns);  // ...but only the other edges reach the queue
        }
        REQUIRE(wait_processed(encoder, 7));
        THEN("the illegal transition is counted") {
          CHECK(encoder.illegal_transitions() >= 1);
        }
      }
      encoder.close();
      CHECK(chip.all_free());
      CHECK_FALSE(chip.chip_open());
    }
  }
  GIVEN("an encoder whose chip vanishes") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodEncoder encoder(chip, encoder_config());
    REQUIRE(encoder.open().ok());
    chip.vanish();
    THEN("read_counts() soon reports the device lost and close() is clean") {
      std::int64_t counts = 0;
      DeviceStatus status = DeviceStatus::kOk;
      const std::int64_t deadline = now_ns() + 5'000 * kNsPerMs;
      while ((status = encoder.read_counts(counts)) == DeviceStatus::kOk && now_ns() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
      CHECK(status == DeviceStatus::kDeviceLost);
      encoder.close();
      CHECK_FALSE(chip.chip_open());
    }
  }
  GIVEN("an encoder configured with one line twice") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodEncoderConfig config = encoder_config();
    config.line_b = config.line_a;
    GpiodEncoder encoder(chip, config);
    Status status = encoder.open();
    THEN("open() refuses and names both keys") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message,
                 Catch::Contains("gpio.encoder_a_line") && Catch::Contains("gpio.encoder_b_line"));
    }
  }
}

SCENARIO("set, pulse, read, wait_edge and read_counts never allocate", "[gpio]") {
  GIVEN("an open I/O and a running encoder on one chip") {
    FakeChip chip("gpiochip-fake", 16);
    GpiodIo io(chip, io_config());
    REQUIRE(io.open().ok());
    // The same chip object cannot be opened twice; the encoder gets its own chip.
    FakeChip encoder_chip("gpiochip-fake", 16);
    GpiodEncoder running(encoder_chip, encoder_config());
    REQUIRE(running.open().ok());
    WHEN("the real-time calls run with an edge pending") {
      chip.drive(kPartPresent, 1, now_ns());
      long allocations = 0;
      DeviceStatus statuses[6] = {};
      std::int64_t counts = 0;
      bool active = false;
      EdgeEvent edge;
      {
        const cellsight::test::AllocationWindow window;  // proves the real-time calls never reach the heap
        statuses[0] = io.set(Output::kLaserEnable, true);
        statuses[1] = io.pulse(Output::kCameraTrigger, 20);
        statuses[2] = io.read(Input::kPartPresent, active);
        statuses[3] = io.wait_edge(edge, 20);
        statuses[4] = io.wait_edge(edge, 1);
        statuses[5] = running.read_counts(counts);
        allocations = window.count();
      }
      THEN("they worked and nothing was allocated") {
        CHECK(statuses[0] == DeviceStatus::kOk);
        CHECK(statuses[1] == DeviceStatus::kOk);
        CHECK(statuses[2] == DeviceStatus::kOk);
        CHECK(statuses[3] == DeviceStatus::kOk);
        CHECK(statuses[4] == DeviceStatus::kTimeout);
        CHECK(statuses[5] == DeviceStatus::kOk);
        CHECK(allocations == 0);
      }
    }
  }
}
