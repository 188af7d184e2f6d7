// V4L2Camera against a fake V4L2 device behind SysSeam: formats, buffers, streaming, exposure, faults, teardown.
#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/mman.h>
#include <time.h>

#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "drivers/camera/v4l2_camera.hpp"
#include "drivers/sys_seam.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using cellsight::Status;
using cellsight::drivers::DeviceStatus;
using cellsight::drivers::Frame;
using cellsight::drivers::RealSys;
using cellsight::drivers::SysSeam;
using cellsight::drivers::V4L2Camera;
using cellsight::drivers::V4L2CameraConfig;
// Proves grab()/release()/set_exposure_us() never reach the heap.
using cellsight::test::AllocationWindow;

constexpr int kFakeFd = 7;
constexpr std::uint32_t kOffsetStride = 0x100000;  // mmap cookie per buffer, like vb2's PLANE_INDEX_SHIFT
constexpr std::uint32_t kTriggerControlId = V4L2_CID_USER_BASE + 0x1000;  // a driver-private control
constexpr std::int64_t kNsPerSecond = 1'000'000'000;

std::int64_t now_ns() {
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<std::int64_t>(now.tv_sec) * kNsPerSecond + now.tv_nsec;
}

// V4L2 timestamps have microsecond resolution; steps of a test that compare times must be further apart.
void let_time_pass() {
  const std::int64_t until = now_ns() + 5'000;
  while (now_ns() < until) {
  }
}

// Fixed-capacity FIFO of buffer indices: the fake must not allocate inside QBUF/DQBUF either.
class IndexRing {
 public:
  void push(std::uint32_t value) {
    slots_[(head_ + size_) % slots_.size()] = value;
    ++size_;
  }
  std::uint32_t pop() {
    std::uint32_t value = slots_[head_];
    head_ = (head_ + 1) % slots_.size();
    --size_;
    return value;
  }
  [[nodiscard]] bool empty() const { return size_ == 0; }
  void clear() { head_ = size_ = 0; }

 private:
  std::array<std::uint32_t, 64> slots_{};
  std::size_t head_ = 0;
  std::size_t size_ = 0;
};

// A V4L2 single-planar capture device with vb2-like rules: buffers move user -> queued (QBUF) -> done (the
// sensor captured into it) -> user (DQBUF); REQBUFS(0) fails with EBUSY while streaming or while mapped.
class FakeV4L2Device final : public SysSeam {
 public:
  struct Options {
    std::string path = "/dev/video-fake";
    std::uint32_t width = 40;
    std::uint32_t height = 30;
    std::uint32_t padding_bytes = 24;  // bytesperline = width * bpp + padding: the driver must honour the stride
    std::vector<std::uint32_t> formats{V4L2_PIX_FMT_GREY};
    std::uint32_t max_buffers = 8;
    std::uint32_t capabilities = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
    bool has_exposure = true;
    std::int32_t exposure_min = 1;  // 100 µs units
    std::int32_t exposure_max = 5000;
    std::int32_t exposure_step = 1;
    std::int32_t exposure_default = 100;
    bool has_trigger = false;
  };
  enum class Call { kStreamOn, kStreamOff, kMmap, kMunmap, kAllocate, kFree, kClose };
  struct Capture {
    bool dropped = false;
    std::int32_t exposure_units = 0;
    std::int64_t timestamp_ns = 0;  // truncated to µs like the V4L2 timeval
  };

  explicit FakeV4L2Device(Options options) : options_(std::move(options)) {
    exposure_units_ = options_.exposure_default;
    injections_.reserve(16);
    captures_.reserve(256);
  }

  // ---- the sensor and the test's levers ----

  // The luma of pixel (x, y) in the frame with kernel sequence `sequence`.
  static std::uint8_t pattern(std::uint32_t x, std::uint32_t y, std::uint32_t sequence) {
    return static_cast<std::uint8_t>(x * 7u + y * 13u + sequence * 29u);
  }
  // Exposes one frame into the oldest queued buffer and returns its sequence; -1 when no buffer was queued (the
  // frame is dropped, but the sequence advances, as in vb2).
  int capture(bool error_flag = false, std::uint32_t bytes_used = 0) {
    const std::uint32_t sequence = sequence_++;
    Capture truth;
    truth.exposure_units = exposure_units_;
    truth.timestamp_ns = now_ns() / 1000 * 1000;
    if (!streaming_ || queued_.empty()) {
      truth.dropped = true;
      captures_.push_back(truth);
      return -1;
    }
    const std::uint32_t index = queued_.pop();
    Buffer& buffer = buffers_[index];
    const bool yuyv = pixel_format_ == V4L2_PIX_FMT_YUYV;
    for (std::uint32_t y = 0; y < options_.height; ++y) {
      std::uint8_t* line = buffer.memory.data() + static_cast<std::size_t>(y) * bytes_per_line_;
      for (std::uint32_t x = 0; x < options_.width; ++x) {
        if (yuyv) {
          const std::size_t luma = 2 * static_cast<std::size_t>(x);
          line[luma] = pattern(x, y, sequence);
          line[luma + 1] = static_cast<std::uint8_t>(0x80u + 3u * x + sequence);  // U or V: must not leak in
        } else {
          line[x] = pattern(x, y, sequence);
        }
      }
      for (std::uint32_t pad = options_.width * (yuyv ? 2u : 1u); pad < bytes_per_line_; ++pad) line[pad] = 0xEE;
    }
    buffer.state = State::kDone;
    buffer.sequence = sequence;
    buffer.timestamp_ns = truth.timestamp_ns;
    buffer.bytes_used = bytes_used != 0 ? bytes_used : size_image_;
    buffer.error = error_flag;
    done_.push(index);
    captures_.push_back(truth);
    return static_cast<int>(sequence);
  }
  [[nodiscard]] const Capture& truth(int sequence) const { return captures_.at(static_cast<std::size_t>(sequence)); }

