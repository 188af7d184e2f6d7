// Writes the seed corpus of the fuzz targets (tests/fuzz/corpus/<target>/) with cellsight's own writers, so the
// seeds are what the product produces: scans, a template for a tiny grid, a trained SVM, a manifest, Modbus frames.
// Usage: make_fuzz_seeds CORPUS_DIR (scripts/fuzz.sh --seeds). The shipped config is copied by the script.
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "algo/cascade.hpp"
#include "algo/svm.hpp"
#include "base/file_read.hpp"
#include "formats/manifest.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "formats/template_file.hpp"
#include "tests/fuzz/seed_grid.hpp"

namespace {

using namespace cellsight;
namespace fs = std::filesystem;

constexpr char kVerbatim = '\0';  // mode byte of the checksummed targets: the reader checks the checksums
constexpr char kRepair = '\1';    // the target recomputes them before the reader sees the file

bool put(const fs::path& path, const std::string& bytes) {
  fs::create_directories(path.parent_path());
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  if (!out) std::fprintf(stderr, "make_fuzz_seeds: cannot write %s\n", path.c_str());
  return static_cast<bool>(out);
}

// Both modes of one checksummed file.
bool put_checksummed(const fs::path& dir, const std::string& name, const std::string& file) {
  return put(dir / (name + "-verbatim"), kVerbatim + file) && put(dir / (name + "-repair"), kRepair + file);
}

std::vector<algo::ScanPoint> small_scan() {
  std::vector<algo::ScanPoint> points;
  for (int i = 0; i < 6; ++i) {
    points.push_back({0.012F + 0.01F * static_cast<float>(i), 0.025F + 0.005F * static_cast<float>(i), 0.035F,
                      static_cast<std::uint16_t>(i), static_cast<std::uint16_t>(10 + i)});
  }
  return points;
}

bool ply_seeds(const fs::path& dir) {
  const auto points = small_scan();
  // Another exporter's file: a comment, a face list before the vertices, double coordinates, an extra property.
  const std::string foreign =
      "ply\r\nformat ascii 1.0\r\ncomment other scanner\r\nelement face 1\r\nproperty list uchar int vertex_indices\r\n"
      "element vertex 2\r\nproperty double x\r\nproperty double y\r\nproperty uchar intensity\r\nproperty double z\r\n"
      "end_header\r\n3 0 1 1\r\n0.1 0.2 7 0.3\r\n-0.5 1e-3 255 2.5\r\n";
  return put(dir / "binary.ply", formats::write_ply_binary(points)) &&
         put(dir / "ascii.ply", formats::write_ply_ascii(points)) && put(dir / "foreign.ply", foreign);
}

Expected<std::string> template_file(const fs::path& scratch) {
  auto model = formats::build_template(small_scan(), fuzz::seed_template_grid());
  if (!model) return model.error();
  const std::string path = (scratch / "seed.dmap").string();
  if (Status written = formats::write_template(path, *model, {"seed_part", 7, 1700000000}); !written) {
    return written.error();
  }
  constexpr std::size_t kMaxSeedTemplateBytes = std::size_t{64} << 20;  // an 8 x 8 x 8 grid's: a few kB
  return base::read_file(path, kMaxSeedTemplateBytes);
}

Expected<std::string> svm_file() {
  // Two classes, three samples each, on three features.
  std::vector<algo::FeatureVector> features;
  std::vector<int> labels;
  for (int i = 0; i < 6; ++i) {
    algo::FeatureVector f{};
    f[0] = static_cast<float>(i % 2) + 0.1F * static_cast<float>(i);
    f[1] = static_cast<float>(i % 2) * 2.0F - 0.05F * static_cast<float>(i);
    f[20] = 0.3F * static_cast<float>(i);
    features.push_back(f);
    labels.push_back(i % 2);
  }
  algo::FeatureMask mask;
  mask.set(0).set(1).set(20);
  algo::silence_libsvm();
  auto model = algo::SvmModel::train(features, labels, {{"seed_a", 1}, {"seed_b", 2}}, mask,
                                     algo::Scaler::fit(features), algo::SvmHyper{}, 1);
  if (!model) return model.error();
  return model->serialize();
}

std::string manifest_file() {
  formats::Manifest m;
  m.feature_version = algo::kFeatureVersion;
  m.learn_version = algo::kLearnVersion;
  m.grid = fuzz::seed_template_grid();
  for (int p = 0; p < 2; ++p) {
    formats::PartEntry e;
    e.name = p == 0 ? "seed_a" : "seed_b";
    e.id = p + 1;
    e.template_file = "templates/" + e.name + ".dmap";
    e.taught_at = "2024-01-02 03:04:05";
    e.scans = {{"scans/" + e.name + "/0001.ply", 0x12345678U, "sim seed 1"},
               {"scans/" + e.name + "/0002.ply", 0x9abcdef0U, "/data/import \"b\".ply"}};
    e.template_scan = e.scans[1].file;
    e.thresholds = {true, 0.01, 0.002, 0.003, 0.1, 0.05, 0.0005, 0.001, -0.002, 0.01};
    e.confusable = {p == 0 ? "seed_b" : "seed_a"};
    e.flagged = {e.scans[0].file};
    m.parts.push_back(e);
  }
  m.svm = {true, "svm.bin", 0x0badf00dU, "2024-01-02 03:04:06", "deadbeef-2", 0.9, 0.85, 4, 2, 3, "rbf C=1"};
  return formats::manifest_text(m);
}

std::string frame(std::initializer_list<int> bytes) {
  std::string out;
  for (const int b : bytes) out += static_cast<char>(b);
  return out;
}

bool modbus_seeds(const fs::path& dir) {
  // MBAP (transaction, protocol 0, length, unit 1), then the PDU; as a PLC sends them (README register map): the
  // whole result block 200-234 of map version 2, and 200-226 as a PLC written for version 1 still reads it.
  const std::string read_result = frame({0, 1, 0, 0, 0, 6, 1, 3, 0, 200, 0, 35});
  const std::string read_result_v1 = frame({0, 5, 0, 0, 0, 6, 1, 3, 0, 200, 0, 27});
  const std::string read_status = frame({0, 2, 0, 0, 0, 6, 1, 4, 0, 100, 0, 20});
  const std::string write_control = frame({0, 3, 0, 0, 0, 6, 1, 6, 0, 0, 0, 4});
  const std::string write_command = frame({0, 4, 0, 0, 0, 13, 1, 16, 0, 1, 0, 3, 6, 0, 1, 0, 0, 0, 2});
  return put(dir / "read_result", read_result) && put(dir / "read_result_v1", read_result_v1) &&
         put(dir / "read_status", read_status) && put(dir / "write_control", write_control) &&
         put(dir / "write_command", write_command) && put(dir / "pipelined", read_status + write_control + read_result);
}

}  // namespace

