// Files from outside (configuration, scans): only regular files are read, and a scan no further than its header
// allows: a device, a folder or a file whose header promises more than it holds is refused before its body is read.
#pragma once

#include <string>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "formats/ply.hpp"

namespace cellsight::formats {

// "PATH: is a directory<what>" or "PATH: is not a regular file (a device, pipe or socket)<what>"; a path that
// cannot be looked at gives "PATH: cannot open: <reason>". `what` ends the message, e.g. ", not a configuration file".
[[nodiscard]] Status check_regular_file(const std::string& path, const std::string& what);

// Checks a PLY scan without reading its body: a regular file, a header that ends within limits.max_header_bytes,
// a vertex count within limits.max_vertices, and at least as many bytes after the header as the declared
// elements need. Errors begin with the path.
[[nodiscard]] Status check_ply_file(const std::string& path, const formats::PlyLimits& limits = {});

// check_ply_file, then the whole file (at most its size at the check).
[[nodiscard]] Expected<std::string> read_ply_file(const std::string& path, const formats::PlyLimits& limits = {});

// read_ply_file, then algo::parse_ply; errors begin with the path.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> load_ply_file(const std::string& path,
                                                                   const formats::PlyLimits& limits = {});

}  // namespace cellsight::formats
