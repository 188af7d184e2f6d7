// FrameMemo: rendered frames in one memfd mapping.
#include "drivers/sim/frame_memo.hpp"

#include <sys/mman.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>

namespace cellsight::sim {

FrameMemo::~FrameMemo() {
  if (base_ != nullptr) ::munmap(base_, bytes_);
}

Status FrameMemo::allocate(std::size_t slots, int frames, int width_px, int height_px) {
  if (base_ != nullptr) return make_error("frame memo: allocated twice");
  if (slots == 0 || frames <= 0 || width_px <= 0 || height_px <= 0) return make_error("frame memo: empty");
  const std::size_t bytes = slots * static_cast<std::size_t>(frames) * static_cast<std::size_t>(width_px) *
                            static_cast<std::size_t>(height_px);
  const int fd = ::memfd_create("cellsight-sim-frames", MFD_CLOEXEC);
  if (fd < 0) return make_error(std::string("frame memo: memfd_create: ") + std::strerror(errno));
  if (::ftruncate(fd, static_cast<off_t>(bytes)) != 0) {
    const int err = errno;
    ::close(fd);
    return make_error("frame memo: " + std::to_string(bytes >> 20) + " MB: " + std::strerror(err));
  }
  void* base = ::mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  const int err = errno;
  ::close(fd);  // the mapping keeps the memory
  if (base == MAP_FAILED) return make_error(std::string("frame memo: mmap: ") + std::strerror(err));
  base_ = static_cast<std::uint8_t*>(base);
  bytes_ = bytes;
  slots_ = slots;
  frames_ = frames;
  width_ = width_px;
  height_ = height_px;
  keys_.assign(slots * static_cast<std::size_t>(frames), -1);
  return {};
}

const std::uint8_t* FrameMemo::find(std::size_t slot, int frame, std::int32_t exposure_us, bool laser_on) const {
  if (base_ == nullptr || slot >= slots_ || frame < 0 || frame >= frames_) return nullptr;
  const std::size_t i = index(slot, frame);
  if (keys_[i] != static_cast<std::int64_t>(exposure_us) * 2 + (laser_on ? 1 : 0)) return nullptr;
  ++hits_;
  return base_ + i * static_cast<std::size_t>(width_) * static_cast<std::size_t>(height_);
}

void FrameMemo::store(std::size_t slot, int frame, std::int32_t exposure_us, bool laser_on, const std::uint8_t* pixels,
                      std::size_t stride) {
  if (base_ == nullptr || slot >= slots_ || frame < 0 || frame >= frames_) return;
  const std::size_t i = index(slot, frame);
  std::uint8_t* out = base_ + i * static_cast<std::size_t>(width_) * static_cast<std::size_t>(height_);
  for (int y = 0; y < height_; ++y) {
    std::memcpy(out + static_cast<std::size_t>(y) * static_cast<std::size_t>(width_),
                pixels + static_cast<std::size_t>(y) * stride, static_cast<std::size_t>(width_));
  }
  keys_[i] = static_cast<std::int64_t>(exposure_us) * 2 + (laser_on ? 1 : 0);
  ++stores_;
}

}  // namespace cellsight::sim
