// libFuzzer target: the model database manifest (models/manifest.yaml, app::parse_manifest, what ModelDb::open
// does with the file's bytes). Input: a mode byte, then the file (tests/fuzz/fuzz_util.hpp). Whatever is accepted
// must survive the next save: written back by manifest_text, it reads as the same database.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <string>

#include "base/crc32.hpp"
#include "formats/manifest.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight;

constexpr const char* kChecksumKey = "checksum_crc32:";  // the manifest's last line (formats/manifest.cpp)

// Rewrites the last checksum line (or appends one) with the checksum of everything before it.
void repair_checksum(std::string& text) {
  const std::size_t at = text.rfind(std::string("\n") + kChecksumKey);
  std::string body = at == std::string::npos ? text : text.substr(0, at + 1);
  if (!body.empty() && body.back() != '\n') body += '\n';
  char line[40];
  std::snprintf(line, sizeof line, "%s \"%08x\"\n", kChecksumKey, static_cast<unsigned>(base::crc32(body)));
  text = body + line;
}

bool same_manifest(const formats::Manifest& a, const formats::Manifest& b) {
  if (a.format_version != b.format_version || a.feature_version != b.feature_version || a.grid.nx != b.grid.nx ||
      a.grid.ny != b.grid.ny || a.grid.nz != b.grid.nz || a.grid.resolution_m != b.grid.resolution_m ||
      a.grid.origin_m != b.grid.origin_m || a.parts.size() != b.parts.size()) {
    return false;
  }
  for (std::size_t i = 0; i < a.parts.size(); ++i) {
    const formats::PartEntry& p = a.parts[i];
    const formats::PartEntry& q = b.parts[i];
    if (p.name != q.name || p.id != q.id || p.template_file != q.template_file || p.taught_at != q.taught_at ||
        p.template_scan != q.template_scan || p.confusable != q.confusable || p.flagged != q.flagged ||
        p.scans.size() != q.scans.size() || p.thresholds.learnt != q.thresholds.learnt ||
        p.thresholds.max_error != q.thresholds.max_error) {
      return false;
    }
    for (std::size_t s = 0; s < p.scans.size(); ++s) {
      if (p.scans[s].file != q.scans[s].file || p.scans[s].crc32 != q.scans[s].crc32 ||
          p.scans[s].source != q.scans[s].source) {
        return false;
      }
    }
  }
  const formats::SvmEntry& s = a.svm;
  const formats::SvmEntry& t = b.svm;
  return s.present == t.present && s.file == t.file && s.crc32 == t.crc32 && s.trained_at == t.trained_at &&
         s.parts_fingerprint == t.parts_fingerprint && s.hyper == t.hyper && s.train_scans == t.train_scans;
}

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::ChecksummedInput in = fuzz::split_mode_byte(data, size);
  if (in.repair) repair_checksum(in.file);
  auto manifest = formats::parse_manifest("manifest.yaml", in.file);
  if (!manifest) return 0;
  auto again = formats::parse_manifest("manifest.yaml", formats::manifest_text(*manifest));
  CS_FUZZ_EXPECT(again.ok() && same_manifest(*manifest, *again));
  return 0;
}
