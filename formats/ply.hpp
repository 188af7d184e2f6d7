// PLY scans (DESIGN.md): ASCII or binary little-endian, `element vertex` with float/double x, y, z in metres in
// the carrier frame; other properties and elements are skipped. Parses from memory: the caller does the file I/O.
#pragma once

#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan.hpp"

namespace cellsight::formats {

struct PlyLimits {
  std::size_t max_vertices = 20'000'000;  // a scan is ~0.5 M points; anything far larger is not a scan
  std::size_t max_header_bytes = 65'536;  // end_header must come within these: a header is a few hundred bytes
};

// What a checked header declares, so a file can be judged before its body is read.
struct PlyHeader {
  bool binary = false;
  std::size_t data_start = 0;      // bytes before the data
  std::size_t vertex_count = 0;    // within PlyLimits::max_vertices
  std::size_t min_data_bytes = 0;  // the least data the elements up to the vertices need (a longer file may be fine)
};

// The header checks of parse_ply on the first bytes of a file (at least up to end_header and its line break).
[[nodiscard]] Expected<PlyHeader> parse_ply_header(std::string_view bytes, const PlyLimits& limits = {});

// Every malformed input (bad magic, unsupported format, missing x/y/z, truncated data, non-finite coordinates,
// counts that do not fit) is refused with a message that says what is wrong; nothing is half-returned.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> parse_ply(std::string_view bytes, const PlyLimits& limits = {});

// Binary little-endian PLY with float x, y, z and ushort frame, row (readers that do not know them skip them).
[[nodiscard]] std::string write_ply_binary(std::span<const algo::ScanPoint> points);
[[nodiscard]] std::string write_ply_ascii(std::span<const algo::ScanPoint> points);

}  // namespace cellsight::formats
