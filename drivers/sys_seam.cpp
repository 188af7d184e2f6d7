// The real kernel behind SysSeam: each call forwards to libc and turns -1 + errno into -errno.
#include "drivers/sys_seam.hpp"

#include <fcntl.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cerrno>

namespace cellsight::drivers {

int RealSys::open(const char* path, int flags) {
  int fd = ::open(path, flags);
  return fd < 0 ? -errno : fd;
}

int RealSys::close(int fd) {
  return ::close(fd) < 0 ? -errno : 0;
}

int RealSys::ioctl(int fd, unsigned long request, void* arg) {
  // A signal landing in a blocking V4L2 ioctl must not look like a device fault (libcamera retries the same way).
  int result = 0;
  do {
    result = ::ioctl(fd, request, arg);
  } while (result < 0 && errno == EINTR);
  return result < 0 ? -errno : result;
}

int RealSys::mmap(std::size_t length, int prot, int flags, int fd, off_t offset, void*& mapped) {
  void* address = ::mmap(nullptr, length, prot, flags, fd, offset);
  if (address == MAP_FAILED) return -errno;
  mapped = address;
  return 0;
}

int RealSys::munmap(void* address, std::size_t length) {
  return ::munmap(address, length) < 0 ? -errno : 0;
}

int RealSys::poll(pollfd* fds, nfds_t count, int timeout_ms) {
  int ready = ::poll(fds, count, timeout_ms);
  return ready < 0 ? -errno : ready;
}

ssize_t RealSys::read(int fd, void* buffer, std::size_t count) {
  ssize_t bytes = ::read(fd, buffer, count);
  return bytes < 0 ? -static_cast<ssize_t>(errno) : bytes;
}

}  // namespace cellsight::drivers