  // The next `times` calls of `request` fail with -error (DQBUF with EIO also dequeues a done buffer, as some
  // drivers do on signal loss).
  void inject(unsigned long request, int error, int times = 1) { injections_.push_back({request, -error, times}); }
  // Overrides poll()'s answer (0: model behaviour).
  void set_poll_revents(short revents) { poll_revents_ = revents; }
  // Unplugged: every ioctl says ENODEV and poll says POLLERR | POLLHUP, like an unregistered video node.
  void vanish() { vanished_ = true; }

  [[nodiscard]] bool is_open() const { return open_; }
  [[nodiscard]] int opens() const { return opens_; }
  [[nodiscard]] int closes() const { return closes_; }
  [[nodiscard]] std::size_t mapped_count() const {
    return static_cast<std::size_t>(
        std::count_if(buffers_.begin(), buffers_.end(), [](const Buffer& b) { return b.mapped; }));
  }
  [[nodiscard]] std::size_t allocated_buffers() const { return buffers_.size(); }
  [[nodiscard]] bool streaming() const { return streaming_; }
  [[nodiscard]] int busy_refusals() const { return busy_refusals_; }
  [[nodiscard]] std::int32_t exposure_units() const { return exposure_units_; }
  [[nodiscard]] std::int32_t exposure_auto() const { return exposure_auto_; }
  [[nodiscard]] std::int32_t trigger_value() const { return trigger_value_; }
  [[nodiscard]] int exposure_writes() const { return exposure_writes_; }
  [[nodiscard]] const std::vector<Call>& calls() const { return calls_; }
  [[nodiscard]] std::size_t first(Call call) const {
    return static_cast<std::size_t>(std::find(calls_.begin(), calls_.end(), call) - calls_.begin());
  }
  [[nodiscard]] std::size_t last(Call call) const {
    auto it = std::find(calls_.rbegin(), calls_.rend(), call);
    return it == calls_.rend() ? calls_.size() : static_cast<std::size_t>(calls_.rend() - it - 1);
  }
  // True when the exposure value is one the control accepts.
  [[nodiscard]] bool valid_exposure(std::int32_t units) const {
    return units >= options_.exposure_min && units <= options_.exposure_max &&
           (units - options_.exposure_min) % options_.exposure_step == 0;
  }

  // ---- SysSeam ----

  int open(const char* path, int flags) override {
    if (options_.path != path) return -ENOENT;
    if (open_) return -EBUSY;
    if ((flags & O_NONBLOCK) == 0) return -EINVAL;  // the driver must never block in DQBUF
    open_ = true;
    ++opens_;
    return kFakeFd;
  }
  int close(int fd) override {
    if (fd != kFakeFd || !open_) return -EBADF;
    open_ = false;
    ++closes_;
    calls_.push_back(Call::kClose);
    return 0;
  }
  int mmap(std::size_t length, int prot, int flags, int fd, off_t offset, void*& mapped) override {
    if (fd != kFakeFd || !open_ || (prot & PROT_READ) == 0 || (flags & MAP_SHARED) == 0) return -EINVAL;
    const auto index = static_cast<std::size_t>(offset) / kOffsetStride;
    if (static_cast<std::size_t>(offset) % kOffsetStride != 0 || index >= buffers_.size()) return -EINVAL;
    if (length != buffers_[index].memory.size()) return -EINVAL;
    buffers_[index].mapped = true;
    mapped = buffers_[index].memory.data();
    calls_.push_back(Call::kMmap);
    return 0;
  }
  int munmap(void* address, std::size_t length) override {
    for (Buffer& buffer : buffers_) {
      if (buffer.memory.data() == address && buffer.memory.size() == length && buffer.mapped) {
        buffer.mapped = false;
        calls_.push_back(Call::kMunmap);
        return 0;
      }
    }
    return -EINVAL;
  }
  int poll(pollfd* fds, nfds_t count, int /*timeout_ms*/) override {
    if (count != 1 || fds[0].fd != kFakeFd) return -EINVAL;
    fds[0].revents = 0;
    if (vanished_) {
      fds[0].revents = POLLERR | POLLHUP | POLLPRI;
    } else if (poll_revents_ != 0) {
      fds[0].revents = poll_revents_;
    } else if (!streaming_ || (queued_.empty() && done_.empty())) {
      fds[0].revents = POLLERR;  // vb2: nothing can ever arrive
    } else if (!done_.empty()) {
      fds[0].revents = POLLIN | POLLRDNORM;
    }
    return fds[0].revents != 0 ? 1 : 0;  // a timeout returns at once: tests need no real waiting
  }
  ssize_t read(int /*fd*/, void* /*buffer*/, std::size_t /*count*/) override { return -EINVAL; }

  int ioctl(int fd, unsigned long request, void* arg) override {
    if (fd != kFakeFd || !open_) return -EBADF;
    if (vanished_) return -ENODEV;
    for (Injection& injection : injections_) {
      if (injection.request != request || injection.times <= 0) continue;
      --injection.times;
      if (request == VIDIOC_DQBUF && injection.result == -EIO && !done_.empty()) {
        const std::uint32_t index = done_.pop();
        buffers_[index].state = State::kUser;
        static_cast<v4l2_buffer*>(arg)->index = index;
      }
      return injection.result;
    }
    switch (request) {
      case VIDIOC_QUERYCAP: return query_capabilities(*static_cast<v4l2_capability*>(arg));
      case VIDIOC_ENUM_FMT: return enumerate_format(*static_cast<v4l2_fmtdesc*>(arg));
      case VIDIOC_G_FMT: return get_format(*static_cast<v4l2_format*>(arg));
      case VIDIOC_S_FMT: return set_format(*static_cast<v4l2_format*>(arg));
      case VIDIOC_REQBUFS: return request_buffers(*static_cast<v4l2_requestbuffers*>(arg));
      case VIDIOC_QUERYBUF: return query_buffer(*static_cast<v4l2_buffer*>(arg));
      case VIDIOC_QBUF: return queue_buffer(*static_cast<v4l2_buffer*>(arg));
      case VIDIOC_DQBUF: return dequeue_buffer(*static_cast<v4l2_buffer*>(arg));
      case VIDIOC_STREAMON: return stream(*static_cast<int*>(arg), true);
      case VIDIOC_STREAMOFF: return stream(*static_cast<int*>(arg), false);
      case VIDIOC_QUERYCTRL: return query_control(*static_cast<v4l2_queryctrl*>(arg));
      case VIDIOC_G_CTRL: return get_control(*static_cast<v4l2_control*>(arg));
      case VIDIOC_S_CTRL: return set_control(*static_cast<v4l2_control*>(arg));
      default: return -ENOTTY;
    }
  }

