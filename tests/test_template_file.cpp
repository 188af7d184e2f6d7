// Tests of formats/template_file: template building against brute force, file round trip, every refusal of a bad
// file (corrupt, truncated, foreign, other grid, missing), atomic replacement.
#include <signal.h>
#include <stdlib.h>
#include <sys/resource.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <catch2/catch.hpp>
#include <cinttypes>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "formats/template_file.hpp"
#include "tests/scratch_dir.hpp"

namespace {

namespace fs = std::filesystem;
using Catch::Matchers::Contains;
using cellsight::algo::GridSpec;
using cellsight::algo::ScanPoint;
using cellsight::algo::SurfaceCell;
using cellsight::formats::build_template;
using cellsight::formats::describe_grid;
using cellsight::formats::kTemplateHeaderBytes;
using cellsight::formats::kTemplateSectionAlignment;
using cellsight::formats::read_template_info;
using cellsight::formats::TemplateBuildParams;
using cellsight::formats::TemplateFile;
using cellsight::formats::TemplateIdentity;
using cellsight::formats::TemplateModel;
using cellsight::formats::write_template;

// Offsets of a few header fields (the layout of the version 2 header, written down independently of the code).
constexpr std::size_t kVersionOffset = 8;
constexpr std::size_t kHeaderCrcOffset = 252;

// A small grid whose origin is not at zero, so that a lost origin shows.
GridSpec small_grid() {
  GridSpec g;
  g.origin_m = Eigen::Vector3d(0.10, -0.05, 0.20);
  g.nx = 28;
  g.ny = 34;
  g.nz = 18;
  g.resolution_m = 0.005;
  return g;
}

ScanPoint point(double x, double y, double z) {
  return ScanPoint{static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, 0};
}

// A sheet-metal-like part inside small_grid(): a plate tilted in depth with a round hole, and a flange bent back
// along its lower edge. Sampled every 1.5 mm (denser than the 5 mm cells).
std::vector<ScanPoint> part_points(const GridSpec& g) {
  std::vector<ScanPoint> pts;
  const double x0 = g.origin_m.x() + 0.02;
  const double y0 = g.origin_m.y() + 0.03;
  const double z0 = g.origin_m.z() + 0.03;
  constexpr double kStep = 0.0015;
  constexpr int kStepsU = 66;  // 0.10 m
  constexpr int kStepsV = 80;  // 0.12 m
  constexpr int kStepsW = 20;  // 0.03 m
  for (int i = 0; i <= kStepsU; ++i) {
    const double u = i * kStep;
    for (int j = 0; j <= kStepsV; ++j) {
      const double v = j * kStep;
      if (std::hypot(u - 0.06, v - 0.07) < 0.015) continue;  // hole
      pts.push_back(point(x0 + u, y0 + v, z0 + 0.25 * u + 0.1 * v));
    }
    for (int k = 0; k <= kStepsW; ++k) pts.push_back(point(x0 + u, y0, z0 + 0.25 * u + k * kStep));  // flange
  }
  return pts;
}

// Occupied cells by the test's own floor of (p - origin) / resolution.
using Cell = std::tuple<int, int, int>;
std::set<Cell> occupied_cells(const std::vector<ScanPoint>& pts, const GridSpec& g) {
  std::set<Cell> cells;
  for (const ScanPoint& p : pts) {
    const int x = static_cast<int>(std::floor((double{p.x} - g.origin_m.x()) / g.resolution_m));
    const int y = static_cast<int>(std::floor((double{p.y} - g.origin_m.y()) / g.resolution_m));
    const int z = static_cast<int>(std::floor((double{p.z} - g.origin_m.z()) / g.resolution_m));
    REQUIRE((x >= 0 && y >= 0 && z >= 0 && x < g.nx && y < g.ny && z < g.nz));
    cells.insert({x, y, z});
  }
  return cells;
}

Eigen::Vector3d centre(const Cell& c, const GridSpec& g) {
  return g.origin_m +
         g.resolution_m * Eigen::Vector3d(std::get<0>(c) + 0.5, std::get<1>(c) + 0.5, std::get<2>(c) + 0.5);
}

Cell cell_of(const SurfaceCell& c) {
  return {c.x, c.y, c.z};
}

std::size_t align_up(std::size_t n) {
  return (n + kTemplateSectionAlignment - 1) / kTemplateSectionAlignment * kTemplateSectionAlignment;
}

using cellsight::test::TempDir;

std::vector<char> read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  REQUIRE(in);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

void write_bytes(const std::string& path, const std::vector<char>& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  REQUIRE(out);
}

TemplateModel built_model(const GridSpec& g, const TemplateBuildParams& params = {}) {
  auto model = build_template(part_points(g), g, params);
  REQUIRE(model.ok());
  return std::move(model.value());
}

TemplateIdentity standard_identity() {
  return {"bracket-7", 17, 1700000000};
}

// Writes the standard template to `path` and returns its bytes.
std::vector<char> write_standard(const std::string& path) {
  const TemplateModel model = built_model(small_grid());
  const auto written = write_template(path, model, standard_identity());
  REQUIRE(written.ok());
  return read_bytes(path);
}

std::uint32_t load_u32(const std::vector<char>& bytes, std::size_t offset) {
  std::uint32_t v = 0;
  std::memcpy(&v, bytes.data() + offset, sizeof v);
  return v;
}
void store_u32(std::vector<char>& bytes, std::size_t offset, std::uint32_t v) {
  std::memcpy(bytes.data() + offset, &v, sizeof v);
}

// Refused, with the file named in the message and the reason given.
void require_refused(const std::string& path, const GridSpec& grid, const std::string& reason) {
  const auto opened = TemplateFile::open(path, grid);
  REQUIRE_FALSE(opened.ok());
  CHECK_THAT(opened.error().message, Contains(path));
  CHECK_THAT(opened.error().message, Contains(reason));
}

}  // namespace

