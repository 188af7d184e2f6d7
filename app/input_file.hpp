// Files from outside (configuration, scans): only regular files are read.
#pragma once

#include <string>

#include "algo/result.hpp"

namespace cellsight::app {

// "PATH: is a directory<what>" or "PATH: is not a regular file (a device, pipe or socket)<what>"; a path that
// cannot be looked at gives "PATH: cannot open: <reason>". `what` ends the message, e.g. ", not a configuration file".
[[nodiscard]] Status check_regular_file(const std::string& path, const std::string& what);

}  // namespace cellsight::app