 private:
  enum class State { kUser, kQueued, kDone };
  struct Buffer {
    std::vector<std::uint8_t> memory;
    State state = State::kUser;
    bool mapped = false;
    std::uint32_t sequence = 0;
    std::int64_t timestamp_ns = 0;
    std::uint32_t bytes_used = 0;
    bool error = false;
  };
  struct Injection {
    unsigned long request;
    int result;
    int times;
  };
  struct Control {
    std::uint32_t id;
    const char* name;
    std::uint32_t type;
    std::int32_t minimum, maximum, step, default_value;
  };

  [[nodiscard]] std::uint32_t bytes_per_pixel() const { return pixel_format_ == V4L2_PIX_FMT_YUYV ? 2u : 1u; }

  int query_capabilities(v4l2_capability& caps) const {
    caps = v4l2_capability{};
    std::memcpy(caps.driver, "fakecam", 8);
    std::memcpy(caps.card, "Fake laser camera", 18);
    caps.capabilities = options_.capabilities | V4L2_CAP_DEVICE_CAPS;
    caps.device_caps = options_.capabilities;
    return 0;
  }
  int enumerate_format(v4l2_fmtdesc& description) const {
    if (description.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || description.index >= options_.formats.size()) return -EINVAL;
    description.pixelformat = options_.formats[description.index];
    return 0;
  }
  int get_format(v4l2_format& format) const {
    if (format.type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return -EINVAL;
    format.fmt.pix.width = options_.width;
    format.fmt.pix.height = options_.height;
    format.fmt.pix.pixelformat = pixel_format_;
    format.fmt.pix.field = V4L2_FIELD_NONE;
    format.fmt.pix.bytesperline = bytes_per_line_;
    format.fmt.pix.sizeimage = size_image_;
    return 0;
  }
  int set_format(v4l2_format& format) {
    if (format.type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return -EINVAL;
    if (streaming_ || !buffers_.empty()) return -EBUSY;
    const auto& offered = options_.formats;
    // Like real drivers: an unsupported format or size is replaced, not refused.
    pixel_format_ = std::find(offered.begin(), offered.end(), format.fmt.pix.pixelformat) != offered.end()
                        ? format.fmt.pix.pixelformat
                        : offered.front();
    bytes_per_line_ = options_.width * bytes_per_pixel() + options_.padding_bytes;
    size_image_ = bytes_per_line_ * options_.height;
    return get_format(format);
  }
  int request_buffers(v4l2_requestbuffers& request) {
    if (request.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || request.memory != V4L2_MEMORY_MMAP) return -EINVAL;
    if (streaming_ || mapped_count() != 0) {
      ++busy_refusals_;
      return -EBUSY;
    }
    buffers_.clear();
    queued_.clear();
    done_.clear();
    if (request.count == 0) {
      calls_.push_back(Call::kFree);
      return 0;
    }
    request.count = std::min(request.count, options_.max_buffers);
    buffers_.resize(request.count);
    for (Buffer& buffer : buffers_) buffer.memory.assign(size_image_, 0);
    calls_.push_back(Call::kAllocate);
    return 0;
  }
  int query_buffer(v4l2_buffer& buffer) const {
    if (buffer.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || buffer.index >= buffers_.size()) return -EINVAL;
    buffer.length = static_cast<std::uint32_t>(buffers_[buffer.index].memory.size());
    buffer.m.offset = buffer.index * kOffsetStride;
    return 0;
  }
  int queue_buffer(v4l2_buffer& buffer) {
    if (buffer.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || buffer.memory != V4L2_MEMORY_MMAP) return -EINVAL;
    if (buffer.index >= buffers_.size() || buffers_[buffer.index].state != State::kUser) return -EINVAL;
    buffers_[buffer.index].state = State::kQueued;
    queued_.push(buffer.index);
    return 0;
  }
  int dequeue_buffer(v4l2_buffer& buffer) {
    if (buffer.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || buffer.memory != V4L2_MEMORY_MMAP) return -EINVAL;
    if (!streaming_) return -EINVAL;
    if (done_.empty()) return -EAGAIN;  // opened O_NONBLOCK
    const std::uint32_t index = done_.pop();
    Buffer& source = buffers_[index];
    source.state = State::kUser;
    buffer.index = index;
    buffer.bytesused = source.bytes_used;
    buffer.sequence = source.sequence;
    buffer.flags = V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC | (source.error ? V4L2_BUF_FLAG_ERROR : 0u);
    buffer.timestamp.tv_sec = static_cast<time_t>(source.timestamp_ns / kNsPerSecond);
    buffer.timestamp.tv_usec = static_cast<suseconds_t>(source.timestamp_ns % kNsPerSecond / 1000);
    buffer.length = static_cast<std::uint32_t>(source.memory.size());
    return 0;
  }
  int stream(int type, bool on) {
    if (type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return -EINVAL;
    if (on) {
      if (buffers_.empty()) return -EINVAL;
      streaming_ = true;
      calls_.push_back(Call::kStreamOn);
      return 0;
    }
    streaming_ = false;
    for (Buffer& buffer : buffers_) buffer.state = State::kUser;  // STREAMOFF hands every buffer back
    queued_.clear();
    done_.clear();
    calls_.push_back(Call::kStreamOff);
    return 0;
  }
  [[nodiscard]] std::vector<Control> controls() const {
    std::vector<Control> list;
    if (options_.has_trigger) list.push_back({kTriggerControlId, "Trigger Mode", V4L2_CTRL_TYPE_BOOLEAN, 0, 1, 1, 0});
    if (options_.has_exposure) {
      list.push_back({V4L2_CID_EXPOSURE_AUTO, "Auto Exposure", V4L2_CTRL_TYPE_MENU, 0, 3, 1, 3});
      list.push_back({V4L2_CID_EXPOSURE_ABSOLUTE, "Exposure Time, Absolute", V4L2_CTRL_TYPE_INTEGER,
                      options_.exposure_min, options_.exposure_max, options_.exposure_step, options_.exposure_default});
    }
    return list;  // sorted by id, as the NEXT_CTRL enumeration requires
  }
  int query_control(v4l2_queryctrl& query) const {
    const bool next = (query.id & V4L2_CTRL_FLAG_NEXT_CTRL) != 0;
    const std::uint32_t id = query.id & ~(V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND);
    for (const Control& control : controls()) {
      if (next ? control.id > id : control.id == id) {
        query = v4l2_queryctrl{};
        query.id = control.id;
        query.type = control.type;
        std::strncpy(reinterpret_cast<char*>(query.name), control.name, sizeof query.name - 1);
        query.minimum = control.minimum;
        query.maximum = control.maximum;
        query.step = control.step;
        query.default_value = control.default_value;
        return 0;
      }
    }
    return -EINVAL;
  }
  int get_control(v4l2_control& control) const {
    if (options_.has_exposure && control.id == V4L2_CID_EXPOSURE_ABSOLUTE) {
      control.value = exposure_units_;
      return 0;
    }
    if (options_.has_exposure && control.id == V4L2_CID_EXPOSURE_AUTO) {
      control.value = exposure_auto_;
      return 0;
    }
    return -EINVAL;
  }
  int set_control(v4l2_control& control) {
    if (options_.has_exposure && control.id == V4L2_CID_EXPOSURE_ABSOLUTE) {
      // Stricter than the kernel, which would clamp silently: the driver must send valid values itself.
      if (!valid_exposure(control.value)) return -ERANGE;
      exposure_units_ = control.value;
      ++exposure_writes_;
      return 0;
    }
    if (options_.has_exposure && control.id == V4L2_CID_EXPOSURE_AUTO) {
      // A UVC-style menu: only MANUAL and APERTURE_PRIORITY exist.
      if (control.value != V4L2_EXPOSURE_MANUAL && control.value != V4L2_EXPOSURE_APERTURE_PRIORITY) return -EINVAL;
      exposure_auto_ = control.value;
      return 0;
    }
    if (options_.has_trigger && control.id == kTriggerControlId) {
      if (control.value < 0 || control.value > 1) return -ERANGE;
      trigger_value_ = control.value;
      return 0;
    }
    return -EINVAL;
  }

  Options options_;
  bool open_ = false;
  bool vanished_ = false;
  bool streaming_ = false;
  int opens_ = 0;
  int closes_ = 0;
  int busy_refusals_ = 0;
  std::uint32_t pixel_format_ = 0;
  std::uint32_t bytes_per_line_ = 0;
  std::uint32_t size_image_ = 0;
  std::vector<Buffer> buffers_;
  IndexRing queued_;
  IndexRing done_;
  std::uint32_t sequence_ = 0;
  std::int32_t exposure_units_ = 0;
  std::int32_t exposure_auto_ = V4L2_EXPOSURE_APERTURE_PRIORITY;
  std::int32_t trigger_value_ = 0;
  int exposure_writes_ = 0;
  short poll_revents_ = 0;
  std::vector<Injection> injections_;
  std::vector<Capture> captures_;
  std::vector<Call> calls_;
};

V4L2CameraConfig config_for(const FakeV4L2Device::Options& options) {
  V4L2CameraConfig config;
  config.device = options.path;
  config.width_px = static_cast<int>(options.width);
  config.height_px = static_cast<int>(options.height);
  config.buffer_count = 4;
  config.poll_timeout_ms = 0;
  return config;
}

// Pixels of `frame` that differ from the fake sensor's pattern for kernel sequence `sequence`.
int pixel_mismatches(const Frame& frame, int sequence) {
  int mismatches = 0;
  for (int y = 0; y < frame.height_px; ++y) {
    for (int x = 0; x < frame.width_px; ++x) {
      const std::uint8_t expected = FakeV4L2Device::pattern(
          static_cast<std::uint32_t>(x), static_cast<std::uint32_t>(y), static_cast<std::uint32_t>(sequence));
      if (frame.data[static_cast<std::size_t>(y) * static_cast<std::size_t>(frame.stride_bytes) +
                     static_cast<std::size_t>(x)] != expected) {
        ++mismatches;
      }
    }
  }
  return mismatches;
}

// After stop() or a failed start(): nothing mapped, nothing allocated, descriptor closed exactly once per open.
void require_clean(const FakeV4L2Device& fake) {
  CHECK_FALSE(fake.is_open());
  CHECK(fake.closes() == fake.opens());
  CHECK(fake.mapped_count() == 0);
  CHECK(fake.allocated_buffers() == 0);
  CHECK_FALSE(fake.streaming());
  CHECK(fake.busy_refusals() == 0);
}

}  // namespace

SCENARIO("frames arrive with the sensor's pixels, a running sequence, timestamps and exposure", "[camera]") {
  GIVEN("a GREY camera whose lines are padded beyond the image width") {
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    REQUIRE(camera.start().ok());
    REQUIRE_FALSE(camera.converts_yuyv());
    REQUIRE(camera.buffer_count() == 4);
    REQUIRE(fake.exposure_auto() == V4L2_EXPOSURE_MANUAL);

    WHEN("the sensor captures three frames and each is grabbed and released") {
      std::vector<int> sequences(3);
      for (int& sequence : sequences) sequence = fake.capture();
      std::vector<Frame> frames(3);
      std::vector<int> mismatches;
      for (Frame& frame : frames) {
        REQUIRE(camera.grab(frame, 10) == DeviceStatus::kOk);
        mismatches.push_back(pixel_mismatches(frame, sequences[static_cast<std::size_t>(frame.sequence)]));
        camera.release(frame);
      }
      THEN("every pixel matches, the sequence counts 0, 1, 2 and time and exposure are the sensor's") {
        CHECK(mismatches == std::vector<int>{0, 0, 0});
        for (std::size_t i = 0; i < frames.size(); ++i) {
          CHECK(frames[i].sequence == i);
          CHECK(frames[i].width_px == 40);
          CHECK(frames[i].height_px == 30);
          CHECK(frames[i].stride_bytes == 40 + 24);
          CHECK(frames[i].timestamp_ns == fake.truth(sequences[i]).timestamp_ns);
          CHECK(frames[i].exposure_us == fake.truth(sequences[i]).exposure_units * 100);
        }
        CHECK(camera.stats().frames == 3);
        CHECK(camera.stats().dropped_frames == 0);
      }
    }
    WHEN("the exposure changes between two captures that are grabbed only afterwards") {
      const int before = fake.capture();
      let_time_pass();
      REQUIRE(camera.set_exposure_us(25'000) == DeviceStatus::kOk);
      let_time_pass();
      const int after = fake.capture();
      Frame first;
      Frame second;
      REQUIRE(camera.grab(first, 10) == DeviceStatus::kOk);
      REQUIRE(camera.grab(second, 10) == DeviceStatus::kOk);
      THEN("each frame reports the exposure it was captured with, not the latest one") {
        CHECK(fake.truth(before).exposure_units != fake.truth(after).exposure_units);
        CHECK(first.exposure_us == fake.truth(before).exposure_units * 100);
        CHECK(second.exposure_us == fake.truth(after).exposure_units * 100);
        CHECK(second.exposure_us == 25'000);
      }
      camera.release(first);
      camera.release(second);
    }
    WHEN("the camera is stopped") {
      (void)fake.capture();
      Frame held;
      REQUIRE(camera.grab(held, 10) == DeviceStatus::kOk);  // a frame still borrowed at stop()
      camera.stop();
      THEN("STREAMOFF comes first, every buffer is unmapped before they are freed, and the descriptor closes last") {
        using Call = FakeV4L2Device::Call;
        CHECK(fake.last(Call::kStreamOff) < fake.first(Call::kMunmap));
        CHECK(fake.last(Call::kMunmap) < fake.last(Call::kFree));
        CHECK(fake.last(Call::kFree) < fake.last(Call::kClose));
        CHECK(fake.last(Call::kClose) == fake.calls().size() - 1);
        require_clean(fake);
      }
      AND_THEN("a second stop() and a grab() after it are harmless") {
        camera.stop();
        Frame frame;
        CHECK(camera.grab(frame, 0) == DeviceStatus::kNotStarted);
        CHECK(camera.set_exposure_us(1000) == DeviceStatus::kNotStarted);
        require_clean(fake);
      }
    }
  }
}

SCENARIO("exposure in µs becomes the nearest valid 100 µs control value inside the control's range", "[camera]") {
  GIVEN("a control from 300 µs to 200 ms in steps of 200 µs that refuses anything else") {
    FakeV4L2Device::Options options;
    options.exposure_min = 3;
    options.exposure_max = 2000;
    options.exposure_step = 2;
    options.exposure_default = 51;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    REQUIRE(camera.start().ok());
    CHECK(camera.exposure_min_us() == 300);
    CHECK(camera.exposure_max_us() == 200'000);

    WHEN("many exposures, below, inside and above the range, are requested") {
      std::mt19937 random(20240611);
      std::vector<std::int32_t> requests{1,
                                         99,
                                         250,
                                         300,
                                         349,
                                         350,
                                         351,
                                         399,
                                         400,
                                         401,
                                         12'345,
                                         199'899,
                                         199'900,
                                         200'000,
                                         250'000,
                                         1'000'000,
                                         std::numeric_limits<std::int32_t>::max()};
      std::uniform_int_distribution<std::int32_t> any(1, 300'000);
      for (int i = 0; i < 300; ++i) requests.push_back(any(random));
      int refused = 0;
      int not_nearest = 0;
      int invalid = 0;
      for (std::int32_t request : requests) {
        if (camera.set_exposure_us(request) != DeviceStatus::kOk) {
          ++refused;
          continue;
        }
        const std::int32_t sent = fake.exposure_units();
        if (!fake.valid_exposure(sent)) ++invalid;
        // Brute force: the smallest distance any accepted value has to the request.
        std::int64_t best_us = std::numeric_limits<std::int64_t>::max();
        for (std::int32_t units = options.exposure_min; units <= options.exposure_max; ++units) {
          if (fake.valid_exposure(units)) {
            best_us = std::min(best_us, std::abs(static_cast<std::int64_t>(units) * 100 - request));
          }
        }
        if (std::abs(static_cast<std::int64_t>(sent) * 100 - request) != best_us) {
          ++not_nearest;
          UNSCOPED_INFO("request " << request << " us sent " << sent << " units");
        }
      }
      THEN("each is accepted by the device and is as close to the request as the control allows") {
        CHECK(refused == 0);
        CHECK(invalid == 0);
        CHECK(not_nearest == 0);
        CHECK(fake.exposure_writes() == static_cast<int>(requests.size()));
      }
    }
    WHEN("a frame is taken after an exposure above the range was requested") {
      REQUIRE(camera.set_exposure_us(900'000) == DeviceStatus::kOk);
      let_time_pass();
      const int sequence = fake.capture();
      Frame frame;
      REQUIRE(camera.grab(frame, 10) == DeviceStatus::kOk);
      THEN("the frame reports the clamped exposure the device actually used") {
        CHECK(fake.truth(sequence).exposure_units == 1999);
        CHECK(frame.exposure_us == 199'900);
      }
      camera.release(frame);
    }
    WHEN("a non-positive exposure is requested") {
      const std::int32_t before = fake.exposure_units();
      THEN("it is refused and the device is untouched") {
        CHECK(camera.set_exposure_us(0) == DeviceStatus::kInvalidArgument);
        CHECK(camera.set_exposure_us(-5) == DeviceStatus::kInvalidArgument);
        CHECK(fake.exposure_units() == before);
      }
    }
  }
  GIVEN("a configured start-up exposure") {
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.exposure_us = 4'260;
    V4L2Camera camera(fake, config);
    REQUIRE(camera.start().ok());
    THEN("the device receives it in 100 µs units before the first frame") {
      CHECK(fake.exposure_units() == 43);
      const int sequence = fake.capture();
      Frame frame;
      REQUIRE(camera.grab(frame, 10) == DeviceStatus::kOk);
      CHECK(fake.truth(sequence).exposure_units == 43);
      CHECK(frame.exposure_us == 4'300);
      camera.release(frame);
    }
  }
}

SCENARIO("a device that only offers YUYV is converted to mono8", "[camera]") {
  GIVEN("a YUYV-only camera with padded lines") {
    FakeV4L2Device::Options options;
    options.formats = {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_YUYV};
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    REQUIRE(camera.start().ok());

    WHEN("two frames are captured and both are held at the same time") {
      const int first_sequence = fake.capture();
      const int second_sequence = fake.capture();
      Frame first;
      Frame second;
      REQUIRE(camera.grab(first, 10) == DeviceStatus::kOk);
      REQUIRE(camera.grab(second, 10) == DeviceStatus::kOk);
      THEN("each is a packed mono8 image of exactly the luma samples, chroma left out") {
        CHECK(camera.converts_yuyv());
        CHECK(first.stride_bytes == first.width_px);
        CHECK(first.data != second.data);
        CHECK(pixel_mismatches(first, first_sequence) == 0);
        CHECK(pixel_mismatches(second, second_sequence) == 0);
      }
      camera.release(first);
      camera.release(second);
    }
  }
  GIVEN("a device that offers neither GREY nor YUYV") {
    FakeV4L2Device::Options options;
    options.formats = {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_RGB24};
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    Status status = camera.start();
    THEN("start() fails and lists what the device offers") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message,
                 Catch::Contains("/dev/video-fake") && Catch::Contains("MJPG") && Catch::Contains("RGB3"));
      require_clean(fake);
    }
  }
}

SCENARIO("timeouts, I/O errors and a vanished device are reported and survived", "[camera]") {
  FakeV4L2Device::Options options;
  FakeV4L2Device fake(options);
  V4L2Camera camera(fake, config_for(options));
  REQUIRE(camera.start().ok());
  Frame frame;

  WHEN("nothing has been captured") {
    THEN("grab() times out") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kTimeout);
      CHECK(camera.stats().timeouts == 1);
    }
  }
  WHEN("poll() wakes but DQBUF answers EAGAIN") {
    const int sequence = fake.capture();
    fake.inject(VIDIOC_DQBUF, EAGAIN);
    THEN("that grab() is a timeout and the next one delivers the frame") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kTimeout);
      REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
      CHECK(pixel_mismatches(frame, sequence) == 0);
      camera.release(frame);
    }
  }
  WHEN("DQBUF fails with EIO six times in a row, each time taking a buffer with it") {
    std::vector<DeviceStatus> statuses;
    for (int i = 0; i < 6; ++i) {
      (void)fake.capture();
      fake.inject(VIDIOC_DQBUF, EIO);
      statuses.push_back(camera.grab(frame, 0));
    }
    THEN("each is an I/O error, the buffers are requeued and streaming goes on with correct frames") {
      CHECK(statuses == std::vector<DeviceStatus>(6, DeviceStatus::kIoError));
      CHECK(camera.stats().io_errors == 6);
      for (int i = 0; i < 8; ++i) {  // more frames than buffers: a leaked buffer would starve the queue
        const int sequence = fake.capture();
        REQUIRE(sequence >= 0);
        REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
        CHECK(pixel_mismatches(frame, sequence) == 0);
        camera.release(frame);
      }
    }
  }
  WHEN("the driver flags a buffer as corrupt or delivers it truncated") {
    (void)fake.capture(true);
    (void)fake.capture(false, 100);
    const DeviceStatus corrupt = camera.grab(frame, 0);
    const DeviceStatus truncated = camera.grab(frame, 0);
    THEN("both are I/O errors and both buffers go back into circulation") {
      CHECK(corrupt == DeviceStatus::kIoError);
      CHECK(truncated == DeviceStatus::kIoError);
      for (int i = 0; i < 8; ++i) {
        const int sequence = fake.capture();
        REQUIRE(sequence >= 0);
        REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
        CHECK(pixel_mismatches(frame, sequence) == 0);
        camera.release(frame);
      }
    }
  }
  WHEN("the caller holds every buffer and the sensor keeps going") {
    std::array<Frame, 4> held;
    for (Frame& f : held) {
      (void)fake.capture();
      REQUIRE(camera.grab(f, 0) == DeviceStatus::kOk);
    }
    const int lost_a = fake.capture();
    const int lost_b = fake.capture();
    const DeviceStatus starved = camera.grab(frame, 0);
    for (Frame& f : held) camera.release(f);
    const int next = fake.capture();
    REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
    THEN("grab() reports the starvation, and the two frames the kernel dropped are counted") {
      CHECK(lost_a == -1);
      CHECK(lost_b == -1);
      CHECK(starved == DeviceStatus::kIoError);
      CHECK(camera.stats().dropped_frames == 2);
      CHECK(frame.sequence == 4);
      CHECK(pixel_mismatches(frame, next) == 0);
      camera.release(frame);
    }
  }
  WHEN("a frame is released twice or a foreign frame is released") {
    (void)fake.capture();
    REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
    camera.release(frame);
    camera.release(frame);
    Frame foreign;
    foreign.buffer_index = 99;
    camera.release(foreign);
    THEN("both are counted and ignored") {
      CHECK(camera.stats().release_errors == 2);
    }
  }
  WHEN("the camera is unplugged mid-stream while the caller holds a frame") {
    (void)fake.capture();
    Frame held;
    REQUIRE(camera.grab(held, 0) == DeviceStatus::kOk);
    (void)fake.capture();
    fake.vanish();
    const DeviceStatus lost = camera.grab(frame, 0);
    THEN("grab() reports the device lost, and keeps doing so without touching it; stop() cleans up") {
      CHECK(lost == DeviceStatus::kDeviceLost);
      CHECK(camera.grab(frame, 0) == DeviceStatus::kDeviceLost);
      CHECK(camera.set_exposure_us(1000) == DeviceStatus::kDeviceLost);
      camera.release(held);
      camera.stop();
      CHECK_FALSE(fake.is_open());
      CHECK(fake.mapped_count() == 0);
    }
  }
  WHEN("poll() says a frame is ready but DQBUF answers ENODEV") {
    (void)fake.capture();
    fake.inject(VIDIOC_DQBUF, ENODEV);
    THEN("the device is lost") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kDeviceLost);
    }
  }
  WHEN("poll() reports only POLLERR and DQBUF answers ENODEV") {
    fake.set_poll_revents(POLLERR);
    fake.inject(VIDIOC_DQBUF, ENODEV);
    THEN("the device is lost") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kDeviceLost);
    }
  }
  WHEN("poll() reports POLLHUP, which only an unregistered video node does") {
    fake.set_poll_revents(POLLERR | POLLHUP);
    (void)fake.capture();
    THEN("the device is lost even before an ioctl fails") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kDeviceLost);
    }
  }
  WHEN("poll() reports POLLERR but the device is still there") {
    fake.set_poll_revents(POLLERR);
    THEN("it is an I/O error, not a lost device") {
      CHECK(camera.grab(frame, 0) == DeviceStatus::kIoError);
      fake.set_poll_revents(0);
      const int sequence = fake.capture();
      REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
      CHECK(pixel_mismatches(frame, sequence) == 0);
      camera.release(frame);
    }
  }
  camera.stop();
  CHECK_FALSE(fake.is_open());
  CHECK(fake.mapped_count() == 0);
}