TEST_CASE("build: centroid, surface cells and distances agree with brute force over the occupied cells",
          "[template_file]") {
  // Given a part inside the grid, and a surface-cell cap above its number of occupied cells
  const GridSpec g = small_grid();
  const std::vector<ScanPoint> pts = part_points(g);
  const std::set<Cell> truth = occupied_cells(pts, g);
  TemplateBuildParams params;
  params.max_surface_points = truth.size() + 10;
  params.band_m = 0.012;

  // When the template is built
  const auto model = build_template(pts, g, params);
  REQUIRE(model.ok());

  // Then the surface cells are exactly the occupied cells, each once
  CHECK(model->occupied_cells == truth.size());
  std::set<Cell> seen;
  for (const SurfaceCell& c : model->surface_cells) seen.insert(cell_of(c));
  CHECK(model->surface_cells.size() == truth.size());
  CHECK(seen == truth);

  // and the centroid is their mean in x, y
  Eigen::Vector2d sum = Eigen::Vector2d::Zero();
  for (const Cell& c : truth) sum += centre(c, g).head<2>();
  const Eigen::Vector2d mean = sum / static_cast<double>(truth.size());
  CHECK((model->centroid_m - mean).norm() < 1e-12);
  CHECK(model->map.band_m() == params.band_m);

  // and every cell within the band stores the distance to the nearest occupied centre (to the 0.1 mm quantization),
  // as does every other cell of a stored brick up to the fine range; a cell beyond the band may be coarse only
  const auto& view = model->map.view();
  long in_band = 0;
  long beyond_band_fine = 0;
  for (int z = 0; z < g.nz; ++z)
    for (int y = 0; y < g.ny; ++y)
      for (int x = 0; x < g.nx; ++x) {
        const Cell c{x, y, z};
        double best = std::numeric_limits<double>::infinity();
        for (const Cell& o : truth) best = std::min(best, (centre(c, g) - centre(o, g)).norm());
        const std::uint8_t q = view.fine(x, y, z);
        if (best <= params.band_m) {
          ++in_band;
          REQUIRE(q != cellsight::algo::kFineFar);
        } else if (q != cellsight::algo::kFineFar) {
          ++beyond_band_fine;
        }
        if (q != cellsight::algo::kFineFar)
          REQUIRE(q * cellsight::algo::kDistanceUnitM == Approx(best).margin(0.5e-4 + 1e-6));
      }
  CHECK(in_band > static_cast<long>(truth.size()));
  CHECK(beyond_band_fine > 0);  // whole bricks are stored
  // and less is stored than the grid has cells: bricks away from the part are absent
  CHECK(model->map.stored_bricks() < cellsight::algo::BrickGrid(model->map.dims()).brick_count());
}

