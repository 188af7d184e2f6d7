// V4L2 capture backend: QUERYCAP, S_FMT, REQBUFS + mmap, streaming and exposure (libcamera's V4L2VideoDevice).
#include "drivers/camera/v4l2_camera.hpp"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <sys/mman.h>
#include <time.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <utility>

#include "drivers/log.hpp"

namespace cellsight::drivers {
namespace {

constexpr const char* kComponent = "camera";
constexpr const char* kConfigHint = "config/cellsight.yaml";
constexpr std::uint32_t kNoIndex = 0xFFFFFFFFu;
constexpr std::uint32_t kMaxFormats = 64;  // ENUM_FMT stops with EINVAL long before; the bound guards broken drivers
constexpr int kMaxControls = 1024;         // same for QUERYCTRL enumeration
constexpr std::uint32_t kMaxSequenceGap = 1u << 30;  // larger "gaps" are a driver restarting its counter, not drops
constexpr std::int64_t kNsPerSecond = 1'000'000'000;
constexpr std::int64_t kNsPerUs = 1'000;
constexpr std::uint32_t kCaptureType = V4L2_BUF_TYPE_VIDEO_CAPTURE;

std::int64_t monotonic_now_ns() {
  timespec now{};
  clock_gettime(CLOCK_MONOTONIC, &now);
  return static_cast<std::int64_t>(now.tv_sec) * kNsPerSecond + now.tv_nsec;
}

std::string fourcc_text(std::uint32_t fourcc) {
  std::string text(4, '?');
  for (std::size_t i = 0; i < 4; ++i) {
    auto c = static_cast<char>((fourcc >> (8 * i)) & 0xFFu);
    if (c >= ' ' && c <= '~') text[i] = c;
  }
  return text;
}

// Kernel strings are fixed arrays that need not be terminated.
template <std::size_t N>
std::string kernel_string(const std::uint8_t (&chars)[N]) {
  const char* begin = reinterpret_cast<const char*>(chars);
  return std::string(begin, strnlen(begin, N));
}

bool names_trigger(const std::uint8_t (&name)[32]) {
  std::string text = kernel_string(name);
  std::transform(text.begin(), text.end(), text.begin(),
                 [](char c) { return (c >= 'A' && c <= 'Z') ? static_cast<char>(c - 'A' + 'a') : c; });
  return text.find("trigger") != std::string::npos;
}

// What a person should check for an open() failure.
const char* open_hint(int error_number) {
  switch (error_number) {
    case EACCES:
    case EPERM: return "is the user in the 'video' group?";
    case EBUSY: return "is another program using the camera?";
    default: return "is the camera connected?";
  }
}

// The value V4L2 accepts (min + k * step, up to max; in 100 µs units) whose exposure is nearest to exposure_us.
// Rounded once, in µs: rounding to whole units first and then to the step could pick the farther neighbour.
std::int64_t nearest_control_value(std::int64_t exposure_us, std::int64_t min, std::int64_t max, std::int64_t step,
                                   std::int64_t unit_us) {
  const std::int64_t step_us = step * unit_us;
  const std::int64_t above_min_us = std::max<std::int64_t>(0, exposure_us - min * unit_us);
  const std::int64_t k = std::min((above_min_us + step_us / 2) / step_us, (max - min) / step);
  return min + k * step;
}

// When the frame was exposed: the driver's timestamp when it is on CLOCK_MONOTONIC, else the time of dequeueing.
std::int64_t frame_timestamp_ns(const v4l2_buffer& buffer) {
  std::int64_t timestamp_ns = monotonic_now_ns();
  if ((buffer.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC) {
    timestamp_ns = static_cast<std::int64_t>(buffer.timestamp.tv_sec) * kNsPerSecond +
                   static_cast<std::int64_t>(buffer.timestamp.tv_usec) * kNsPerUs;
  }
  return timestamp_ns;
}

}  // namespace

std::int32_t V4L2Camera::units_to_us(std::int32_t units) {
  // A driver may report an absurd maximum; saturate rather than overflow.
  return static_cast<std::int32_t>(
      std::clamp<std::int64_t>(static_cast<std::int64_t>(units) * kExposureUnitUs, INT32_MIN, INT32_MAX));
}

std::int32_t V4L2Camera::units_for_us(std::int32_t exposure_us) const {
  return static_cast<std::int32_t>(
      nearest_control_value(exposure_us, exposure_min_, exposure_max_, exposure_step_, kExposureUnitUs));
}

V4L2Camera::V4L2Camera(SysSeam& sys, V4L2CameraConfig config) : sys_(sys), config_(std::move(config)) {}

V4L2Camera::~V4L2Camera() {
  stop();
}

std::string V4L2Camera::where() const {
  return "camera: " + config_.device;
}

Status V4L2Camera::start() {
  if (started_) return make_error(where() + " is already started");
  if (config_.buffer_count < kMinBuffers || config_.buffer_count > kMaxBuffers) {
    return make_error("camera: camera.buffers is " + std::to_string(config_.buffer_count) + ", it must be " +
                      std::to_string(kMinBuffers) + ".." + std::to_string(kMaxBuffers) + " (" + kConfigHint + ")");
  }
  if (config_.width_px <= 0 || config_.height_px <= 0 || config_.poll_timeout_ms < 0 || config_.exposure_us < 0) {
    return make_error(
        "camera: rig.camera.width_px, rig.camera.height_px, camera.timeout_ms and camera.exposure_us "
        "must not be negative, and the size not zero (" +
        std::string(kConfigHint) + ")");
  }
  stats_ = {};
  lost_ = false;
  have_sequence_ = false;
  next_sequence_ = 0;
  exposure_history_count_ = 0;
  exposure_history_head_ = 0;

  ScopeExit undo([this] { teardown(); });
  if (Status status = open_device(); !status.ok()) return status;
  if (Status status = negotiate_format(); !status.ok()) return status;
  if (Status status = setup_exposure(); !status.ok()) return status;
  if (Status status = setup_trigger(); !status.ok()) return status;
  if (Status status = allocate_buffers(); !status.ok()) return status;
  if (Status status = queue_all_and_stream(); !status.ok()) return status;
  undo.dismiss();
  started_ = true;

  CS_LOG_INFO(kComponent, "%s streaming %dx%d %s%s, %d buffers, exposure %d..%d us", config_.device.c_str(),
              config_.width_px, config_.height_px, yuyv_ ? "YUYV" : "GREY", yuyv_ ? " (converted to mono8)" : "",
              buffer_count(), exposure_min_us(), exposure_max_us());
  return {};
}

Status V4L2Camera::open_device() {
  // Non-blocking: DQBUF must return EAGAIN instead of hanging when poll() and the queue disagree.
  int fd = sys_.open(config_.device.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    return make_error("camera: cannot open " + config_.device + ": " + errno_text(-fd) + " (" + open_hint(-fd) +
                      " check camera.device in " + kConfigHint + ")");
  }
  fd_ = fd;

  v4l2_capability caps{};
  if (int result = sys_.ioctl(fd_, VIDIOC_QUERYCAP, &caps); result < 0) {
    return make_error(where() + " is not a V4L2 device (VIDIOC_QUERYCAP: " + errno_text(-result) +
                      "); check camera.device in " + kConfigHint);
  }
  // device_caps describes this node; capabilities describes the whole physical device.
  std::uint32_t node_caps = (caps.capabilities & V4L2_CAP_DEVICE_CAPS) != 0 ? caps.device_caps : caps.capabilities;
  std::string identity = " ('" + kernel_string(caps.card) + "', driver " + kernel_string(caps.driver) + ")";
  if ((node_caps & V4L2_CAP_VIDEO_CAPTURE) == 0) {
    const char* why = (node_caps & V4L2_CAP_VIDEO_CAPTURE_MPLANE) != 0
                          ? " is a multi-planar capture node, which cellsight does not support"
                          : " is not a video capture node";
    return make_error(where() + identity + why + "; `v4l2-ctl --list-devices` shows the capture nodes");
  }
  if ((node_caps & V4L2_CAP_STREAMING) == 0) {
    return make_error(where() + identity + " does not support streaming I/O (needed for mmap buffers)");
  }
  return {};
}

Status V4L2Camera::negotiate_format() {
  bool offers_grey = false;
  bool offers_yuyv = false;
  std::string offered;
  for (std::uint32_t index = 0; index < kMaxFormats; ++index) {
    v4l2_fmtdesc description{};
    description.index = index;
    description.type = kCaptureType;
    int result = sys_.ioctl(fd_, VIDIOC_ENUM_FMT, &description);
    if (result == -EINVAL) break;  // end of the list
    if (result < 0) return make_error(where() + ": VIDIOC_ENUM_FMT failed: " + errno_text(-result));
    offers_grey = offers_grey || description.pixelformat == V4L2_PIX_FMT_GREY;
    offers_yuyv = offers_yuyv || description.pixelformat == V4L2_PIX_FMT_YUYV;
    if (!offered.empty()) offered += ' ';
    offered += fourcc_text(description.pixelformat);
  }
  if (!offers_grey && !offers_yuyv) {
    return make_error(where() + " offers neither GREY nor YUYV (it offers: " + (offered.empty() ? "nothing" : offered) +
                      "); a mono camera is expected");
  }
  // GREY is the sensor's own data; YUYV (colour webcams, some USB mono cameras) costs a conversion pass.
  const std::uint32_t fourcc = offers_grey ? V4L2_PIX_FMT_GREY : V4L2_PIX_FMT_YUYV;
  const std::uint32_t bytes_per_pixel = offers_grey ? 1 : 2;
  if (!offers_grey && config_.width_px % 2 != 0) {
    return make_error(where() + " only offers YUYV, which needs an even rig.camera.width_px (it is " +
                      std::to_string(config_.width_px) + ")");
  }

  v4l2_format format{};
  format.type = kCaptureType;
  format.fmt.pix.width = static_cast<std::uint32_t>(config_.width_px);
  format.fmt.pix.height = static_cast<std::uint32_t>(config_.height_px);
  format.fmt.pix.pixelformat = fourcc;
  format.fmt.pix.field = V4L2_FIELD_NONE;
  if (int result = sys_.ioctl(fd_, VIDIOC_S_FMT, &format); result < 0) {
    const char* hint = result == -EBUSY ? " (is another program streaming from it?)" : "";
    return make_error(where() + ": cannot set " + fourcc_text(fourcc) + " " + std::to_string(config_.width_px) + "x" +
                      std::to_string(config_.height_px) + ": " + errno_text(-result) + hint);
  }
  // Drivers adjust instead of failing; the calibration is only valid for exactly the configured size.
  if (format.fmt.pix.pixelformat != fourcc) {
    return make_error(where() + " answered format " + fourcc_text(format.fmt.pix.pixelformat) + " when asked for " +
                      fourcc_text(fourcc));
  }
  if (format.fmt.pix.width != static_cast<std::uint32_t>(config_.width_px) ||
      format.fmt.pix.height != static_cast<std::uint32_t>(config_.height_px)) {
    return make_error(where() + " delivers " + std::to_string(format.fmt.pix.width) + "x" +
                      std::to_string(format.fmt.pix.height) + ", but rig.camera.width_px x height_px is " +
                      std::to_string(config_.width_px) + "x" + std::to_string(config_.height_px) + " (" + kConfigHint +
                      "; `v4l2-ctl -d " + config_.device + " --list-formats-ext` lists the sizes)");
  }
  const std::uint32_t row_bytes = format.fmt.pix.width * bytes_per_pixel;
  bytes_per_line_ = std::max(format.fmt.pix.bytesperline, row_bytes);
  image_bytes_ = bytes_per_line_ * format.fmt.pix.height;
  if (format.fmt.pix.sizeimage != 0 && format.fmt.pix.sizeimage < image_bytes_) {
    return make_error(where() + " reports a frame size of " + std::to_string(format.fmt.pix.sizeimage) +
                      " bytes, smaller than its " + std::to_string(bytes_per_line_) + " bytes per line x " +
                      std::to_string(format.fmt.pix.height) + " lines");
  }
  yuyv_ = !offers_grey;
  return {};
}

Status V4L2Camera::setup_exposure() {
  v4l2_queryctrl absolute{};
  absolute.id = V4L2_CID_EXPOSURE_ABSOLUTE;
  if (sys_.ioctl(fd_, VIDIOC_QUERYCTRL, &absolute) < 0 || (absolute.flags & V4L2_CTRL_FLAG_DISABLED) != 0 ||
      absolute.maximum < absolute.minimum) {
    has_exposure_ = false;
    exposure_min_ = exposure_max_ = 0;
    CS_LOG_WARN(kComponent, "%s has no exposure control; the exposure loop cannot act (frames report 0 us)",
                config_.device.c_str());
    return {};
  }
  has_exposure_ = true;
  exposure_min_ = absolute.minimum;
  exposure_max_ = absolute.maximum;
  exposure_step_ = std::max(1, absolute.step);

  // Manual exposure, or the camera's own loop fights ours. UVC cameras offer MANUAL as a menu entry.
  v4l2_queryctrl automatic{};
  automatic.id = V4L2_CID_EXPOSURE_AUTO;
  if (sys_.ioctl(fd_, VIDIOC_QUERYCTRL, &automatic) == 0 && (automatic.flags & V4L2_CTRL_FLAG_DISABLED) == 0) {
    v4l2_control manual{};
    manual.id = V4L2_CID_EXPOSURE_AUTO;
    manual.value = V4L2_EXPOSURE_MANUAL;
    if (int result = sys_.ioctl(fd_, VIDIOC_S_CTRL, &manual); result < 0) {
      return make_error(where() + ": cannot switch auto exposure to manual: " + errno_text(-result));
    }
  }

  if (config_.exposure_us > 0) {
    v4l2_control control{};
    control.id = V4L2_CID_EXPOSURE_ABSOLUTE;
    control.value = units_for_us(config_.exposure_us);
    if (int result = sys_.ioctl(fd_, VIDIOC_S_CTRL, &control); result < 0) {
      return make_error(where() + ": cannot set camera.exposure_us " + std::to_string(config_.exposure_us) + ": " +
                        errno_text(-result));
    }
    record_exposure(units_to_us(control.value), monotonic_now_ns());
  } else {
    v4l2_control control{};
    control.id = V4L2_CID_EXPOSURE_ABSOLUTE;
    if (int result = sys_.ioctl(fd_, VIDIOC_G_CTRL, &control); result < 0) {
      return make_error(where() + ": cannot read the exposure: " + errno_text(-result));
    }
    record_exposure(units_to_us(control.value), monotonic_now_ns());
  }
  return {};
}

Status V4L2Camera::setup_trigger() {
  if (!config_.external_trigger) return {};
  v4l2_queryctrl control{};
  bool found = false;
  if (config_.trigger_control_id != 0) {
    control.id = config_.trigger_control_id;
    found = sys_.ioctl(fd_, VIDIOC_QUERYCTRL, &control) == 0 && (control.flags & V4L2_CTRL_FLAG_DISABLED) == 0;
  } else {
    control.id = V4L2_CTRL_FLAG_NEXT_CTRL;
    for (int i = 0; i < kMaxControls && sys_.ioctl(fd_, VIDIOC_QUERYCTRL, &control) == 0; ++i) {
      if ((control.flags & V4L2_CTRL_FLAG_DISABLED) == 0 && names_trigger(control.name)) {
        found = true;
        break;
      }
      control.id |= V4L2_CTRL_FLAG_NEXT_CTRL;
    }
  }
  if (!found) {
    char id_text[16];
    std::snprintf(id_text, sizeof id_text, "0x%08x", config_.trigger_control_id);
    return make_error(where() + ": camera.external_trigger is on but the device has " +
                      (config_.trigger_control_id != 0 ? "no control " + std::string(id_text)
                                                       : std::string("no control named like \"trigger\"")) +
                      " (`v4l2-ctl -d " + config_.device +
                      " --list-ctrls`; set camera.trigger_control_id, or turn "
                      "camera.external_trigger off in " +
                      kConfigHint + ")");
  }
  v4l2_control select{};
  select.id = control.id;
  select.value = config_.trigger_control_value;
  if (int result = sys_.ioctl(fd_, VIDIOC_S_CTRL, &select); result < 0) {
    return make_error(where() + ": cannot set trigger control '" + kernel_string(control.name) + "' to " +
                      std::to_string(config_.trigger_control_value) + ": " + errno_text(-result));
  }
  CS_LOG_INFO(kComponent, "%s external trigger: control '%s' = %d", config_.device.c_str(),
              kernel_string(control.name).c_str(), config_.trigger_control_value);
  return {};
}

Status V4L2Camera::allocate_buffers() {
  v4l2_requestbuffers request{};
  request.count = static_cast<std::uint32_t>(config_.buffer_count);
  request.type = kCaptureType;
  request.memory = V4L2_MEMORY_MMAP;
  if (int result = sys_.ioctl(fd_, VIDIOC_REQBUFS, &request); result < 0) {
    const char* hint = result == -EINVAL ? " (the driver does not offer mmap buffers)" : "";
    return make_error(where() + ": cannot allocate " + std::to_string(config_.buffer_count) +
                      " capture buffers: " + errno_text(-result) + hint);
  }
  buffers_requested_ = true;
  if (request.count < static_cast<std::uint32_t>(kMinBuffers)) {
    return make_error(where() + " granted only " + std::to_string(request.count) +
                      " capture buffers; cellsight needs "
                      "at least " +
                      std::to_string(kMinBuffers) + " (camera.buffers = " + std::to_string(config_.buffer_count) +
                      "); the driver is short of memory (CMA) or limits them");
  }
  // A driver may raise the count to its own minimum; buffers beyond kMaxBuffers are simply never queued.
  const std::uint32_t count = std::min(request.count, static_cast<std::uint32_t>(kMaxBuffers));
  buffers_.assign(count, Buffer{});
  for (std::uint32_t index = 0; index < count; ++index) {
    v4l2_buffer buffer{};
    buffer.type = kCaptureType;
    buffer.memory = V4L2_MEMORY_MMAP;
    buffer.index = index;
    if (int result = sys_.ioctl(fd_, VIDIOC_QUERYBUF, &buffer); result < 0) {
      return make_error(where() + ": VIDIOC_QUERYBUF " + std::to_string(index) + " failed: " + errno_text(-result));
    }
    if (buffer.length < image_bytes_) {
      return make_error(where() + ": buffer " + std::to_string(index) + " holds " + std::to_string(buffer.length) +
                        " bytes, a frame needs " + std::to_string(image_bytes_));
    }
    void* mapping = nullptr;
    if (int result = sys_.mmap(buffer.length, PROT_READ, MAP_SHARED, fd_, static_cast<off_t>(buffer.m.offset), mapping);
        result < 0) {
      return make_error(where() + ": cannot map buffer " + std::to_string(index) + ": " + errno_text(-result));
    }
    buffers_[index].mapping = mapping;
    buffers_[index].length = buffer.length;
  }
  if (yuyv_) {
    mono_.assign(static_cast<std::size_t>(count) * static_cast<std::size_t>(config_.width_px) *
                     static_cast<std::size_t>(config_.height_px),
                 0);
  }
  return {};
}

Status V4L2Camera::queue_all_and_stream() {
  for (std::uint32_t index = 0; index < buffers_.size(); ++index) {
    v4l2_buffer buffer{};
    buffer.type = kCaptureType;
    buffer.memory = V4L2_MEMORY_MMAP;
    buffer.index = index;
    if (int result = sys_.ioctl(fd_, VIDIOC_QBUF, &buffer); result < 0) {
      return make_error(where() + ": cannot queue buffer " + std::to_string(index) + ": " + errno_text(-result));
    }
    buffers_[index].queued = true;
    ++queued_count_;
  }
  int type = static_cast<int>(kCaptureType);
  if (int result = sys_.ioctl(fd_, VIDIOC_STREAMON, &type); result < 0) {
    return make_error(where() + ": cannot start streaming: " + errno_text(-result));
  }
  streaming_ = true;
  return {};
}

// STREAMOFF returns every buffer to user space, the mappings must go before REQBUFS(0) may free the buffers (vb2
// answers EBUSY while any is mapped), and the descriptor closes last. Safe on any half-started state.
void V4L2Camera::teardown() {
  if (fd_ >= 0) {
    if (streaming_) {
      int type = static_cast<int>(kCaptureType);
      if (int result = sys_.ioctl(fd_, VIDIOC_STREAMOFF, &type); result < 0 && !lost_) {
        CS_LOG_WARN(kComponent, "%s STREAMOFF: %s", config_.device.c_str(), errno_text(-result).c_str());
      }
    }
    for (Buffer& buffer : buffers_) {
      if (buffer.mapping != nullptr) (void)sys_.munmap(buffer.mapping, buffer.length);
    }
    if (buffers_requested_) {
      v4l2_requestbuffers request{};
      request.count = 0;
      request.type = kCaptureType;
      request.memory = V4L2_MEMORY_MMAP;
      if (int result = sys_.ioctl(fd_, VIDIOC_REQBUFS, &request); result < 0 && !lost_ && result != -ENODEV) {
        CS_LOG_WARN(kComponent, "%s freeing buffers: %s", config_.device.c_str(), errno_text(-result).c_str());
      }
    }
    (void)sys_.close(fd_);
  }
  fd_ = -1;
  streaming_ = false;
  buffers_requested_ = false;
  started_ = false;
  buffers_.clear();
  mono_.clear();
  queued_count_ = 0;
  has_exposure_ = false;
}

void V4L2Camera::stop() {
  if (started_) {
    CS_LOG_INFO(kComponent,
                "%s stopped: %llu frames, %llu timeouts, %llu I/O errors, %llu dropped, %llu release errors%s",
                config_.device.c_str(), static_cast<unsigned long long>(stats_.frames),
                static_cast<unsigned long long>(stats_.timeouts), static_cast<unsigned long long>(stats_.io_errors),
                static_cast<unsigned long long>(stats_.dropped_frames),
                static_cast<unsigned long long>(stats_.release_errors), lost_ ? " (device lost)" : "");
  }
  teardown();
}

DeviceStatus V4L2Camera::lose_device() {
  if (!lost_)
    CS_LOG_ERROR(kComponent, "%s vanished (unplugged or driver reset); restart needed", config_.device.c_str());
  lost_ = true;
  return DeviceStatus::kDeviceLost;
}

DeviceStatus V4L2Camera::requeue(std::uint32_t index) {
  v4l2_buffer buffer{};
  buffer.type = kCaptureType;
  buffer.memory = V4L2_MEMORY_MMAP;
  buffer.index = index;
  int result = sys_.ioctl(fd_, VIDIOC_QBUF, &buffer);
  if (result == -ENODEV) return lose_device();
  if (result < 0) return DeviceStatus::kIoError;
  buffers_[index].queued = true;
  ++queued_count_;
  return DeviceStatus::kOk;
}

DeviceStatus V4L2Camera::grab(Frame& out, int timeout_ms) {
  if (!started_) return DeviceStatus::kNotStarted;
  if (lost_) return DeviceStatus::kDeviceLost;
  if (queued_count_ == 0) {
    // Every buffer is borrowed: the kernel has nowhere to write; the caller must release() first.
    ++stats_.io_errors;
    return DeviceStatus::kIoError;
  }
  short revents = 0;
  if (const DeviceStatus status = wait_for_frame(timeout_ms, revents); status != DeviceStatus::kOk) return status;
  v4l2_buffer buffer{};
  if (const DeviceStatus status = dequeue(revents, buffer); status != DeviceStatus::kOk) return status;
  const std::uint32_t index = buffer.index;
  // Counted before the error check: a corrupt frame is an I/O error, not a drop.
  count_dropped_frames(buffer.sequence);

  if ((buffer.flags & V4L2_BUF_FLAG_ERROR) != 0 || buffer.bytesused < image_bytes_) {
    // Corrupt or truncated frame (the recommended way for drivers to report a recoverable error).
    ++stats_.io_errors;
    if (requeue(index) == DeviceStatus::kDeviceLost) return DeviceStatus::kDeviceLost;
    return DeviceStatus::kIoError;
  }

  const std::int64_t timestamp_ns = frame_timestamp_ns(buffer);
  int stride_bytes = static_cast<int>(bytes_per_line_);
  const std::uint8_t* pixels = mono_pixels(index, stride_bytes);
  out.data = pixels;
  out.width_px = config_.width_px;
  out.height_px = config_.height_px;
  out.stride_bytes = stride_bytes;
  out.sequence = next_sequence_++;
  out.timestamp_ns = timestamp_ns;
  out.exposure_us = exposure_at(timestamp_ns);
  out.buffer_index = static_cast<std::int32_t>(index);
  ++stats_.frames;
  return DeviceStatus::kOk;
}

DeviceStatus V4L2Camera::wait_for_frame(int timeout_ms, short& revents) {
  pollfd descriptor{};
  descriptor.fd = fd_;
  descriptor.events = POLLIN;
  int ready = sys_.poll(&descriptor, 1, timeout_ms < 0 ? config_.poll_timeout_ms : timeout_ms);
  if (ready == 0 || ready == -EINTR) {
    ++stats_.timeouts;
    return DeviceStatus::kTimeout;
  }
  if (ready < 0) {
    ++stats_.io_errors;
    return DeviceStatus::kIoError;
  }
  // An unregistered video node answers POLLERR | POLLHUP (v4l2_poll); vb2 alone never sets POLLHUP on capture.
  if ((descriptor.revents & (POLLHUP | POLLNVAL)) != 0) return lose_device();
  revents = descriptor.revents;
  return DeviceStatus::kOk;
}

DeviceStatus V4L2Camera::dequeue(short revents, v4l2_buffer& buffer) {
  buffer.type = kCaptureType;
  buffer.memory = V4L2_MEMORY_MMAP;
  buffer.index = kNoIndex;
  int result = sys_.ioctl(fd_, VIDIOC_DQBUF, &buffer);
  if (result == -ENODEV) return lose_device();
  if (result == -EAGAIN && (revents & POLLERR) == 0) {
    ++stats_.timeouts;  // woken without a frame
    return DeviceStatus::kTimeout;
  }
  if (result == -EIO) {
    ++stats_.io_errors;
    return hand_back_empty(buffer.index);
  }
  if (result < 0) {
    ++stats_.io_errors;
    return DeviceStatus::kIoError;
  }
  const std::uint32_t index = buffer.index;
  if (index >= buffers_.size() || !buffers_[index].queued) {
    ++stats_.io_errors;  // the kernel handed out a buffer we never queued: nothing safe to do with it
    return DeviceStatus::kIoError;
  }
  buffers_[index].queued = false;
  --queued_count_;
  return DeviceStatus::kOk;
}

DeviceStatus V4L2Camera::hand_back_empty(std::uint32_t index) {
  // Some drivers dequeue an empty buffer with EIO (signal loss). Hand it back so the pool does not drain; when the
  // kernel still owned it, QBUF fails harmlessly and it stays queued.
  if (index < buffers_.size() && buffers_[index].queued) {
    buffers_[index].queued = false;
    --queued_count_;
    if (requeue(index) == DeviceStatus::kDeviceLost) return DeviceStatus::kDeviceLost;
    if (!buffers_[index].queued) {
      buffers_[index].queued = true;
      ++queued_count_;
    }
  }
  return DeviceStatus::kIoError;
}

void V4L2Camera::count_dropped_frames(std::uint32_t kernel_sequence) {
  if (have_sequence_) {
    std::uint32_t gap = kernel_sequence - last_kernel_sequence_ - 1u;  // unsigned: wraps like the kernel counter
    if (gap != 0 && gap < kMaxSequenceGap) stats_.dropped_frames += gap;
  }
  have_sequence_ = true;
  last_kernel_sequence_ = kernel_sequence;
}

const std::uint8_t* V4L2Camera::mono_pixels(std::uint32_t index, int& stride_bytes) {
  const auto* pixels = static_cast<const std::uint8_t*>(buffers_[index].mapping);
  if (!yuyv_) return pixels;
  // YUYV packs Y0 U Y1 V: the luma of pixel x sits at byte 2x of its line.
  const auto width = static_cast<std::size_t>(config_.width_px);
  const auto height = static_cast<std::size_t>(config_.height_px);
  std::uint8_t* mono = mono_.data() + index * width * height;
  for (std::size_t y = 0; y < height; ++y) {
    const std::uint8_t* line = pixels + y * bytes_per_line_;
    std::uint8_t* row = mono + y * width;
    for (std::size_t x = 0; x < width; ++x) row[x] = line[2 * x];
  }
  stride_bytes = config_.width_px;
  return mono;
}

void V4L2Camera::release(const Frame& frame) {
  if (!started_ || lost_) return;
  if (frame.buffer_index < 0 || static_cast<std::size_t>(frame.buffer_index) >= buffers_.size() ||
      buffers_[static_cast<std::size_t>(frame.buffer_index)].queued) {
    ++stats_.release_errors;  // not a frame we handed out, or released twice
    return;
  }
  DeviceStatus status = requeue(static_cast<std::uint32_t>(frame.buffer_index));
  if (status == DeviceStatus::kIoError) ++stats_.release_errors;
}

DeviceStatus V4L2Camera::set_exposure_us(std::int32_t exposure_us) {
  if (!started_) return DeviceStatus::kNotStarted;
  if (lost_) return DeviceStatus::kDeviceLost;
  if (exposure_us <= 0 || !has_exposure_) return DeviceStatus::kInvalidArgument;
  v4l2_control control{};
  control.id = V4L2_CID_EXPOSURE_ABSOLUTE;
  control.value = units_for_us(exposure_us);
  int result = sys_.ioctl(fd_, VIDIOC_S_CTRL, &control);
  if (result == -ENODEV) return lose_device();
  if (result < 0) {
    ++stats_.io_errors;
    return DeviceStatus::kIoError;
  }
  record_exposure(units_to_us(control.value), monotonic_now_ns());
  return DeviceStatus::kOk;
}

void V4L2Camera::record_exposure(std::int32_t exposure_us, std::int64_t since_ns) {
  exposure_history_[exposure_history_head_] = ExposureChange{since_ns, exposure_us};
  exposure_history_head_ = (exposure_history_head_ + 1) % kExposureHistory;
  exposure_history_count_ = std::min(exposure_history_count_ + 1, kExposureHistory);
}

// The exposure in force when the frame was stamped. Approximate by nature: a sensor applies a new exposure one or
// two frames after the control is written, and the history only reaches kExposureHistory changes back.
std::int32_t V4L2Camera::exposure_at(std::int64_t timestamp_ns) const {
  std::int32_t exposure_us = 0;
  for (std::size_t age = 1; age <= exposure_history_count_; ++age) {
    const ExposureChange& change =
        exposure_history_[(exposure_history_head_ + kExposureHistory - age) % kExposureHistory];
    exposure_us = change.exposure_us;
    if (change.since_ns <= timestamp_ns) break;
  }
  return exposure_us;
}

}  // namespace cellsight::drivers
