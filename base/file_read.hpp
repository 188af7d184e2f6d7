// Reading whole files: only regular files, and no more bytes than the caller allows, with a message that names them.
#pragma once

#include <cstddef>
#include <string>

#include "base/result.hpp"

namespace cellsight::base {

// The size of the regular file at `path`, or why it is not one: "PATH: is a directory<what>", "PATH: is not a
// regular file (a device, pipe or socket)<what>", "PATH: cannot open: <reason>". `what` ends the message, e.g.
// ", not a configuration file". A folder opens as a stream and reads as nothing, a device may never end: both are
// refused from a stat, before anything is read.
[[nodiscard]] Expected<std::size_t> regular_file_size(const std::string& path, const std::string& what = "");

// The whole regular file at `path`. A file larger than `max_bytes` is refused before it is read ("PATH: is N bytes,
// more than the M this reader takes"), so a wrong path cannot fill the memory.
[[nodiscard]] Expected<std::string> read_file(const std::string& path, std::size_t max_bytes);

}  // namespace cellsight::base
