// libFuzzer target: PLY scans (formats/ply, formats/input_file). Every input is parsed in memory and, through a file,
// by the checks classify and teach run before reading a body; the two must agree, and whatever is accepted must
// survive a write and a re-read unchanged.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string_view>
#include <vector>

#include "formats/input_file.hpp"
#include "formats/ply.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight;

bool same_points(const std::vector<algo::ScanPoint>& a, const std::vector<algo::ScanPoint>& b) {
  if (a.size() != b.size()) return false;
  for (std::size_t i = 0; i < a.size(); ++i) {
    if (a[i].x != b[i].x || a[i].y != b[i].y || a[i].z != b[i].z) return false;
  }
  return true;
}

void check(std::string_view bytes, const std::string& path, const formats::PlyLimits& limits) {
  const auto in_memory = formats::parse_ply(bytes, limits);
  const auto from_file = formats::load_ply_file(path, limits);
  // The file checks refuse only what the parser would refuse too (they judge the header and the size alone).
  CS_FUZZ_EXPECT(in_memory.ok() == from_file.ok());
  if (!in_memory) return;
  CS_FUZZ_EXPECT(same_points(*in_memory, *from_file));
  CS_FUZZ_EXPECT(formats::check_ply_file(path, limits).ok());
  for (const algo::ScanPoint& p : *in_memory)
    CS_FUZZ_EXPECT(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z));
  // What cellsight writes of an accepted scan reads back as the same points (scan --out, perturb).
  const auto again = formats::parse_ply(formats::write_ply_binary(*in_memory));
  CS_FUZZ_EXPECT(again.ok() && same_points(*again, *in_memory));
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static fuzz::ScratchFile file("cellsight-fuzz-ply");
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  const std::string& path = file.write(bytes);
  check(bytes, path, formats::PlyLimits{});
  // Small limits too, so that the limit checks themselves are reached by small inputs.
  constexpr formats::PlyLimits kTight{.max_vertices = 16, .max_header_bytes = 200};
  check(bytes, path, kTight);
  return 0;
}
