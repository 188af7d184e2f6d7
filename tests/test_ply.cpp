// PLY scans: round trips, the DESIGN.md subset (ASCII, binary LE, float/double, extra properties), and refusals.
#include <catch2/catch.hpp>
#include <chrono>
#include <cstring>
#include <limits>
#include <random>

#include "formats/ply.hpp"

using namespace cellsight;

namespace {

std::vector<algo::ScanPoint> sample_points() {
  std::vector<algo::ScanPoint> pts;
  for (int i = 0; i < 257; ++i) {
    pts.push_back({0.001F * i, 1.0F - 0.002F * i, 0.1F + 0.0001F * i, static_cast<std::uint16_t>(i / 10),
                   static_cast<std::uint16_t>(i)});
  }
  return pts;
}

template <class T>
void append(std::string& s, T v) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  s.append(b, sizeof(T));
}

std::string parse_error(const std::string& text) {
  auto r = formats::parse_ply(text);
  REQUIRE_FALSE(r.ok());
  return r.error().message;
}

}  // namespace

TEST_CASE("Given points, when written as binary or ASCII PLY and read back, then x, y, z are unchanged") {
  const auto pts = sample_points();
  for (const std::string& file : {formats::write_ply_binary(pts), formats::write_ply_ascii(pts)}) {
    auto back = formats::parse_ply(file);
    REQUIRE(back.ok());
    REQUIRE(back->size() == pts.size());
    for (std::size_t i = 0; i < pts.size(); ++i) {
      CHECK((*back)[i].x == Approx(pts[i].x).margin(1e-8));
      CHECK((*back)[i].y == Approx(pts[i].y).margin(1e-8));
      CHECK((*back)[i].z == Approx(pts[i].z).margin(1e-8));
    }
  }
}

TEST_CASE(
    "Given a binary PLY from another tool (double x y z, colour, normals, a face element first), when read, "
    "then the vertices come through and the rest is skipped") {
  std::string f =
      "ply\nformat binary_little_endian 1.0\ncomment other scanner\nelement face 2\n"
      "property list uchar int vertex_indices\nelement vertex 3\nproperty double x\nproperty uchar red\n"
      "property double y\nproperty float nx\nproperty double z\nend_header\n";
  for (int face = 0; face < 2; ++face) {
    append<std::uint8_t>(f, 3);
    for (int k = 0; k < 3; ++k) append<std::int32_t>(f, k);
  }
  for (int i = 0; i < 3; ++i) {
    append<double>(f, 0.1 * i);
    append<std::uint8_t>(f, 200);
    append<double>(f, 0.5);
    append<float>(f, 0.0F);
    append<double>(f, -0.25 * i);
  }
  auto pts = formats::parse_ply(f);
  REQUIRE(pts.ok());
  REQUIRE(pts->size() == 3);
  CHECK((*pts)[2].x == Approx(0.2));
  CHECK((*pts)[2].y == Approx(0.5));
  CHECK((*pts)[2].z == Approx(-0.5));
}

TEST_CASE("Given an ASCII PLY with extra columns and CRLF lines, when read, then x, y, z are taken by name") {
  const std::string f =
      "ply\r\nformat ascii 1.0\r\nelement vertex 2\r\nproperty float z\r\nproperty float intensity\r\n"
      "property float x\r\nproperty float y\r\nend_header\r\n0.3 99 0.1 0.2\r\n-1e-3 5 4 5.5\r\n";
  auto pts = formats::parse_ply(f);
  REQUIRE(pts.ok());
  REQUIRE(pts->size() == 2);
  CHECK((*pts)[0].x == Approx(0.1F));
  CHECK((*pts)[0].z == Approx(0.3F));
  CHECK((*pts)[1].z == Approx(-0.001F));
}