TEST_CASE("build: capped surface points are an even, deterministic subset of the occupied cells", "[template_file]") {
  // Given a cap of a tenth of the occupied cells
  const GridSpec g = small_grid();
  const std::vector<ScanPoint> pts = part_points(g);
  const std::set<Cell> truth = occupied_cells(pts, g);
  TemplateBuildParams params;
  params.max_surface_points = truth.size() / 10;

  // When built twice
  const TemplateModel a = built_model(g, params);
  const TemplateModel b = built_model(g, params);

  // Then exactly the cap, distinct occupied cells, the same both times
  REQUIRE(a.surface_cells.size() == params.max_surface_points);
  std::set<Cell> seen;
  for (const SurfaceCell& p : a.surface_cells) {
    const Cell c = cell_of(p);
    CHECK(truth.count(c) == 1);
    seen.insert(c);
  }
  CHECK(seen.size() == a.surface_cells.size());
  CHECK(a.surface_cells == b.surface_cells);

  // and spread evenly: every occupied cell has a surface point near it, also when only every 3rd stored point is
  // taken. On a surface, n/m cells per point means a spacing of about sqrt(n/m) cells; allow 1.5 times that as
  // the covering radius (the first m cells, say, would be far off).
  const auto covering_radius_cells = [&](int stride) {
    double worst = 0.0;
    for (const Cell& c : truth) {
      double best = std::numeric_limits<double>::infinity();
      for (std::size_t i = 0; i < a.surface_cells.size(); i += static_cast<std::size_t>(stride)) {
        best = std::min(best, (centre(c, g) - centre(cell_of(a.surface_cells[i]), g)).norm());
      }
      worst = std::max(worst, best);
    }
    return worst / g.resolution_m;
  };
  const double cells_per_point = static_cast<double>(truth.size()) / static_cast<double>(a.surface_cells.size());
  const double r1 = covering_radius_cells(1);
  const double r3 = covering_radius_cells(3);
  INFO("covering radius " << r1 << " cells (all), " << r3 << " (every 3rd); " << cells_per_point << " cells/point");
  CHECK(r1 <= 1.5 * std::sqrt(cells_per_point));
  CHECK(r3 <= 1.5 * std::sqrt(3.0 * cells_per_point));
}

TEST_CASE("build: a part reaching outside the grid is refused, naming how many points and which sides",
          "[template_file]") {
  // Given a part with 3 points beyond the +x side and 2 below the -z side (one of which is also beyond +y)
  const GridSpec g = small_grid();
  std::vector<ScanPoint> pts = part_points(g);
  const double x_max = g.origin_m.x() + g.nx * g.resolution_m;
  const double y_max = g.origin_m.y() + g.ny * g.resolution_m;
  for (int i = 0; i < 3; ++i) pts.push_back(point(x_max + 0.001 * (i + 1), 0.0, 0.25));
  pts.push_back(point(0.15, 0.0, g.origin_m.z() - 0.01));
  pts.push_back(point(0.15, y_max + 0.02, g.origin_m.z() - 0.01));

  // When the template is built
  const auto model = build_template(pts, g);

  // Then it is refused with the count and the sides
  REQUIRE_FALSE(model.ok());
  const std::string& why = model.error().message;
  CHECK_THAT(why, Contains("5 of " + std::to_string(pts.size()) + " points lie outside the grid"));
  CHECK_THAT(why, Contains("x >= 0.24 m: 3"));
  CHECK_THAT(why, Contains("y >= 0.12 m: 1"));
  CHECK_THAT(why, Contains("z < 0.2 m: 2"));

  // And with a tolerance of 5 stray points it is built from the rest
  TemplateBuildParams lenient;
  lenient.max_outside_points = 5;
  const auto tolerated = build_template(pts, g, lenient);
  REQUIRE(tolerated.ok());
  CHECK(tolerated->outside_points == 5);
  CHECK(tolerated->occupied_cells == occupied_cells(part_points(g), g).size());
}

TEST_CASE("build: an empty scan, a non-finite point and an unusable grid are refused", "[template_file]") {
  const GridSpec g = small_grid();
  const auto empty = build_template({}, g);
  REQUIRE_FALSE(empty.ok());
  CHECK_THAT(empty.error().message, Contains("no points"));

  std::vector<ScanPoint> pts = part_points(g);
  pts.push_back(point(std::numeric_limits<double>::quiet_NaN(), 0.0, 0.25));
  const auto nan = build_template(pts, g);
  REQUIRE_FALSE(nan.ok());
  CHECK_THAT(nan.error().message, Contains("not finite: 1"));

  GridSpec bad = g;
  bad.resolution_m = 0.0;
  CHECK_FALSE(build_template(part_points(g), bad).ok());
}

