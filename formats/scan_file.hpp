// Compact taught-scan files (models/scans/NAME/NNNNN.cscan, issue 11): points quantised to a fixed step, each field
// in its own plane, delta-coded in scan order and zlib-compressed: ~5x smaller than the binary PLY of the same scan,
// so 3 600 taught scans fit the 3 GB database. Parses from memory: the caller does the file I/O.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan.hpp"

namespace cellsight::formats {

// File layout, version 1 (all numbers little-endian):
//   [0, 80)   header: magic (8), version u32, header bytes u32 (80), point count u64, step in nm u32, flags u32 (0),
//             origin i32 x 3 (in steps), extent u32 x 3 (in steps), raw bytes u64 (inflated payload),
//             compressed bytes u64 (the rest of the file), zeros up to 76, CRC-32 of bytes [0, 76) in [76, 80)
//   [80, end) zlib stream of the payload: five planes in this order, each point_count LEB128 varints of the
//             zig-zagged difference to the previous point's value (the first point: to 0):
//             x, y, z (steps above the origin, 0..extent), frame, row (0..65535)
// Consecutive points are neighbours on a profile (or consecutive profiles), so the differences are small and the
// planes compress well; frame and row are kept exactly.
inline constexpr std::uint32_t kScanFileVersion = 1;
inline constexpr std::size_t kScanFileHeaderBytes = 80;
// "CSCAN", then CR LF and SUB as in PNG's magic: a transfer that mangles line ends or text is caught at once.
inline constexpr std::string_view kScanFileMagic{"CSCAN\r\n\x1a", 8};

// The quantisation step: 16 um. Far below the sensor's ~0.25 mm noise and the 2.2 mm template grid, so features and
// Perfect Match cannot tell the difference (a uniform error of +-8 um has an RMS of 4.6 um, 1/50 of the noise);
// coarser would save ~1 bit per axis and point, finer would store noise. The largest error is step / 2 per axis.
inline constexpr std::uint32_t kScanStepNm = 16'000;

struct ScanFileLimits {
  std::size_t max_points = 20'000'000;  // as PlyLimits::max_vertices: a scan is ~0.1-0.5 M points
};

// The file's bytes. Refuses a point with a non-finite coordinate or one beyond the range the quantised origin can
// hold (+-34 km at 16 um): taught scans come from the scan builder, whose points are finite.
[[nodiscard]] Expected<std::string> write_scan_file(std::span<const algo::ScanPoint> points,
                                                    std::uint32_t step_nm = kScanStepNm);

// Whether `bytes` begins with the magic (the dispatch between this format and PLY).
[[nodiscard]] bool is_scan_file(std::string_view bytes);

// Every malformed input (bad magic, other version, damaged header, a point count above the limit, sizes that do not
// add up, a payload that inflates to more or fewer bytes than declared, values beyond the declared extent) is
// refused with a message that says what is wrong, before anything large is allocated; nothing is half-returned.
// Each coordinate comes back within step / 2 of what was written; frame and row exactly.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> parse_scan_file(std::string_view bytes,
                                                                     const ScanFileLimits& limits = {});

}  // namespace cellsight::formats
