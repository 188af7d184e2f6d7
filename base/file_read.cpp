// The one whole-file reader: stat first (regular file, size cap), then one read of exactly that many bytes.
#include "base/file_read.hpp"

#include <sys/stat.h>

#include <cerrno>
#include <cstring>
#include <fstream>

namespace cellsight::base {

Expected<std::size_t> regular_file_size(const std::string& path, const std::string& what) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return make_error(path + ": cannot open: " + std::strerror(errno));
  if (S_ISDIR(st.st_mode)) return make_error(path + ": is a directory" + what);
  if (!S_ISREG(st.st_mode)) return make_error(path + ": is not a regular file (a device, pipe or socket)" + what);
  return static_cast<std::size_t>(st.st_size);
}

Expected<std::string> read_file(const std::string& path, std::size_t max_bytes) {
  auto size = regular_file_size(path);
  if (!size) return size.error();
  if (*size > max_bytes) {
    return make_error(path + ": is " + std::to_string(*size) + " bytes, more than the " + std::to_string(max_bytes) +
                      " this reader takes");
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) return make_error(path + ": cannot open: " + std::strerror(errno));
  std::string bytes(*size, '\0');
  in.read(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (in.bad()) return make_error(path + ": read failed");
  // A file that shrank since the stat gives what it still holds; one that grew, the bytes of its size at the stat.
  bytes.resize(static_cast<std::size_t>(in.gcount()));
  return bytes;
}

}  // namespace cellsight::base