TEST_CASE("round trip: the mapped file serves the same map, surface cells, centroid and identity", "[template_file]") {
  // Given a template written to a file
  TempDir dir;
  const std::string path = dir.file("bracket-7.dmap");
  const GridSpec g = small_grid();
  const TemplateModel model = built_model(g);
  REQUIRE(write_template(path, model, standard_identity()).ok());

  // When it is opened
  auto opened = TemplateFile::open(path, g);
  REQUIRE(opened.ok());
  // (moving the owner keeps the mapped view valid)
  const TemplateFile file = std::move(opened.value());

  // Then the arrays are the in-memory map's, page-aligned, and every sample equals the in-memory map's
  const auto& mapped = file.view();
  const auto memory = model.map.view();
  const auto& data = mapped.data();
  REQUIRE(data.stored_bricks == model.map.stored_bricks());
  REQUIRE(mapped.bricks().brick_count() == model.map.brick_table().size());
  CHECK(reinterpret_cast<std::uintptr_t>(data.brick_table) % kTemplateSectionAlignment == 0);
  CHECK(reinterpret_cast<std::uintptr_t>(data.bricks) % kTemplateSectionAlignment == 0);
  CHECK(std::equal(model.map.brick_table().begin(), model.map.brick_table().end(), data.brick_table));
  CHECK(std::equal(model.map.coarse().begin(), model.map.coarse().end(), data.coarse));
  CHECK(std::equal(model.map.bricks().begin(), model.map.bricks().end(), data.bricks));
  // in memory of the file's own, read-only and anonymous (no file behind it whose pages the kernel could drop)
  const std::string maps = std::string(std::istreambuf_iterator<char>(std::ifstream("/proc/self/maps").rdbuf()), {});
  const auto address = reinterpret_cast<std::uintptr_t>(data.brick_table);
  bool found = false;
  std::istringstream lines(maps);
  for (std::string line; std::getline(lines, line);) {
    std::uintptr_t lo = 0, hi = 0;
    char perms[5] = {};
    unsigned long long offset = 0;
    char dev[16] = {};
    unsigned long inode = 1;
    if (std::sscanf(line.c_str(), "%" SCNxPTR "-%" SCNxPTR " %4s %llx %15s %lu", &lo, &hi, perms, &offset, dev,
                    &inode) != 6 ||
        address < lo || address >= hi) {
      continue;
    }
    found = true;
    INFO(line);
    CHECK(std::string(perms) == "r--p");
    CHECK(inode == 0);
  }
  CHECK(found);
  CHECK(mapped.origin_m() == g.origin_m);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> ux(g.origin_m.x() - 0.02, g.origin_m.x() + g.nx * g.resolution_m + 0.02);
  std::uniform_real_distribution<double> uy(g.origin_m.y() - 0.02, g.origin_m.y() + g.ny * g.resolution_m + 0.02);
  std::uniform_real_distribution<double> uz(g.origin_m.z() - 0.02, g.origin_m.z() + g.nz * g.resolution_m + 0.02);
  for (int i = 0; i < 5000; ++i) {
    const double x = ux(rng), y = uy(rng), z = uz(rng);
    const auto a = mapped.sample(x, y, z);
    const auto b = memory.sample(x, y, z);
    REQUIRE(a.distance_m == b.distance_m);
    REQUIRE(a.grad_x == b.grad_x);
    REQUIRE(a.grad_y == b.grad_y);
  }

  // and the surface cells, centroid, identity and header fields are those written
  REQUIRE(file.surface_cells().size() == model.surface_cells.size());
  CHECK(std::equal(file.surface_cells().begin(), file.surface_cells().end(), model.surface_cells.begin()));
  CHECK(file.centroid_m() == model.centroid_m);
  CHECK(file.part_name() == "bracket-7");
  CHECK(file.plc_id() == 17);
  CHECK(file.path() == path);
  const auto& info = file.info();
  CHECK(info.created_unix_s == 1700000000);
  CHECK(info.band_m == model.map.band_m());
  CHECK(info.stored_bricks == model.map.stored_bricks());
  CHECK(info.occupied_cells == model.occupied_cells);
  CHECK(info.file_bytes == fs::file_size(path));
  CHECK(describe_grid(info.grid) == describe_grid(g));

  // and the header-only reader agrees
  const auto header = read_template_info(path);
  REQUIRE(header.ok());
  CHECK(header->part_name == "bracket-7");
  CHECK(header->body_crc32 == info.body_crc32);
  CHECK(header->surface_cell_count == model.surface_cells.size());
  // and the file holds what it says: header, surface cells, brick table and coarse field, fine bricks
  const std::size_t table_offset = align_up(kTemplateSectionAlignment + model.surface_cells.size() * 6);
  const std::size_t bricks_offset = align_up(table_offset + 4 * model.map.brick_table().size());
  CHECK(info.file_bytes == bricks_offset + 512 * model.map.stored_bricks());
}