TEST_CASE("Given malformed PLY files, when read, then each is refused with what is wrong") {
  const std::string head =
      "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float "
      "z\nend_header\n";
  CHECK(parse_error("PLY\nformat ascii 1.0\n").find("not a PLY file") != std::string::npos);
  CHECK(parse_error("ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n")
            .find("binary_big_endian' is not supported") != std::string::npos);
  CHECK(
      parse_error("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n").find("end_header") !=
      std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n")
            .find("lacks x, y or z") != std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty float y\nproperty float "
                    "z\nend_header\n1 2 3\n")
            .find("must be float or double") != std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int i\nend_header\n")
            .find("no 'element vertex'") != std::string::npos);
  CHECK(parse_error("ply\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n")
            .find("no format line") != std::string::npos);
  CHECK(parse_error(head + std::string(20, '\0')).find("truncated at vertex 1 of 2") != std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float "
                    "z\nend_header\n1 2 3\n4 5\n")
            .find("missing number at vertex 1") != std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float "
                    "z\nend_header\n1 nan 3\n")
            .find("vertex 0") != std::string::npos);
  CHECK(parse_error("ply\nformat ascii 1.0\nelement vertex 99999999999\nproperty float x\nproperty float y\nproperty "
                    "float z\nend_header\n")
            .find("more than a scan can have") != std::string::npos);
  CHECK(
      parse_error(
          "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty quux z\nend_header\n")
          .find("unknown property type 'quux'") != std::string::npos);
}

TEST_CASE(
    "Given a valid file with random bytes corrupted or cut, when read, then it either parses or is refused, "
    "never crashes") {
  const std::string good = formats::write_ply_binary(sample_points());
  const std::string good_ascii = formats::write_ply_ascii(sample_points());
  std::mt19937 rng(5);
  int refused = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::string f = trial % 2 ? good : good_ascii;
    const int edits = 1 + static_cast<int>(rng() % 6);
    for (int e = 0; e < edits; ++e) f[rng() % f.size()] = static_cast<char>(rng() % 256);
    if (trial % 3 == 0) f.resize(rng() % f.size());
    auto r = formats::parse_ply(f);
    if (!r.ok()) {
      ++refused;
      CHECK(r.error().message.rfind("PLY: ", 0) == 0);
    }
  }
  CHECK(refused > 100);
}

TEST_CASE(
    "Given a header that does not end within 64 kB, when read, then it is refused from those bytes (a file "
    "that is no scan is not searched to its end)") {
  const std::string comments(70000, '\n');
  const std::string text = "ply\nformat ascii 1.0\n" + comments +
                           "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                           "1 2 3\n";
  CHECK(parse_error(text) == "PLY: no end_header in the first 65536 bytes: not a PLY scan");
  CHECK(formats::parse_ply_header(text.substr(0, 65536)).error().message ==
        "PLY: no end_header in the first 65536 bytes: not a PLY scan");
  CHECK(formats::parse_ply_header("ply\nformat ascii 1.0\nelement vertex 1\n").error().message ==
        "PLY: no end_header: the header is truncated");
}

TEST_CASE(
    "Given a header whose end_header line ends just past the header limit, when read whole or judged from "
    "its first bytes, then both refuse it alike (fuzz_ply finding)") {
  // Found by tests/fuzz/fuzz_ply: parse_ply looked for the line break after end_header in the whole text, the file
  // check (formats/input_file) in the first max_header_bytes, so the in-memory reader took what classify refused.
  const std::string head =
      "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
      "property float z\nend_header";
  const formats::PlyLimits limits{.max_vertices = 16, .max_header_bytes = head.size() + 1};
  const std::string text = head + "\r\n1 2 3\n";  // '\r' is the last byte within the limit, '\n' the first past it
  const auto whole = formats::parse_ply(text, limits);
  const auto first_bytes = formats::parse_ply_header(text.substr(0, limits.max_header_bytes), limits);
  REQUIRE_FALSE(first_bytes.ok());
  REQUIRE_FALSE(whole.ok());
  CHECK(whole.error().message == first_bytes.error().message);
  CHECK(whole.error().message == "PLY: the end_header line does not end in the first " +
                                     std::to_string(limits.max_header_bytes) + " bytes: not a PLY scan");
  // One byte more of room and both take it.
  const formats::PlyLimits roomier{.max_vertices = 16, .max_header_bytes = head.size() + 2};
  CHECK(formats::parse_ply(text, roomier).ok());
  CHECK(formats::parse_ply_header(text.substr(0, roomier.max_header_bytes), roomier).ok());
}

