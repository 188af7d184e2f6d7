// Kernel-call seam (open/close/ioctl/mmap/munmap/poll/read) for the real device backends, plus their shared helpers.
#pragma once

#include <poll.h>
#include <sys/types.h>

#include <cstddef>
#include <cstring>
#include <string>
#include <utility>

namespace cellsight::drivers {

// One virtual call per kernel entry point a backend uses. Every call returns a negative errno on failure instead
// of -1 + errno (libcamera's convention): a fake never has to touch the thread's errno, and a caller cannot read a
// stale errno clobbered by logging in between. Implementations must not allocate: backends call them on the
// real-time path.
class SysSeam {
 public:
  virtual ~SysSeam() = default;
  SysSeam() = default;
  SysSeam(const SysSeam&) = delete;
  SysSeam& operator=(const SysSeam&) = delete;

  // File descriptor >= 0, or -errno.
  [[nodiscard]] virtual int open(const char* path, int flags) = 0;
  // 0 or -errno. The descriptor is gone either way (Linux close semantics), so callers never retry.
  virtual int close(int fd) = 0;
  // The ioctl's non-negative result, or -errno. The real seam retries EINTR.
  [[nodiscard]] virtual int ioctl(int fd, unsigned long request, void* arg) = 0;
  // 0 and `mapped` set, or -errno and `mapped` untouched.
  [[nodiscard]] virtual int mmap(std::size_t length, int prot, int flags, int fd, off_t offset, void*& mapped) = 0;
  virtual int munmap(void* address, std::size_t length) = 0;
  // Number of ready descriptors (0 on timeout), or -errno (EINTR is passed up: the caller's timeout decides).
  [[nodiscard]] virtual int poll(pollfd* fds, nfds_t count, int timeout_ms) = 0;
  // Bytes read, or -errno.
  [[nodiscard]] virtual ssize_t read(int fd, void* buffer, std::size_t count) = 0;
};

// The real kernel. Stateless: the application owns one and lends it to every backend.
class RealSys final : public SysSeam {
 public:
  int open(const char* path, int flags) override;
  int close(int fd) override;
  int ioctl(int fd, unsigned long request, void* arg) override;
  int mmap(std::size_t length, int prot, int flags, int fd, off_t offset, void*& mapped) override;
  int munmap(void* address, std::size_t length) override;
  int poll(pollfd* fds, nfds_t count, int timeout_ms) override;
  ssize_t read(int fd, void* buffer, std::size_t count) override;
};

namespace detail {
// strerror_r comes in two flavours (GNU returns the text, XSI fills the buffer); overloading picks the right one.
inline const char* strerror_text(const char* gnu_result, const char* /*buffer*/) {
  return gnu_result;
}
inline const char* strerror_text(int /*xsi_result*/, const char* buffer) {
  return buffer;
}
}  // namespace detail

// Thread-safe text for an errno value ("No such file or directory"), for start-up messages only (allocates).
inline std::string errno_text(int error_number) {
  char buffer[128] = {};
  return detail::strerror_text(::strerror_r(error_number, buffer, sizeof buffer), buffer);
}

// Undoes half-done start-up work on every early return unless dismissed (libcamera's ScopeExitActions).
template <class F>
class ScopeExit {
 public:
  explicit ScopeExit(F action) : action_(std::move(action)) {}
  ~ScopeExit() {
    if (armed_) action_();
  }
  ScopeExit(const ScopeExit&) = delete;
  ScopeExit& operator=(const ScopeExit&) = delete;
  void dismiss() { armed_ = false; }

 private:
  F action_;
  bool armed_ = true;
};

}  // namespace cellsight::drivers