TEST_CASE("refused: any single corrupt byte in the header", "[template_file]") {
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  const std::vector<char> good = write_standard(path);
  const GridSpec g = small_grid();
  for (std::size_t i = 0; i < kTemplateHeaderBytes; ++i) {
    std::vector<char> bad = good;
    bad[i] = static_cast<char>(bad[i] ^ 0x10);
    write_bytes(path, bad);
    const auto opened = TemplateFile::open(path, g);
    INFO("header byte " << i);
    REQUIRE_FALSE(opened.ok());
    CHECK_THAT(opened.error().message, Contains(path));
    CHECK_FALSE(read_template_info(path).ok());
  }
  // A byte of the fields behind magic, version and size is caught by the header checksum.
  std::vector<char> bad = good;
  bad[40] = static_cast<char>(bad[40] ^ 1);  // lowest byte of resolution_m
  write_bytes(path, bad);
  require_refused(path, g, "header checksum mismatch");
}

TEST_CASE("refused: a corrupt byte in the body (padding, surface cells, table, coarse field, bricks)",
          "[template_file]") {
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  const std::vector<char> good = write_standard(path);
  const GridSpec g = small_grid();
  // Header padding, first surface cell, padding before the table, first table entry, first coarse node, padding
  // before the bricks, first brick byte, a middle brick byte, the last byte.
  const auto info = read_template_info(path);
  REQUIRE(info.ok());
  const std::size_t table_offset = align_up(kTemplateSectionAlignment + info->surface_cell_count * 6);
  const std::size_t coarse_offset = table_offset + 2 * info->brick_count;
  const std::size_t bricks_offset = good.size() - 512 * info->stored_bricks;
  REQUIRE(bricks_offset % kTemplateSectionAlignment == 0);
  REQUIRE(bricks_offset > coarse_offset + 2 * info->brick_count);
  for (const std::size_t at :
       {kTemplateHeaderBytes + 1, kTemplateSectionAlignment, table_offset - 1, table_offset, coarse_offset,
        bricks_offset - 1, bricks_offset, bricks_offset + (good.size() - bricks_offset) / 2 + 3, good.size() - 1}) {
    std::vector<char> bad = good;
    bad[at] = static_cast<char>(bad[at] ^ 0x01);
    write_bytes(path, bad);
    INFO("body byte " << at);
    require_refused(path, g, "body checksum mismatch");
    // The header reader does not read the body: it accepts the header (and says so in its contract).
    CHECK(read_template_info(path).ok());
  }
}

TEST_CASE("refused: truncated or extended files", "[template_file]") {
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  const std::vector<char> good = write_standard(path);
  const GridSpec g = small_grid();
  for (const std::size_t length : {good.size() - 1, good.size() / 2, kTemplateSectionAlignment, kTemplateHeaderBytes,
                                   kTemplateHeaderBytes - 1, std::size_t{10}, std::size_t{0}}) {
    write_bytes(path, std::vector<char>(good.begin(), good.begin() + static_cast<std::ptrdiff_t>(length)));
    INFO("length " << length);
    require_refused(path, g, "truncated");
    CHECK_FALSE(read_template_info(path).ok());
  }
  std::vector<char> longer = good;
  longer.push_back(0);
  write_bytes(path, longer);
  require_refused(path, g, "1 bytes more than its header says");
}