SCENARIO("start() failures give a clear message and leave nothing behind", "[camera]") {
  GIVEN("a driver that grants only two buffers") {
    FakeV4L2Device::Options options;
    options.max_buffers = 2;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    Status status = camera.start();
    THEN("start() says how many it got and how many are needed, and the buffers are freed") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("granted only 2") && Catch::Contains("at least 4"));
      require_clean(fake);
      CHECK(fake.last(FakeV4L2Device::Call::kFree) < fake.last(FakeV4L2Device::Call::kClose));
    }
    AND_THEN("stop() after the failed start is safe and closes nothing twice") {
      camera.stop();
      camera.stop();
      require_clean(fake);
      CHECK(fake.closes() == 1);
    }
  }
  GIVEN("each ioctl of the start-up sequence failing in turn") {
    const std::vector<unsigned long> requests{VIDIOC_QUERYCAP, VIDIOC_ENUM_FMT, VIDIOC_S_FMT, VIDIOC_S_CTRL,
                                              VIDIOC_REQBUFS,  VIDIOC_QUERYBUF, VIDIOC_QBUF,  VIDIOC_STREAMON};
    THEN("start() fails, undoes what it did in the right order and can be stopped") {
      for (unsigned long request : requests) {
        INFO("failing request 0x" << std::hex << request);
        FakeV4L2Device::Options options;
        FakeV4L2Device fake(options);
        fake.inject(request, EIO);
        V4L2Camera camera(fake, config_for(options));
        Status status = camera.start();
        REQUIRE_FALSE(status.ok());
        CHECK_THAT(status.error().message, Catch::Contains("/dev/video-fake"));
        CHECK_FALSE(camera.started());
        require_clean(fake);
        camera.stop();
        CHECK(fake.closes() == 1);
      }
    }
  }
  GIVEN("a failing mmap of the third buffer") {
    // Wraps the fake to fail one mmap: the first two mappings must be undone.
    class FailingMmap final : public SysSeam {
     public:
      explicit FailingMmap(FakeV4L2Device& inner) : inner_(inner) {}
      int open(const char* path, int flags) override { return inner_.open(path, flags); }
      int close(int fd) override { return inner_.close(fd); }
      int ioctl(int fd, unsigned long request, void* arg) override { return inner_.ioctl(fd, request, arg); }
      int mmap(std::size_t length, int prot, int flags, int fd, off_t offset, void*& mapped) override {
        if (++maps_ == 3) return -ENOMEM;
        return inner_.mmap(length, prot, flags, fd, offset, mapped);
      }
      int munmap(void* address, std::size_t length) override { return inner_.munmap(address, length); }
      int poll(pollfd* fds, nfds_t count, int timeout_ms) override { return inner_.poll(fds, count, timeout_ms); }
      ssize_t read(int fd, void* buffer, std::size_t count) override { return inner_.read(fd, buffer, count); }

     private:
      FakeV4L2Device& inner_;
      int maps_ = 0;
    };
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    FailingMmap seam(fake);
    V4L2Camera camera(seam, config_for(options));
    Status status = camera.start();
    THEN("the two mapped buffers are unmapped before the buffers are freed") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("cannot map buffer 2"));
      require_clean(fake);
    }
  }
  GIVEN("a node that is not a capture device") {
    FakeV4L2Device::Options options;
    options.capabilities = V4L2_CAP_VIDEO_OUTPUT | V4L2_CAP_STREAMING;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    Status status = camera.start();
    THEN("start() names the device and says why") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message,
                 Catch::Contains("Fake laser camera") && Catch::Contains("not a video capture node"));
      require_clean(fake);
    }
  }
  GIVEN("a capture device without streaming I/O") {
    FakeV4L2Device::Options options;
    options.capabilities = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_READWRITE;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    Status status = camera.start();
    THEN("start() refuses it") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("streaming"));
      require_clean(fake);
    }
  }
  GIVEN("a sensor that cannot deliver the configured size") {
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.width_px = 1024;
    config.height_px = 768;
    V4L2Camera camera(fake, config);
    Status status = camera.start();
    THEN("start() names both sizes and the config keys") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message,
                 Catch::Contains("40x30") && Catch::Contains("1024x768") && Catch::Contains("rig.camera.width_px"));
      require_clean(fake);
    }
  }
  GIVEN("a configured buffer count below four") {
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.buffer_count = 2;
    V4L2Camera camera(fake, config);
    Status status = camera.start();
    THEN("start() refuses the config before touching the device") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("camera.buffers"));
      CHECK(fake.opens() == 0);
    }
  }
}

