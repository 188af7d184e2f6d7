// Reading files from outside: refused from a stat when they cannot be what they should be.
#include "app/input_file.hpp"

#include <sys/stat.h>

#include <cerrno>
#include <cstring>

namespace cellsight::app {
namespace {

// The size of a regular file, or why the path is not one.
Expected<std::size_t> regular_file_size(const std::string& path, const std::string& what) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return make_error(path + ": cannot open: " + std::strerror(errno));
  if (S_ISDIR(st.st_mode)) return make_error(path + ": is a directory" + what);
  if (!S_ISREG(st.st_mode)) return make_error(path + ": is not a regular file (a device, pipe or socket)" + what);
  return static_cast<std::size_t>(st.st_size);
}

}  // namespace

Status check_regular_file(const std::string& path, const std::string& what) {
  auto size = regular_file_size(path, what);
  if (!size) return size.error();
  return {};
}

}  // namespace cellsight::app