TEST_CASE(
    "Given double coordinates beyond float range, when read, then the scan is refused instead of holding "
    "infinities (fuzz_ply finding)") {
  // Found by tests/fuzz/fuzz_ply: a finite double such as 1e300 passed the finiteness check and became +inf in the
  // float a scan point stores.
  const std::string ascii =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
      "property double z\nend_header\n0.1 0.2 0.3\n0.1 -1e300 0.3\n";
  CHECK(parse_error(ascii) == "PLY: vertex 1 has a non-finite coordinate or one beyond float range");
  std::string binary =
      "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\n"
      "property double y\nproperty double z\nend_header\n";
  append<double>(binary, 3.5e38);
  append<double>(binary, 0.0);
  append<double>(binary, 0.0);
  CHECK(parse_error(binary) == "PLY: vertex 0 has a non-finite coordinate or one beyond float range");
  // The largest float itself is still a number a scan may hold.
  const std::string largest =
      "ply\nformat ascii 1.0\nelement vertex 1\nproperty double x\nproperty double y\n"
      "property double z\nend_header\n3.4028234663852886e38 0 -3.4028234663852886e38\n";
  const auto points = formats::parse_ply(largest);
  REQUIRE(points.ok());
  CHECK((*points)[0].x == std::numeric_limits<float>::max());
}

TEST_CASE(
    "Given an element without properties and a huge count before the vertices, when read, then the vertices "
    "come at once (found writing fuzz_ply)") {
  // Found writing tests/fuzz/fuzz_ply: the rows of such an element were skipped one by one, 2^64 - 1 of them, so a
  // 130-byte file held classify for ever (its rows take no bytes, so the size check cannot catch it).
  for (const std::string format : {"ascii", "binary_little_endian"}) {
    std::string text = "ply\nformat " + format +
                       " 1.0\nelement nothing 18446744073709551615\nelement vertex 1\n"
                       "property float x\nproperty float y\nproperty float z\nend_header\n";
    if (format == "ascii") {
      text += "1 2 3\n";
    } else {
      for (const float v : {1.0F, 2.0F, 3.0F}) append<float>(text, v);
    }
    const auto start = std::chrono::steady_clock::now();
    const auto points = formats::parse_ply(text);
    CHECK(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() < 1.0);
    REQUIRE(points.ok());
    REQUIRE(points->size() == 1);
    CHECK((*points)[0].z == 3.0F);
  }
}

TEST_CASE(
    "Given a header alone, when checked, then it tells where the data starts and the least data its elements "
    "need") {
  const std::string binary =
      "ply\nformat binary_little_endian 1.0\nelement face 3\nproperty list uchar int i\n"
      "element vertex 5\nproperty double x\nproperty double y\nproperty double z\n"
      "property uchar red\nend_header\n";
  auto b = formats::parse_ply_header(binary);
  REQUIRE(b.ok());
  CHECK(b->binary);
  CHECK(b->data_start == binary.size());
  CHECK(b->vertex_count == 5);
  CHECK(b->min_data_bytes == 3 * 1 + 5 * (3 * 8 + 1));  // an empty list is its count byte alone
  // The written file holds exactly what its header declares.
  const std::string written = formats::write_ply_binary(sample_points());
  auto w = formats::parse_ply_header(written);
  REQUIRE(w.ok());
  CHECK(w->min_data_bytes == written.size() - w->data_start);
  // ASCII: a digit and a separator per value, the last value without one.
  auto a = formats::parse_ply_header(
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n");
  REQUIRE(a.ok());
  CHECK(a->min_data_bytes == 11);
  // Counts that cannot fit in memory saturate instead of wrapping round to a small number.
  auto huge = formats::parse_ply_header(
      "ply\nformat binary_little_endian 1.0\nelement face 18446744073709551615\n"
      "property int i\nelement vertex 1\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n");
  REQUIRE(huge.ok());
  CHECK(huge->min_data_bytes == SIZE_MAX);
}