SCENARIO("a camera path that does not exist is reported through the real kernel", "[camera]") {
  GIVEN("the real system-call seam and a device node that cannot exist") {
    RealSys sys;
    V4L2CameraConfig config;
    config.device = "/dev/video-cellsight-test-absent";
    V4L2Camera camera(sys, config);
    WHEN("the camera is started") {
      Status status = camera.start();
      THEN("the message names the path, the reason and the config key, and stop() is safe") {
        REQUIRE_FALSE(status.ok());
        CHECK(status.error().message ==
              "camera: cannot open /dev/video-cellsight-test-absent: No such file or directory (is the camera "
              "connected? check camera.device in config/cellsight.yaml)");
        camera.stop();
        Frame frame;
        CHECK(camera.grab(frame, 0) == DeviceStatus::kNotStarted);
      }
    }
  }
  GIVEN("the real seam and a file that is not a video device") {
    RealSys sys;
    V4L2CameraConfig config;
    config.device = "/dev/null";
    V4L2Camera camera(sys, config);
    Status status = camera.start();
    THEN("start() says it is not a V4L2 device") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("/dev/null is not a V4L2 device"));
    }
  }
}

SCENARIO("external trigger mode is selected through the device's trigger control", "[camera]") {
  GIVEN("a device with a private \"Trigger Mode\" control") {
    FakeV4L2Device::Options options;
    options.has_trigger = true;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.external_trigger = true;
    V4L2Camera camera(fake, config);
    THEN("start() finds it by name and switches it on") {
      REQUIRE(camera.start().ok());
      CHECK(fake.trigger_value() == 1);
    }
  }
  GIVEN("the same device with the control named by id") {
    FakeV4L2Device::Options options;
    options.has_trigger = true;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.external_trigger = true;
    config.trigger_control_id = kTriggerControlId;
    V4L2Camera camera(fake, config);
    THEN("start() uses it") {
      REQUIRE(camera.start().ok());
      CHECK(fake.trigger_value() == 1);
    }
  }
  GIVEN("a device without any trigger control") {
    FakeV4L2Device::Options options;
    FakeV4L2Device fake(options);
    V4L2CameraConfig config = config_for(options);
    config.external_trigger = true;
    V4L2Camera camera(fake, config);
    Status status = camera.start();
    THEN("start() fails and says how to fix the config") {
      REQUIRE_FALSE(status.ok());
      CHECK_THAT(status.error().message, Catch::Contains("camera.external_trigger") && Catch::Contains("trigger"));
      require_clean(fake);
    }
  }
  GIVEN("a device without exposure control") {
    FakeV4L2Device::Options options;
    options.has_exposure = false;
    FakeV4L2Device fake(options);
    V4L2Camera camera(fake, config_for(options));
    REQUIRE(camera.start().ok());
    THEN("streaming works, exposure requests are refused and frames report 0 µs") {
      CHECK(camera.set_exposure_us(1000) == DeviceStatus::kInvalidArgument);
      (void)fake.capture();
      Frame frame;
      REQUIRE(camera.grab(frame, 0) == DeviceStatus::kOk);
      CHECK(frame.exposure_us == 0);
      camera.release(frame);
    }
  }
}