// A scan as teach stores it, and the empty scan, each in both modes.
bool scan_file_seeds(const fs::path& dir) {
  auto scan = formats::write_scan_file(small_scan());
  auto empty = formats::write_scan_file({});
  if (!scan || !empty) return false;
  return put_checksummed(dir, "scan.cscan", *scan) && put_checksummed(dir, "empty.cscan", *empty);
}

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_fuzz_seeds CORPUS_DIR\n");
    return 2;
  }
  const fs::path corpus(argv[1]);
  const fs::path scratch = fs::temp_directory_path() / "cellsight-fuzz-seeds";
  fs::create_directories(scratch);
  auto dmap = template_file(scratch);
  fs::remove_all(scratch);
  auto svm = svm_file();
  if (!dmap || !svm) {
    std::fprintf(stderr, "make_fuzz_seeds: %s\n", (dmap ? svm.error() : dmap.error()).message.c_str());
    return 1;
  }
  const bool ok = ply_seeds(corpus / "fuzz_ply") && scan_file_seeds(corpus / "fuzz_scan_file") &&
                  put_checksummed(corpus / "fuzz_template", "seed.dmap", *dmap) &&
                  put_checksummed(corpus / "fuzz_svm", "svm.bin", *svm) &&
                  put_checksummed(corpus / "fuzz_manifest", "manifest.yaml", manifest_file()) &&
                  modbus_seeds(corpus / "fuzz_modbus_request");
  return ok ? 0 : 1;
}