TEST_CASE("refused: wrong magic number or format version", "[template_file]") {
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  const std::vector<char> good = write_standard(path);
  const GridSpec g = small_grid();

  std::vector<char> ply(good);
  std::memcpy(ply.data(), "ply\nform", 8);
  write_bytes(path, ply);
  require_refused(path, g, "not a cellsight template file");

  // Version 3 with a header checksum that matches it: refused for the version, not for corruption.
  std::vector<char> v3(good);
  store_u32(v3, kVersionOffset, 3);
  store_u32(v3, kHeaderCrcOffset,
            static_cast<std::uint32_t>(crc32(0, reinterpret_cast<const Bytef*>(v3.data()), kHeaderCrcOffset)));
  REQUIRE(load_u32(v3, kHeaderCrcOffset) != load_u32(good, kHeaderCrcOffset));
  write_bytes(path, v3);
  require_refused(path, g, "template format version 3, this build reads version 2");

  // Version 1 (the full-grid format of earlier builds; its magic, version and byte-order mark sit where version 2
  // has them): refused before anything else is read, with the command that regenerates it.
  std::vector<char> v1(good);
  store_u32(v1, kVersionOffset, 1);
  write_bytes(path, v1);
  require_refused(path, g, "template format version 1");
  require_refused(path, g, "cellsight parts rebuild");
  const auto v1_info = read_template_info(path);
  REQUIRE_FALSE(v1_info.ok());
  CHECK_THAT(v1_info.error().message, Contains("parts rebuild"));
}

TEST_CASE("refused: a brick table entry or surface cell out of range, even with checksums that match",
          "[template_file]") {
  // The checksums only prove the bytes are as written; a writer bug or a crafted file (fuzz_template recomputes
  // them) must not make sample() or the cascade read outside the mapping.
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  const std::vector<char> good = write_standard(path);
  const GridSpec g = small_grid();
  const auto info = read_template_info(path);
  REQUIRE(info.ok());
  constexpr std::size_t kBodyCrcOffset = 176;
  const auto refix = [](std::vector<char>& bytes) {
    store_u32(bytes, kBodyCrcOffset,
              static_cast<std::uint32_t>(crc32(0, reinterpret_cast<const Bytef*>(bytes.data()) + kTemplateHeaderBytes,
                                               static_cast<uInt>(bytes.size() - kTemplateHeaderBytes))));
    store_u32(bytes, kHeaderCrcOffset,
              static_cast<std::uint32_t>(crc32(0, reinterpret_cast<const Bytef*>(bytes.data()), kHeaderCrcOffset)));
  };
  const std::size_t table_offset = align_up(kTemplateSectionAlignment + info->surface_cell_count * 6);
  std::vector<char> bad_table(good);
  const auto stored = static_cast<std::uint16_t>(info->stored_bricks);
  std::memcpy(bad_table.data() + table_offset + 2, &stored, 2);  // entry 1 names brick `stored`: one past the end
  refix(bad_table);
  write_bytes(path, bad_table);
  require_refused(path, g, "brick table entry 1 names brick");

  std::vector<char> bad_cell(good);
  const auto nz = static_cast<std::uint16_t>(g.nz);
  std::memcpy(bad_cell.data() + kTemplateSectionAlignment + 4, &nz, 2);  // z of the first surface cell
  refix(bad_cell);
  write_bytes(path, bad_cell);
  require_refused(path, g, "surface cell 0 lies outside the grid");
}

TEST_CASE("refused: a header declaring about 2^31 cells on every axis, without overflow (fuzz_template finding)",
          "[template_file]") {
  // Found by tests/fuzz/fuzz_template in CI: the grid check summed the three squared axis lengths in 64 bits, which
  // overflows for axes near INT_MAX (undefined behaviour; UBSan aborted). The corpus holds it as regress-huge-grid.
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  std::vector<char> huge = write_standard(path);
  constexpr std::size_t kNxOffset = 24;  // nx, ny, nz: three int32 after the magic and four uint32
  for (std::size_t axis = 0; axis < 3; ++axis) {
    store_u32(huge, kNxOffset + 4 * axis, static_cast<std::uint32_t>(std::numeric_limits<std::int32_t>::max()));
  }
  store_u32(huge, kHeaderCrcOffset,
            static_cast<std::uint32_t>(crc32(0, reinterpret_cast<const Bytef*>(huge.data()), kHeaderCrcOffset)));
  write_bytes(path, huge);
  const auto info = read_template_info(path);
  REQUIRE_FALSE(info.ok());
  CHECK_THAT(info.error().message, Contains(path));
  CHECK_THAT(info.error().message, Contains("too large"));
  require_refused(path, small_grid(), "too large");
}

