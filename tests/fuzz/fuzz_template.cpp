// libFuzzer target: Perfect Match template files (formats/template_file): the header reader of `parts list/show` and
// the checked, memory-mapped open of `run` and `classify`, on a scratch file (both take a path). Input: a mode byte,
// then the file (tests/fuzz/fuzz_util.hpp). An opened template is sampled as Perfect Match samples it.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string>

#include "base/crc32.hpp"
#include "formats/template_file.hpp"
#include "tests/fuzz/fuzz_util.hpp"
#include "tests/fuzz/seed_grid.hpp"

namespace {

using namespace cellsight;

constexpr std::size_t kHeaderCrcOffset = formats::kTemplateHeaderBytes - 4;  // the header's last 4 bytes
constexpr std::size_t kMaxSamples = 256;

void repair_checksums(std::string& file) {
  if (file.size() < formats::kTemplateHeaderBytes) return;
  const std::string_view bytes(file);
  fuzz::store_u32(file, formats::kTemplateBodyCrcOffset, base::crc32(bytes.substr(formats::kTemplateHeaderBytes)));
  fuzz::store_u32(file, kHeaderCrcOffset, base::crc32(bytes.substr(0, kHeaderCrcOffset)));
}

void sample(const formats::TemplateFile& t) {
  const algo::DistanceMapView& view = t.view();
  (void)view.sample(t.centroid_m().x(), t.centroid_m().y(), 0.0);
  const auto cells = t.surface_cells();
  const algo::GridDims& d = view.dims();
  for (std::size_t i = 0; i < std::min(cells.size(), kMaxSamples); ++i) {
    const Eigen::Vector3d p = view.origin_m() + d.resolution_m * Eigen::Vector3d(cells[i].x, cells[i].y, cells[i].z);
    (void)view.sample(p.x(), p.y(), p.z());
  }
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static fuzz::ScratchFile file("cellsight-fuzz-template");
  fuzz::ChecksummedInput in = fuzz::split_mode_byte(data, size);
  if (in.repair) repair_checksums(in.file);
  const std::string& path = file.write(in.file);
  const auto info = formats::read_template_info(path);
  // As run and classify open it: against the configured grid.
  if (auto opened = formats::TemplateFile::open(path, fuzz::seed_template_grid())) {
    CS_FUZZ_EXPECT(info.ok() && opened->surface_cells().size() == info->surface_cell_count);
    sample(*opened);
  }
  // Against the grid the header names, so that headers for other grids reach the checks behind the grid's.
  if (info) (void)formats::TemplateFile::open(path, info->grid);
  return 0;
}
