// Shared pieces of the libFuzzer targets: an invariant that traps, a scratch file for readers that only take a path,
// and the input layout of the targets whose file format carries a checksum.
#pragma once

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <string_view>

namespace cellsight::fuzz {

// A broken invariant is a crash, so libFuzzer records the input (a refused input is not: readers return errors).
[[noreturn]] inline void violated(const char* what) {
  std::fprintf(stderr, "fuzz: invariant broken: %s\n", what);
  __builtin_trap();
}
inline void expect(bool condition, const char* what) {
  if (!condition) violated(what);
}
#define CS_FUZZ_STR2(x) #x
#define CS_FUZZ_STR(x) CS_FUZZ_STR2(x)
// expect() naming the condition and its line, so a finding says which invariant broke.
#define CS_FUZZ_EXPECT(condition) \
  ::cellsight::fuzz::expect((condition), __FILE__ ":" CS_FUZZ_STR(__LINE__) ": " #condition)

inline void store_u32(std::string& bytes, std::size_t offset, std::uint32_t value) {
  std::memcpy(bytes.data() + offset, &value, sizeof value);  // little-endian host, as the formats
}

// One file per process, rewritten for every input and removed at exit: in $TMPDIR, else in memory (/dev/shm) where
// there is one (a file on disk made the template target seven times slower); else /tmp.
class ScratchFile {
 public:
  explicit ScratchFile(const char* stem) {
    const char* env = std::getenv("TMPDIR");
    struct stat st {};
    const bool shm = ::stat("/dev/shm", &st) == 0 && S_ISDIR(st.st_mode) && ::access("/dev/shm", W_OK) == 0;
    const std::string dir = env != nullptr && env[0] != '\0' ? env : (shm ? "/dev/shm" : "/tmp");
    path_ = dir + "/" + stem + "-XXXXXX";
    fd_ = ::mkostemp(path_.data(), O_CLOEXEC);
    expect(fd_ >= 0, "the scratch file can be created");
  }
  ScratchFile(const ScratchFile&) = delete;
  ScratchFile& operator=(const ScratchFile&) = delete;
  ~ScratchFile() {
    ::close(fd_);
    ::unlink(path_.c_str());
  }
  // Replaces the content with `bytes`; returns the path for the reader.
  const std::string& write(std::string_view bytes) {
    expect(::ftruncate(fd_, 0) == 0, "the scratch file can be emptied");
    std::size_t done = 0;
    while (done < bytes.size()) {
      const ssize_t n = ::pwrite(fd_, bytes.data() + done, bytes.size() - done, static_cast<off_t>(done));
      expect(n > 0, "the scratch file can be written");
      done += static_cast<std::size_t>(n);
    }
    return path_;
  }

 private:
  std::string path_;
  int fd_ = -1;
};

// Inputs of the targets whose format carries a checksum: byte 0 chooses whether the target repairs the checksums
// (bit 0 set) so that mutations reach the parser behind them, or leaves them for the reader to check; the rest is
// the file. The seeds are product files with one such byte in front.
struct ChecksummedInput {
  bool repair = false;
  std::string file;
};
inline ChecksummedInput split_mode_byte(const std::uint8_t* data, std::size_t size) {
  ChecksummedInput in;
  if (size == 0) return in;
  in.repair = (data[0] & 1U) != 0;
  in.file.assign(reinterpret_cast<const char*>(data) + 1, size - 1);
  return in;
}

}  // namespace cellsight::fuzz
