// Simulated camera, digital I/O and encoder on the SimLine timeline.
#include "drivers/sim/sim_devices.hpp"

#include <cmath>
#include <cstring>

namespace cellsight::sim {

using drivers::DeviceStatus;

SimLine::SimLine(SimCell& cell, double gap_between_parts_m) : cell_(cell), gap_m_(gap_between_parts_m) {}

void SimLine::enqueue(const PassSpec& pass, const PassFaults& faults, std::int64_t memo_slot) {
  std::lock_guard lock(mutex_);
  queue_.push_back({pass, faults, memo_slot});
}

Status SimLine::enable_frame_memo(std::size_t slots) {
  std::lock_guard lock(mutex_);
  const auto& k = cell_.rig().params.camera.intrinsics;
  return memo_.allocate(slots, cell_.frame_count(), k.width_px, k.height_px);
}

std::size_t SimLine::queued() const {
  std::lock_guard lock(mutex_);
  return queue_.size();
}

std::uint64_t SimLine::passes_started() const {
  std::lock_guard lock(mutex_);
  return passes_;
}

PassSpec SimLine::current_pass() const {
  std::lock_guard lock(mutex_);
  return current_;
}

void SimLine::set_camera_stalled(bool stalled) {
  std::lock_guard lock(mutex_);
  stalled_ = stalled;
}

std::int64_t SimLine::now_ns_locked() const {
  const auto& c = cell_.rig().params.conveyor;
  const double travel_m = static_cast<double>(counts_) / c.counts_per_mm * 1e-3;
  return static_cast<std::int64_t>(std::llround(travel_m / c.speed_m_per_s * 1e9));
}

std::int64_t SimLine::now_ns() const {
  std::lock_guard lock(mutex_);
  return now_ns_locked();
}

void SimLine::queue_bounces_locked(bool after_level, std::int64_t edge_ns) {
  const std::int64_t spacing_ns = static_cast<std::int64_t>(faults_.bounce_spacing_us) * 1000;
  std::int64_t t = edge_ns;
  for (int i = 0; i < faults_.bounce_pairs; ++i) {
    for (const bool level : {!after_level, after_level}) {
      t += spacing_ns;
      bounces_.push_back({drivers::Input::kPartPresent, level ? drivers::Edge::kRising : drivers::Edge::kFalling, t});
    }
  }
}

DeviceStatus SimLine::next_edge(drivers::EdgeEvent& out) {
  std::lock_guard lock(mutex_);
  out.input = drivers::Input::kPartPresent;
  if (!bounces_.empty()) {
    out = bounces_.front();
    bounces_.pop_front();
    return DeviceStatus::kOk;
  }
  if (falling_pending_) {
    falling_pending_ = false;
    counts_ += cell_.rig().params.conveyor.trigger_every_counts;  // the carrier's end clears the eye a trigger later
    out.edge = drivers::Edge::kFalling;
    out.timestamp_ns = now_ns_locked();
    queue_bounces_locked(false, out.timestamp_ns);
    return DeviceStatus::kOk;
  }
  if (state_ == State::kIdle && !queue_.empty()) {
    current_ = std::move(queue_.front().pass);
    faults_ = queue_.front().faults;
    memo_slot_ = memo_.enabled() ? queue_.front().memo_slot : -1;
    queue_.pop_front();
    stall_started_ = false;
    encoder_ok_from_ = {};
    scene_ready_ = false;
    if (memo_slot_ < 0) {  // with the memo the scene is built only when a frame must be rendered
      if (auto ok = cell_.begin_pass(current_); !ok) return DeviceStatus::kIoError;
      scene_ready_ = true;
    }
    // The conveyor runs the gap between carriers before the next part reaches the photo-eye.
    const auto& c = cell_.rig().params.conveyor;
    counts_ += static_cast<std::int64_t>(std::llround(gap_m_ * 1e3 * c.counts_per_mm));
    pass_start_counts_ = counts_;
    state_ = State::kInPass;
    frame_ = 0;
    ++passes_;
    out.edge = drivers::Edge::kRising;
    out.timestamp_ns = now_ns_locked();
    queue_bounces_locked(true, out.timestamp_ns);
    return DeviceStatus::kOk;
  }
  return DeviceStatus::kTimeout;
}

DeviceStatus SimLine::next_frame(cv::Mat& image, std::int32_t exposure_us, std::int64_t& timestamp_ns) {
  std::lock_guard lock(mutex_);
  if (stalled_ || state_ != State::kInPass) return DeviceStatus::kTimeout;
  if (frame_ == faults_.camera_stall_frame && faults_.camera_stall_ms > 0) {
    const WallClock::time_point now = WallClock::now();
    if (!stall_started_) {
      stall_started_ = true;
      stall_until_ = now + std::chrono::milliseconds(faults_.camera_stall_ms);
    }
    if (now < stall_until_) return DeviceStatus::kTimeout;
  }
  const std::uint8_t* memo =
      memo_slot_ >= 0 ? memo_.find(static_cast<std::size_t>(memo_slot_), frame_, exposure_us, laser_on_) : nullptr;
  if (memo != nullptr) {
    const auto& k = cell_.rig().params.camera.intrinsics;
    image.create(k.height_px, k.width_px, CV_8UC1);
    for (int y = 0; y < image.rows; ++y) {
      std::memcpy(image.ptr<std::uint8_t>(y), memo + static_cast<std::size_t>(y) * static_cast<std::size_t>(image.cols),
                  static_cast<std::size_t>(image.cols));
    }
  } else {
    if (!scene_ready_) {
      if (auto ok = cell_.begin_pass(current_); !ok) return DeviceStatus::kIoError;
      scene_ready_ = true;
    }
    cell_.render_frame(frame_, exposure_us, image, nullptr, laser_on_);
    if (memo_slot_ >= 0) {
      memo_.store(static_cast<std::size_t>(memo_slot_), frame_, exposure_us, laser_on_, image.data, image.step);
    }
  }
  if (frame_ == faults_.encoder_glitch_frame) {
    encoder_ok_from_ = WallClock::now() + std::chrono::milliseconds(faults_.encoder_glitch_ms);
  }
  counts_ = pass_start_counts_ + cell_.frame_info(frame_).encoder_counts;
  timestamp_ns = now_ns_locked();
  ++frame_;
  if (frame_ >= cell_.frame_count()) {
    state_ = State::kIdle;
    falling_pending_ = true;
  }
  return DeviceStatus::kOk;
}

void SimLine::set_output(drivers::Output line, bool active) {
  std::lock_guard lock(mutex_);
  (line == drivers::Output::kLaserEnable ? laser_on_ : trigger_level_) = active;
}

bool SimLine::output(drivers::Output line) const {
  std::lock_guard lock(mutex_);
  return line == drivers::Output::kLaserEnable ? laser_on_ : trigger_level_;
}

bool SimLine::part_present() const {
  std::lock_guard lock(mutex_);
  return state_ == State::kInPass || falling_pending_;
}

std::int64_t SimLine::encoder_counts() const {
  std::lock_guard lock(mutex_);
  return counts_;
}

bool SimLine::encoder_readable() const {
  std::lock_guard lock(mutex_);
  return WallClock::now() >= encoder_ok_from_;
}

std::uint64_t SimLine::trigger_pulses() const {
  std::lock_guard lock(mutex_);
  return trigger_pulses_;
}

void SimLine::count_trigger_pulse() {
  std::lock_guard lock(mutex_);
  ++trigger_pulses_;
}

// --- camera ----------------------------------------------------------------------------------------------
SimCamera::SimCamera(SimLine& line, int buffer_count, std::int32_t exposure_us)
    : line_(line),
      buffers_(static_cast<std::size_t>(buffer_count)),
      in_use_(buffers_.size(), false),
      exposure_us_(exposure_us) {}

Status SimCamera::start() {
  if (buffers_.empty()) return make_error("simulated camera: needs at least one buffer");
  started_ = true;
  return {};
}

void SimCamera::stop() {
  started_ = false;
}

DeviceStatus SimCamera::set_exposure_us(std::int32_t exposure_us) {
  if (exposure_us <= 0) return DeviceStatus::kInvalidArgument;
  exposure_us_ = exposure_us;
  return DeviceStatus::kOk;
}

DeviceStatus SimCamera::grab(drivers::Frame& out, int /*timeout_ms: simulated time does not wait*/) {
  if (!started_) return DeviceStatus::kNotStarted;
  std::size_t index = 0;
  while (index < in_use_.size() && in_use_[index]) ++index;
  if (index == in_use_.size()) return DeviceStatus::kIoError;  // every buffer is held: the caller forgot release()
  std::int64_t timestamp_ns = 0;
  const DeviceStatus status = line_.next_frame(buffers_[index], exposure_us_, timestamp_ns);
  if (status != DeviceStatus::kOk) return status;
  in_use_[index] = true;
  const cv::Mat& image = buffers_[index];
  out.data = image.data;
  out.width_px = image.cols;
  out.height_px = image.rows;
  out.stride_bytes = static_cast<int>(image.step);
  out.sequence = sequence_++;
  out.timestamp_ns = timestamp_ns;
  out.exposure_us = exposure_us_;
  out.buffer_index = static_cast<std::int32_t>(index);
  return DeviceStatus::kOk;
}

void SimCamera::release(const drivers::Frame& frame) {
  if (frame.buffer_index >= 0 && static_cast<std::size_t>(frame.buffer_index) < in_use_.size()) {
    in_use_[static_cast<std::size_t>(frame.buffer_index)] = false;
  }
}

// --- digital I/O -----------------------------------------------------------------------------------------
Status SimDigitalIo::open() {
  debounce_.reset(line_.part_present(), line_.now_ns());
  open_ = true;
  return {};
}

void SimDigitalIo::close() {
  if (open_) line_.set_output(drivers::Output::kLaserEnable, false);  // a closed controller leaves the laser off
  open_ = false;
}

DeviceStatus SimDigitalIo::set(drivers::Output line, bool active) {
  if (!open_) return DeviceStatus::kNotStarted;
  line_.set_output(line, active);
  return DeviceStatus::kOk;
}

DeviceStatus SimDigitalIo::pulse(drivers::Output line, std::int32_t width_us) {
  if (!open_) return DeviceStatus::kNotStarted;
  if (width_us <= 0) return DeviceStatus::kInvalidArgument;
  line_.set_output(line, true);
  line_.set_output(line, false);
  if (line == drivers::Output::kCameraTrigger) line_.count_trigger_pulse();
  return DeviceStatus::kOk;
}

DeviceStatus SimDigitalIo::read(drivers::Input /*line*/, bool& active) {
  if (!open_) return DeviceStatus::kNotStarted;
  active = line_.part_present();
  return DeviceStatus::kOk;
}

DeviceStatus SimDigitalIo::wait_edge(drivers::EdgeEvent& out, int /*timeout_ms: simulated time does not wait*/) {
  if (!open_) return DeviceStatus::kNotStarted;
  for (;;) {
    if (debounce_.unsettled() && line_.now_ns() >= debounce_.settle_at_ns()) {
      out.input = drivers::Input::kPartPresent;
      out.timestamp_ns = debounce_.settle();
      out.edge = debounce_.state() ? drivers::Edge::kRising : drivers::Edge::kFalling;
      return DeviceStatus::kOk;
    }
    drivers::EdgeEvent raw;
    const DeviceStatus status = line_.next_edge(raw);
    if (status != DeviceStatus::kOk) return status;
    if (debounce_.on_edge(raw.edge == drivers::Edge::kRising, raw.timestamp_ns)) {
      out = raw;
      return DeviceStatus::kOk;
    }
    ++bounces_;
  }
}

// --- encoder ---------------------------------------------------------------------------------------------
Status SimEncoder::open() {
  offset_ = line_.encoder_counts();
  open_ = true;
  return {};
}

void SimEncoder::close() {
  open_ = false;
}

DeviceStatus SimEncoder::read_counts(std::int64_t& counts) {
  if (!open_) return DeviceStatus::kNotStarted;
  if (!line_.encoder_readable()) return DeviceStatus::kIoError;
  counts = line_.encoder_counts() - offset_;
  return DeviceStatus::kOk;
}

}  // namespace cellsight::sim