TEST_CASE("refused: a template built for another grid, naming both grids", "[template_file]") {
  TempDir dir;
  const std::string path = dir.file("t.dmap");
  write_standard(path);
  const GridSpec built = small_grid();
  GridSpec taller = built;
  taller.ny += 1;
  GridSpec finer = built;
  finer.resolution_m = 0.004;
  GridSpec shifted = built;
  shifted.origin_m.z() += 0.001;
  for (const GridSpec& other : {taller, finer, shifted}) {
    INFO(describe_grid(other));
    REQUIRE(describe_grid(other) != describe_grid(built));
    require_refused(path, other, "built for another grid");
    require_refused(path, other, describe_grid(built));
    require_refused(path, other, describe_grid(other));
  }
  CHECK(describe_grid(built) == "28 x 34 x 18 cells of 5 mm, origin (0.1, -0.05, 0.2) m");
}

TEST_CASE("refused: a missing file or a folder, with a clear message", "[template_file]") {
  TempDir dir;
  const std::string missing = dir.file("nope.dmap");
  require_refused(missing, small_grid(), "cannot open the template file: No such file or directory");
  const auto info = read_template_info(missing);
  REQUIRE_FALSE(info.ok());
  CHECK_THAT(info.error().message, Contains(missing));
  fs::create_directory(dir.file("folder.dmap"));
  require_refused(dir.file("folder.dmap"), small_grid(), "not a regular file");
}

TEST_CASE("write: a failed write leaves the previous file intact and no temp file behind", "[template_file]") {
  // Given a good template file in a folder
  TempDir dir;
  const std::string path = dir.file("part.dmap");
  const std::vector<char> before = write_standard(path);
  REQUIRE(dir.entries() == std::vector<std::string>{"part.dmap"});
  const GridSpec g = small_grid();
  TemplateBuildParams hundred;
  hundred.max_surface_points = 100;
  const TemplateModel other = built_model(g, hundred);

  // When a new version fails half-way (the file size limit makes write() fail with EFBIG once the temp file has
  // grown past half the size)
  struct rlimit old_limit {};
  REQUIRE(::getrlimit(RLIMIT_FSIZE, &old_limit) == 0);
  struct rlimit small = old_limit;
  small.rlim_cur = static_cast<rlim_t>(before.size() / 2);
  const auto old_handler = ::signal(SIGXFSZ, SIG_IGN);
  REQUIRE(::setrlimit(RLIMIT_FSIZE, &small) == 0);
  const auto failed = write_template(path, other, TemplateIdentity{"other", 3, 1});
  REQUIRE(::setrlimit(RLIMIT_FSIZE, &old_limit) == 0);
  ::signal(SIGXFSZ, old_handler);

  // Then the write reports it, the old file is unchanged and still opens, and no temp file is left
  REQUIRE_FALSE(failed.ok());
  CHECK_THAT(failed.error().message, Contains(path));
  CHECK_THAT(failed.error().message, Contains("write failed"));
  CHECK(read_bytes(path) == before);
  const auto still = TemplateFile::open(path, g);
  REQUIRE(still.ok());
  CHECK(still->part_name() == "bracket-7");
  CHECK(dir.entries() == std::vector<std::string>{"part.dmap"});

  // And invalid input writes nothing at all
  CHECK_FALSE(write_template(path, other, TemplateIdentity{"", 3, 1}).ok());
  CHECK_FALSE(write_template(dir.file("no/such/folder/x.dmap"), other, TemplateIdentity{"x", 3, 1}).ok());
  CHECK(dir.entries() == std::vector<std::string>{"part.dmap"});

  // And a successful write replaces the file as a whole
  REQUIRE(write_template(path, other, TemplateIdentity{"other", 3, 1}).ok());
  const auto replaced = TemplateFile::open(path, g);
  REQUIRE(replaced.ok());
  CHECK(replaced->part_name() == "other");
  CHECK(replaced->surface_cells().size() == 100);
  CHECK(dir.entries() == std::vector<std::string>{"part.dmap"});
}