SCENARIO("grab(), release() and set_exposure_us() never allocate", "[camera]") {
  for (std::uint32_t format : {V4L2_PIX_FMT_GREY, V4L2_PIX_FMT_YUYV}) {
    GIVEN("a streaming camera (format " + std::to_string(format) + ")") {
      FakeV4L2Device::Options options;
      options.formats = {format};
      FakeV4L2Device fake(options);
      V4L2Camera camera(fake, config_for(options));
      REQUIRE(camera.start().ok());
      WHEN("frames are grabbed and released, with exposure changes, timeouts and errors in between") {
        long allocations = 0;
        int delivered = 0;
        int mismatches = 0;
        for (int i = 0; i < 20; ++i) {
          const int sequence = fake.capture(i % 7 == 3);
          Frame frame;
          Frame nothing;
          DeviceStatus status = DeviceStatus::kOk;
          DeviceStatus timeout = DeviceStatus::kOk;
          {
            AllocationWindow window;
            status = camera.grab(frame, 0);
            if (status == DeviceStatus::kOk) {
              ++delivered;
              mismatches += pixel_mismatches(frame, sequence);
              camera.release(frame);
            }
            (void)camera.set_exposure_us(1000 + 100 * i);
            timeout = camera.grab(nothing, 0);
            allocations += window.count();
          }
          CHECK(timeout == DeviceStatus::kTimeout);
        }
        THEN("not one allocation happened and the good frames were right") {
          CHECK(allocations == 0);
          CHECK(delivered == 17);
          CHECK(mismatches == 0);
          CHECK(camera.stats().io_errors == 3);
          CHECK(camera.stats().dropped_frames == 0);
        }
      }
    }
  }
}
