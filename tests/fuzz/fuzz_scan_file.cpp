// libFuzzer target: compact taught-scan files (formats/scan_file), as train and `parts export` read them from the
// model database. Input: a mode byte, then the file (tests/fuzz/fuzz_util.hpp); with the repair bit the header CRC
// is made to match, so mutations reach the size checks, the inflate and the plane decoder behind it. Whatever is
// accepted stays within the limit and writes and reads back to the same points (within half a step).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include "base/crc32.hpp"
#include "formats/scan_file.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight;

constexpr std::size_t kHeaderCrcOffset = formats::kScanFileHeaderBytes - 4;  // the header's last 4 bytes
constexpr std::size_t kStepOffset = 24;                                      // step in nm, u32 (scan_file.hpp)

void repair_checksum(std::string& file) {
  if (file.size() < formats::kScanFileHeaderBytes) return;
  fuzz::store_u32(file, kHeaderCrcOffset, base::crc32(std::string_view(file).substr(0, kHeaderCrcOffset)));
}

// Within half a step of the file's step, and the float's rounding of a value that large.
bool near(float a, float b, double step_m) {
  const double tolerance = step_m / 2 + std::fabs(double{a}) * 1e-6 + 1e-9;
  return std::fabs(double{a} - double{b}) <= tolerance;
}

void check(const std::string& file, const formats::ScanFileLimits& limits) {
  const auto points = formats::parse_scan_file(file, limits);
  if (!points) return;
  CS_FUZZ_EXPECT(points->size() <= limits.max_points);
  std::uint32_t step_nm = 0;
  std::memcpy(&step_nm, file.data() + kStepOffset, sizeof step_nm);
  const auto again = formats::write_scan_file(*points, step_nm);
  if (!again) return;  // a coordinate at the edge of the quantised range may round beyond it: refused, not wrong
  const auto back = formats::parse_scan_file(*again, limits);
  CS_FUZZ_EXPECT(back.ok() && back->size() == points->size());
  const double step_m = step_nm * 1e-9;
  for (std::size_t i = 0; i < points->size(); ++i) {
    const algo::ScanPoint& p = (*points)[i];
    const algo::ScanPoint& q = (*back)[i];
    CS_FUZZ_EXPECT(p.frame == q.frame && p.row == q.row);
    CS_FUZZ_EXPECT(near(p.x, q.x, step_m) && near(p.y, q.y, step_m) && near(p.z, q.z, step_m));
  }
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::ChecksummedInput in = fuzz::split_mode_byte(data, size);
  if (in.repair) repair_checksum(in.file);
  check(in.file, formats::ScanFileLimits{});
  // A small limit too, so that the count check itself is reached by small inputs.
  check(in.file, formats::ScanFileLimits{.max_points = 16});
  return 0;
}
