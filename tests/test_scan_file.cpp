// The compact taught-scan file (formats/scan_file): a real simulated scan comes back within half a step, frame and row
// exact, at a fraction of its PLY size; every damaged, truncated or forged file is refused with its reason.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>

#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/scan_acquisition.hpp"
#include "base/crc32.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "tests/scratch_dir.hpp"
#include "true_calibration_file.hpp"

using namespace cellsight;

namespace {

constexpr double kStepM = formats::kScanStepNm * 1e-9;
// Half a step, and the float's own rounding of a coordinate within a few metres (half an ulp at 4 m: 0.24 um).
constexpr double kMaxErrorM = kStepM / 2 + 2.4e-7;
constexpr std::size_t kCrcAt = formats::kScanFileHeaderBytes - 4;  // the header CRC covers what comes before

// One pass of a catalogue part on the simulated cell with the shipped configuration, carrier included, as teach
// stores it.
std::vector<algo::ScanPoint> simulated_scan(const std::string& part, std::uint64_t seed) {
  auto config = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(config.ok());
  const auto dir = test::scratch_path("scan-file-" + part);
  std::filesystem::create_directories(dir);
  const std::string calibration = (dir / "calibration.yaml").string();
  test::write_true_calibration(*config, calibration);
  std::vector<algo::ScanPoint> out;
  const auto ok = app::acquire_sim_passes(*config, part, 1, seed, calibration, "scanned",
                                          [&](int, std::uint64_t, std::vector<algo::ScanPoint>&& points) -> Status {
                                            out = std::move(points);
                                            return {};
                                          });
  REQUIRE(ok.ok());
  REQUIRE(out.size() > 10'000);
  return out;
}

void check_round_trip(const std::vector<algo::ScanPoint>& in, const std::vector<algo::ScanPoint>& out) {
  REQUIRE(out.size() == in.size());
  double worst = 0.0;
  std::size_t id_mismatches = 0;
  for (std::size_t i = 0; i < in.size(); ++i) {
    worst = std::max({worst, std::fabs(double{out[i].x} - in[i].x), std::fabs(double{out[i].y} - in[i].y),
                      std::fabs(double{out[i].z} - in[i].z)});
    id_mismatches += out[i].frame != in[i].frame || out[i].row != in[i].row ? 1 : 0;
  }
  CHECK(worst <= kMaxErrorM);
  CHECK(id_mismatches == 0);
}

// The header field of type T at `at` replaced by `value`, the header CRC made to match again: a forged file.
template <class T>
std::string forged(std::string file, std::size_t at, T value) {
  std::memcpy(file.data() + at, &value, sizeof value);
  const std::uint32_t crc = base::crc32(std::string_view(file).substr(0, kCrcAt));
  std::memcpy(file.data() + kCrcAt, &crc, sizeof crc);
  return file;
}

std::string refusal(std::string_view bytes, const formats::ScanFileLimits& limits = {}) {
  const auto r = formats::parse_scan_file(bytes, limits);
  return r.ok() ? std::string("accepted") : r.error().message;
}

bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

// A small scan with the awkward values: negative coordinates, frame and row at both ends, jumps between them.
std::vector<algo::ScanPoint> awkward_points() {
  return {{-0.5F, 1.25F, 0.003F, 0, 0},
          {0.75F, -1.5F, -0.25F, 65535, 65535},
          {0.75F, -1.5F, -0.25F, 0, 65535},
          {1e-9F, 0.0F, -1e-9F, 1, 0},
          {0.123456F, 0.654321F, 0.0F, 65535, 1}};
}

// The file's size against the binary PLY of the same points, printed; the ratio.
double compression_ratio(const std::vector<algo::ScanPoint>& scan, const char* what) {
  const std::size_t ply_bytes = formats::write_ply_binary(scan).size();
  const std::size_t bytes = formats::write_scan_file(scan)->size();
  const double ratio = static_cast<double>(ply_bytes) / static_cast<double>(bytes);
  std::printf("scan_file, %s: %zu points: binary PLY %.2f MB, compact %.3f MB (%.2f bytes a point), ratio %.1f : 1\n",
              what, scan.size(), static_cast<double>(ply_bytes) / 1e6, static_cast<double>(bytes) / 1e6,
              static_cast<double>(bytes) / static_cast<double>(scan.size()), ratio);
  return ratio;
}

}  // namespace

TEST_CASE("a simulated scan comes back within half a step, frame and row exact, several times smaller than its PLY",
          "[scan_file]") {
  // Given a real pass of a part on the simulated cell (carrier included, as teach stores it) ...
  const std::vector<algo::ScanPoint> scan = simulated_scan("plate_4h", 3);
  // ... when it is written compactly and read back ...
  auto file = formats::write_scan_file(scan);
  REQUIRE(file.ok());
  CHECK(formats::is_scan_file(*file));
  auto back = formats::parse_scan_file(*file);
  REQUIRE(back.ok());
  // ... then every point is where it was to half a step, and the file is a fraction of the binary PLY's size.
  check_round_trip(scan, *back);
  CHECK(compression_ratio(scan, "simulated pass") >= 8.0);
  // The database reads it through the same dispatch as a PLY of the same scan (whose frame and row PLY drops).
  auto dispatched = app::parse_taught_scan(*file);
  REQUIRE(dispatched.ok());
  check_round_trip(scan, *dispatched);
  auto from_ply = app::parse_taught_scan(formats::write_ply_binary(scan));
  REQUIRE(from_ply.ok());
  CHECK(from_ply->size() == scan.size());
}

TEST_CASE("with a real sensor's noise on every point the file is still at least 3 times smaller than the PLY",
          "[scan_file]") {
  // Given the simulated pass with Gaussian noise as a real sensor has it (algo/perturb's model: 0.25 mm along the
  // viewing ray, z, 0.3 of that in y, x from the encoder exact): noise is what a lossless coder cannot remove.
  std::vector<algo::ScanPoint> scan = simulated_scan("plate_4h", 3);
  constexpr double kNoiseZM = 0.25e-3, kNoiseYShare = 0.3;
  std::mt19937_64 random(11);
  std::normal_distribution<double> noise(0.0, kNoiseZM);
  for (algo::ScanPoint& p : scan) {
    p.z = static_cast<float>(p.z + noise(random));
    p.y = static_cast<float>(p.y + kNoiseYShare * noise(random));
  }
  auto back = formats::parse_scan_file(*formats::write_scan_file(scan));
  REQUIRE(back.ok());
  check_round_trip(scan, *back);
  CHECK(compression_ratio(scan, "with 0.25 mm sensor noise") >= 3.0);
}

TEST_CASE("awkward values, one point and no point round-trip, a coarser step keeps its own bound", "[scan_file]") {
  const std::vector<algo::ScanPoint> points = awkward_points();
  auto file = formats::write_scan_file(points);
  REQUIRE(file.ok());
  auto back = formats::parse_scan_file(*file);
  REQUIRE(back.ok());
  check_round_trip(points, *back);

  auto one = formats::parse_scan_file(*formats::write_scan_file(std::span(points).first(1)));
  REQUIRE(one.ok());
  check_round_trip({points.front()}, *one);

  auto none = formats::write_scan_file({});
  REQUIRE(none.ok());
  auto empty = formats::parse_scan_file(*none);
  REQUIRE(empty.ok());
  CHECK(empty->empty());

  constexpr std::uint32_t kMillimetreNm = 1'000'000;
  auto coarse = formats::parse_scan_file(*formats::write_scan_file(points, kMillimetreNm));
  REQUIRE(coarse.ok());
  for (std::size_t i = 0; i < points.size(); ++i)
    CHECK(std::fabs(double{(*coarse)[i].x} - points[i].x) <= 0.5e-3 + 1e-7);
  CHECK_FALSE(formats::write_scan_file(points, 0).ok());
}

TEST_CASE("a point that is not finite or lies beyond the quantised range is refused by the writer, naming it",
          "[scan_file]") {
  for (const float bad : {std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity(),
                          -std::numeric_limits<float>::infinity(), 1e30F}) {
    std::vector<algo::ScanPoint> points = awkward_points();
    points[3].z = bad;
    const auto r = formats::write_scan_file(points);
    REQUIRE_FALSE(r.ok());
    CHECK(contains(r.error().message, "point 3 has a non-finite coordinate or one beyond"));
  }
}

TEST_CASE("the reader refuses another magic, another version, a damaged header and trailing bytes", "[scan_file]") {
  const std::string file = *formats::write_scan_file(awkward_points());
  CHECK(contains(refusal(formats::write_ply_binary(awkward_points())), "not a cellsight scan file (no CSCAN magic)"));
  CHECK(contains(refusal(""), "no CSCAN magic"));
  std::string v2 = file;
  v2[8] = 2;
  CHECK(contains(refusal(v2), "format version 2 is not supported (this cellsight reads version 1)"));
  for (std::size_t at = 12; at < kCrcAt; ++at) {
    std::string damaged = file;
    damaged[at] = static_cast<char>(damaged[at] ^ 0x10);
    INFO("header byte " << at);
    CHECK(contains(refusal(damaged), "the header is damaged"));
  }
  CHECK(contains(refusal(file + "x"), "1 bytes after the data"));
  CHECK(contains(refusal(forged<std::uint32_t>(file, 28, 1)), "flags"));
  CHECK(contains(refusal(forged<std::uint32_t>(file, 72, 1)), "reserved bytes"));
  CHECK(contains(refusal(forged<std::uint32_t>(file, 24, 0)), "step of 0 nm"));
}

TEST_CASE("a file cut at any length is refused", "[scan_file]") {
  const std::string file = *formats::write_scan_file(simulated_scan("bracket_l", 5));
  std::size_t accepted = 0;
  const std::size_t stride = std::max<std::size_t>(1, file.size() / 997);
  for (std::size_t n = 0; n < file.size(); n += n < 2 * formats::kScanFileHeaderBytes ? 1 : stride) {
    accepted += formats::parse_scan_file(std::string_view(file).substr(0, n)).ok() ? 1 : 0;
  }
  CHECK(accepted == 0);
  CHECK(contains(refusal(std::string_view(file).substr(0, 40)), "truncated: 40 bytes, the header alone takes 80"));
  CHECK(contains(refusal(std::string_view(file).substr(0, file.size() - 1)), "truncated: "));
}

TEST_CASE("a damaged compressed byte is refused wherever it lies", "[scan_file]") {
  const std::string file = *formats::write_scan_file(simulated_scan("plate_4h", 4));
  std::size_t accepted = 0;
  std::size_t tried = 0;
  const std::size_t stride = std::max<std::size_t>(1, (file.size() - formats::kScanFileHeaderBytes) / 499);
  for (std::size_t at = formats::kScanFileHeaderBytes; at < file.size(); at += stride) {
    std::string damaged = file;
    damaged[at] = static_cast<char>(damaged[at] ^ 0x5A);
    accepted += formats::parse_scan_file(damaged).ok() ? 1 : 0;
    ++tried;
  }
  CHECK(tried > 400);
  CHECK(accepted == 0);
  std::string last = file;
  last.back() = static_cast<char>(last.back() ^ 1);  // the stream's own check value
  CHECK(contains(refusal(last), "the compressed data is damaged"));
}

TEST_CASE("a point count above the limit is refused before anything is allocated, forged sizes are refused",
          "[scan_file]") {
  const std::vector<algo::ScanPoint> points = awkward_points();
  const std::string file = *formats::write_scan_file(points);
  formats::ScanFileLimits limits;
  limits.max_points = points.size() - 1;
  CHECK(contains(refusal(file, limits), "5 points is more than a scan can have (limit 4)"));
  // A header that claims 2^40 points, or a payload a thousand times larger than deflate can give from the file.
  CHECK(contains(refusal(forged<std::uint64_t>(file, 16, std::uint64_t{1} << 40)), "more than a scan can have"));
  CHECK(contains(refusal(forged<std::uint64_t>(file, 56, std::uint64_t{1} << 40)), "the declared sizes do not fit"));
  CHECK(contains(refusal(forged<std::uint64_t>(file, 64, 7)), "bytes after the data"));

  // An inflate that yields more or fewer bytes than the header declares.
  const std::string real = *formats::write_scan_file(simulated_scan("plate_4h", 6));
  std::uint64_t raw = 0;
  std::memcpy(&raw, real.data() + 56, sizeof raw);
  CHECK(contains(refusal(forged<std::uint64_t>(real, 56, raw - 1)), "inflates to more than the declared"));
  CHECK(contains(refusal(forged<std::uint64_t>(real, 56, raw + 1)), "fewer than the declared"));
  // Values beyond the declared extent (the payload is intact, the header says the part is smaller).
  std::uint32_t extent_z = 0;
  std::memcpy(&extent_z, real.data() + 52, sizeof extent_z);
  CHECK(contains(refusal(forged<std::uint32_t>(real, 52, extent_z - 1)), "z of point"));
}
