// Tests of algo/distance_map: exact EDT against brute force, the sparse brick map against brute force and analytic
// fields, trilinear sampling and its analytic gradient against hand computation and finite differences.
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <numbers>
#include <random>
#include <string>
#include <vector>

#include "algo/distance_map.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using cellsight::algo::BrickGrid;
using cellsight::algo::build_distance_map;
using cellsight::algo::DistanceMap;
using cellsight::algo::DistanceMapView;
using cellsight::algo::edt_squared;
using cellsight::algo::EdtScratch;
using cellsight::algo::GridDims;
using cellsight::algo::kAbsentBrick;
using cellsight::algo::kCoarseSaturated;
using cellsight::algo::kDistanceUnitM;
using cellsight::algo::kFineFar;
using cellsight::algo::kMaxCoarseDistanceM;
using cellsight::algo::kMaxFineDistanceM;
using cellsight::algo::MapSample;
using cellsight::algo::SparseMapData;
// Counts only while open, so Catch2's own allocations elsewhere do not matter.
using cellsight::test::AllocationWindow;

constexpr double kResolutionM = 0.0022;  // the thesis grid's cell; the code never assumes it

struct Cell {
  int x;
  int y;
  int z;
};

std::vector<Cell> occupied_list(const std::vector<std::uint8_t>& occ, const GridDims& d) {
  std::vector<Cell> cells;
  for (int z = 0; z < d.nz; ++z)
    for (int y = 0; y < d.ny; ++y)
      for (int x = 0; x < d.nx; ++x)
        if (occ[d.index(x, y, z)] != 0) cells.push_back({x, y, z});
  return cells;
}

// Independent truth: minimum over every occupied cell of the integer squared distance; -1 when there is none.
std::int64_t brute_force_d2(const std::vector<Cell>& sites, int x, int y, int z) {
  std::int64_t best = -1;
  for (const Cell& s : sites) {
    const std::int64_t dx = x - s.x;
    const std::int64_t dy = y - s.y;
    const std::int64_t dz = z - s.z;
    const std::int64_t d2 = dx * dx + dy * dy + dz * dz;
    if (best < 0 || d2 < best) best = d2;
  }
  return best;
}

// Counts cells where the transform differs from brute force (exact comparison of integers).
long count_mismatches(const std::vector<float>& d2, const std::vector<Cell>& sites, const GridDims& d) {
  long mismatches = 0;
  for (int z = 0; z < d.nz; ++z)
    for (int y = 0; y < d.ny; ++y)
      for (int x = 0; x < d.nx; ++x) {
        const std::int64_t truth = brute_force_d2(sites, x, y, z);
        const float got = d2[d.index(x, y, z)];
        const bool ok = truth < 0 ? std::isinf(got) && got > 0 : static_cast<double>(got) == static_cast<double>(truth);
        if (!ok) ++mismatches;
      }
  return mismatches;
}

std::vector<float> run_edt(const std::vector<std::uint8_t>& occ, const GridDims& d) {
  EdtScratch scratch(d);
  std::vector<float> d2(d.cell_count(), -1.0f);
  REQUIRE(edt_squared(occ.data(), d, scratch, d2.data()).ok());
  return d2;
}

}  // namespace

SCENARIO("The transform equals brute force exactly on random small grids", "[distance_map][edt]") {
  GIVEN("400 seeded random grids of 1..17 cells per axis with densities from 0.1 % to 50 %") {
    std::mt19937 rng(20240611);
    std::uniform_int_distribution<int> size(1, 17);
    const double densities[] = {0.001, 0.005, 0.02, 0.1, 0.25, 0.5};
    std::uniform_int_distribution<int> pick_density(0, 5);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    WHEN("the squared transform runs on each") {
      THEN("every cell holds the brute-force squared distance in cells, or +inf when nothing is occupied") {
        int empty_grids = 0;
        int failed_grids = 0;
        for (int trial = 0; trial < 400; ++trial) {
          const GridDims d{size(rng), size(rng), size(rng), kResolutionM};
          const double density = densities[pick_density(rng)];
          std::vector<std::uint8_t> occ(d.cell_count());
          for (auto& c : occ) c = unit(rng) < density ? 1 : 0;
          const std::vector<Cell> sites = occupied_list(occ, d);
          if (sites.empty()) ++empty_grids;
          const long mismatches = count_mismatches(run_edt(occ, d), sites, d);
          if (mismatches != 0) {
            ++failed_grids;
            UNSCOPED_INFO("trial " << trial << ": " << d.nx << " x " << d.ny << " x " << d.nz << ", density " << density
                                   << ", occupied " << sites.size() << ", wrong cells " << mismatches);
          }
        }
        CHECK(failed_grids == 0);
        CHECK(empty_grids > 0);  // the sample did include grids with no occupied cell
      }
    }
  }
}

SCENARIO("Empty, full and single-corner grids", "[distance_map][edt]") {
  const GridDims d{13, 7, 10, kResolutionM};
  GIVEN("a grid with no occupied cell") {
    const std::vector<float> d2 = run_edt(std::vector<std::uint8_t>(d.cell_count(), 0), d);
    THEN("every squared distance is +inf (the defined 'no surface' value)") {
      long finite = 0;
      for (float v : d2) finite += (std::isinf(v) && v > 0) ? 0 : 1;
      CHECK(finite == 0);
    }
  }
  GIVEN("a grid where every cell is occupied") {
    const std::vector<float> d2 = run_edt(std::vector<std::uint8_t>(d.cell_count(), 1), d);
    THEN("every squared distance is 0") {
      long non_zero = 0;
      for (float v : d2) non_zero += v == 0.0f ? 0 : 1;
      CHECK(non_zero == 0);
    }
  }
  GIVEN("only the last corner cell is occupied") {
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    occ[d.index(d.nx - 1, d.ny - 1, d.nz - 1)] = 1;
    const std::vector<float> d2 = run_edt(occ, d);
    THEN("each cell's squared distance is dx^2 + dy^2 + dz^2 to that corner") {
      long wrong = 0;
      for (int z = 0; z < d.nz; ++z)
        for (int y = 0; y < d.ny; ++y)
          for (int x = 0; x < d.nx; ++x) {
            const int dx = d.nx - 1 - x;
            const int dy = d.ny - 1 - y;
            const int dz = d.nz - 1 - z;
            wrong += d2[d.index(x, y, z)] == static_cast<float>(dx * dx + dy * dy + dz * dz) ? 0 : 1;
          }
      CHECK(wrong == 0);
    }
  }
  GIVEN("a 1 x 1 x 1 grid, occupied or not") {
    const GridDims one{1, 1, 1, kResolutionM};
    CHECK(run_edt({1}, one)[0] == 0.0f);
    CHECK(std::isinf(run_edt({0}, one)[0]));
  }
}

SCENARIO("Invalid input is refused with a message", "[distance_map][edt]") {
  const GridDims good{4, 4, 4, kResolutionM};
  EdtScratch scratch(good);
  std::vector<std::uint8_t> occ(good.cell_count(), 0);
  std::vector<float> out(good.cell_count());
  WHEN("a dimension is zero") {
    CHECK_FALSE(edt_squared(occ.data(), {4, 0, 4, kResolutionM}, scratch, out.data()).ok());
  }
  WHEN("the resolution is not positive") {
    CHECK_FALSE(edt_squared(occ.data(), {4, 4, 4, 0.0}, scratch, out.data()).ok());
  }
  WHEN("the scratch was sized for a smaller grid") {
    const GridDims bigger{4, 9, 4, kResolutionM};
    std::vector<std::uint8_t> occ_big(bigger.cell_count(), 0);
    std::vector<float> out_big(bigger.cell_count());
    const auto status = edt_squared(occ_big.data(), bigger, scratch, out_big.data());
    REQUIRE_FALSE(status.ok());
    CHECK(status.error().message.find("scratch") != std::string::npos);
  }
  WHEN("the grid's squared diagonal would not be exact in float") {
    CHECK_FALSE(cellsight::algo::validate_dims({3000, 3000, 1, kResolutionM}).ok());
  }
  WHEN("every axis is near INT_MAX (a damaged template header; the squares' sum would overflow 64 bits)") {
    constexpr int kHuge = std::numeric_limits<int>::max();
    CHECK_FALSE(cellsight::algo::validate_dims({kHuge, kHuge, kHuge, kResolutionM}).ok());
    CHECK_FALSE(cellsight::algo::validate_dims({kHuge, 1, 1, kResolutionM}).ok());
  }
}

SCENARIO("Full thesis-size grid with a sparse plate: sampled cells equal brute force", "[distance_map][edt][full]") {
  GIVEN("a 296 x 500 x 182 grid holding a tilted, holed plate scanned in lines plus stray outlier cells") {
    const GridDims d{296, 500, 182, kResolutionM};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    std::vector<Cell> sites;
    const auto mark = [&](double fx, double fy, double fz) {
      const int x = static_cast<int>(std::floor(fx));
      const int y = static_cast<int>(std::floor(fy));
      const int z = static_cast<int>(std::floor(fz));
      if (x < 0 || y < 0 || z < 0 || x >= d.nx || y >= d.ny || z >= d.nz) return;
      std::uint8_t& c = occ[d.index(x, y, z)];
      if (c == 0) sites.push_back({x, y, z});
      c = 1;
    };
    // Plate ~ 0.45 x 0.9 m, turned 20 deg about y and 8 deg about x, sampled every 3 cells across and 7 cells up
    // (a scan's line pitch), with a round hole.
    const double ay = 20.0 * std::numbers::pi / 180.0;
    const double ax = 8.0 * std::numbers::pi / 180.0;
    for (int across = 0; across <= 66; ++across) {
      for (int up = 0; up <= 57; ++up) {
        const double s = -100.0 + 3.0 * across;
        const double t = -200.0 + 7.0 * up;
        if (s * s + (t - 50.0) * (t - 50.0) < 40.0 * 40.0) continue;  // hole
        mark(148.0 + s * std::cos(ay), 250.0 + t * std::cos(ax), 91.0 + s * std::sin(ay) + t * std::sin(ax));
      }
    }
    std::mt19937 rng(7);
    std::uniform_real_distribution<double> ux(0.0, d.nx);
    std::uniform_real_distribution<double> uy(0.0, d.ny);
    std::uniform_real_distribution<double> uz(0.0, d.nz);
    for (int i = 0; i < 150; ++i) {
      const Eigen::Vector3d p{ux(rng), uy(rng), uz(rng)};  // braces: drawn in this order
      mark(p.x(), p.y(), p.z());
    }
    REQUIRE(sites.size() > 3000);
    REQUIRE(sites.size() < 6000);

    WHEN("the squared transform runs once over the whole grid") {
      EdtScratch scratch(d);
      std::vector<float> d2(d.cell_count(), -1.0f);
      REQUIRE(edt_squared(occ.data(), d, scratch, d2.data()).ok());
      THEN("400 random cells and the 8 grid corners equal brute force over the occupied list exactly") {
        std::vector<Cell> probes = {{0, 0, 0},     {295, 0, 0},   {0, 499, 0},   {0, 0, 181},
                                    {295, 499, 0}, {295, 0, 181}, {0, 499, 181}, {295, 499, 181}};
        std::uniform_int_distribution<int> px(0, d.nx - 1);
        std::uniform_int_distribution<int> py(0, d.ny - 1);
        std::uniform_int_distribution<int> pz(0, d.nz - 1);
        for (int i = 0; i < 400; ++i) probes.push_back({px(rng), py(rng), pz(rng)});
        long wrong = 0;
        for (const Cell& p : probes) {
          const std::int64_t truth = brute_force_d2(sites, p.x, p.y, p.z);
          wrong += static_cast<double>(d2[d.index(p.x, p.y, p.z)]) == static_cast<double>(truth) ? 0 : 1;
        }
        CHECK(wrong == 0);
        long occupied_not_zero = 0;
        for (const Cell& s : sites) occupied_not_zero += d2[d.index(s.x, s.y, s.z)] == 0.0f ? 0 : 1;
        CHECK(occupied_not_zero == 0);
      }
    }
  }
}

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kHalfUnitM = 0.5 * kDistanceUnitM;  // what rounding to a storage unit may cost
constexpr int kEdge = BrickGrid::kBrickEdge;

// Independent truth in metres: brute force over the occupied list at every cell; +inf when nothing is occupied.
std::vector<double> brute_force_field_m(const std::vector<Cell>& sites, const GridDims& d) {
  std::vector<double> field(d.cell_count());
  for (int z = 0; z < d.nz; ++z)
    for (int y = 0; y < d.ny; ++y)
      for (int x = 0; x < d.nx; ++x) {
        const std::int64_t d2 = brute_force_d2(sites, x, y, z);
        field[d.index(x, y, z)] = d2 < 0 ? kInf : std::sqrt(static_cast<double>(d2)) * d.resolution_m;
      }
  return field;
}

DistanceMap build_map(const std::vector<std::uint8_t>& occ, const GridDims& d, const Eigen::Vector3d& origin,
                      double band_m) {
  EdtScratch scratch(d);
  std::vector<float> work(d.cell_count());
  DistanceMap map;
  const auto status = build_distance_map(occ.data(), d, origin, band_m, scratch, work.data(), map);
  INFO((status.ok() ? std::string() : status.error().message));
  REQUIRE(status.ok());
  return map;
}

int bricks_along(int n) {
  return (n + kEdge - 1) / kEdge;
}

// What a map built with this band must hold, checked against the brute-force field: counts of violations.
struct BandReport {
  long cells_in_band = 0;
  long in_band_not_fine = 0;   // a cell within the band reads kFineFar
  long fine_off = 0;           // a fine value (any cell of a stored brick) off the truth by more than half a unit
  long far_not_marked = 0;     // a cell of a stored brick beyond the fine range does not read kFineFar
  long stored_wrongly = 0;     // a brick stored although none of its cells is within the band, or absent though one is
  long expected_stored = 0;    // bricks with a cell within the band (brute force)
  long duplicate_numbers = 0;  // two table entries naming the same stored brick, or a number out of range
  long coarse_off = 0;         // coarse node off the mean of its 8 central cells by more than half a unit
  double worst_fine_error_m = 0.0;
  double worst_coarse_error_m = 0.0;
};

BandReport check_band(const DistanceMap& map, const std::vector<double>& truth_m, const GridDims& d, double band_m) {
  BandReport r;
  const DistanceMapView view = map.view();
  const BrickGrid grid(d);
  // The work volume is float: its distances carry ~1e-7 relative error before rounding to a unit. Fine values are
  // below 25.4 mm (<= 5e-9 m of float error), coarse values below ~0.1 m in these grids (<= 2e-8 m).
  constexpr double kFineSlackM = 1e-9;
  constexpr double kCoarseSlackM = 1e-7;
  std::vector<int> number_used(map.stored_bricks(), 0);
  for (int bz = 0; bz < grid.count(2); ++bz)
    for (int by = 0; by < grid.count(1); ++by)
      for (int bx = 0; bx < grid.count(0); ++bx) {
        const std::size_t b = grid.brick_index(bx, by, bz);
        const std::uint16_t number = map.brick_table()[b];
        const bool stored = number != kAbsentBrick;
        if (stored) {
          if (number >= number_used.size() || number_used[number]++ != 0) ++r.duplicate_numbers;
        }
        double nearest_m = kInf;
        for (int z = bz * kEdge; z < std::min((bz + 1) * kEdge, d.nz); ++z)
          for (int y = by * kEdge; y < std::min((by + 1) * kEdge, d.ny); ++y)
            for (int x = bx * kEdge; x < std::min((bx + 1) * kEdge, d.nx); ++x) {
              const double truth = truth_m[d.index(x, y, z)];
              nearest_m = std::min(nearest_m, truth);
              const std::uint8_t q = view.fine(x, y, z);
              if (truth <= band_m) {
                ++r.cells_in_band;
                if (q == kFineFar) ++r.in_band_not_fine;
              }
              if (!stored) continue;
              if (truth < kMaxFineDistanceM) {
                const double error = q == kFineFar ? kInf : std::abs(q * kDistanceUnitM - truth);
                r.worst_fine_error_m = std::max(r.worst_fine_error_m, error);
                if (error > kHalfUnitM + kFineSlackM) ++r.fine_off;
              } else if (truth > kMaxFineDistanceM + kDistanceUnitM && q != kFineFar) {
                ++r.far_not_marked;
              }
            }
        const bool should_store = nearest_m <= band_m;
        r.expected_stored += should_store ? 1 : 0;
        if (stored != should_store) ++r.stored_wrongly;
        // Coarse node: the mean of the brick's 8 central cells, clamped into the grid for a partial brick.
        double sum = 0.0;
        for (int k = 0; k < 2; ++k)
          for (int j = 0; j < 2; ++j)
            for (int i = 0; i < 2; ++i) {
              sum += truth_m[d.index(std::min(bx * kEdge + kEdge / 2 - 1 + i, d.nx - 1),
                                     std::min(by * kEdge + kEdge / 2 - 1 + j, d.ny - 1),
                                     std::min(bz * kEdge + kEdge / 2 - 1 + k, d.nz - 1))];
            }
        const double mean_m = sum / 8.0;
        const std::uint16_t node = map.coarse()[b];
        const double error =
            std::isinf(mean_m) ? (node == kCoarseSaturated ? 0.0 : kInf) : std::abs(node * kDistanceUnitM - mean_m);
        r.worst_coarse_error_m = std::max(r.worst_coarse_error_m, error);
        if (error > kHalfUnitM + kCoarseSlackM) ++r.coarse_off;
      }
  return r;
}

void require_band_report_clean(const BandReport& r, const DistanceMap& map) {
  INFO("cells in band " << r.cells_in_band << ", expected bricks " << r.expected_stored << ", stored "
                        << map.stored_bricks() << ", worst fine error " << r.worst_fine_error_m
                        << " m, worst coarse error " << r.worst_coarse_error_m << " m");
  CHECK(r.in_band_not_fine == 0);
  CHECK(r.fine_off == 0);
  CHECK(r.far_not_marked == 0);
  CHECK(r.stored_wrongly == 0);
  CHECK(r.duplicate_numbers == 0);
  CHECK(static_cast<long>(map.stored_bricks()) == r.expected_stored);
  CHECK(r.coarse_off == 0);
}

}  // namespace

SCENARIO("Every cell within the band is stored exactly, on random small grids", "[distance_map][sparse]") {
  GIVEN("150 seeded random grids of 1..26 cells per axis (whole and partial bricks), densities 0.02 % to 2 %") {
    std::mt19937 rng(20250203);
    std::uniform_int_distribution<int> size(1, 26);
    const double densities[] = {0.0002, 0.001, 0.005, 0.02};
    const double bands_m[] = {0.0022, 0.0088, cellsight::algo::kDefaultBandM, kMaxFineDistanceM};
    std::uniform_int_distribution<int> pick(0, 3);
    std::uniform_real_distribution<double> unit(0.0, 1.0);
    WHEN("a sparse map is built from each with a band of 2.2, 8.8, 17.6 or 25.4 mm") {
      THEN(
          "cells within the band are fine and within half a unit of brute force, bricks without such a cell are "
          "absent, the stored count is the brute-force count and every coarse node is its brick's central mean") {
        int failed = 0;
        long absent_seen = 0;
        long stored_seen = 0;
        for (int trial = 0; trial < 150; ++trial) {
          const GridDims d{size(rng), size(rng), size(rng), kResolutionM};
          const double density = densities[pick(rng)];
          const double band_m = bands_m[pick(rng)];
          std::vector<std::uint8_t> occ(d.cell_count());
          for (auto& c : occ) c = unit(rng) < density ? 1 : 0;
          const std::vector<Cell> sites = occupied_list(occ, d);
          if (sites.empty()) occ[d.index(d.nx / 3, d.ny / 2, d.nz - 1)] = 1;  // empty grids have their own scenario
          const std::vector<Cell> used = occupied_list(occ, d);
          const DistanceMap map = build_map(occ, d, Eigen::Vector3d(0.01, -0.02, 0.3), band_m);
          const BandReport r = check_band(map, brute_force_field_m(used, d), d, band_m);
          const bool clean = r.in_band_not_fine == 0 && r.fine_off == 0 && r.far_not_marked == 0 &&
                             r.stored_wrongly == 0 && r.duplicate_numbers == 0 && r.coarse_off == 0 &&
                             static_cast<long>(map.stored_bricks()) == r.expected_stored && map.has_surface();
          if (!clean) {
            ++failed;
            UNSCOPED_INFO("trial " << trial << ": " << d.nx << " x " << d.ny << " x " << d.nz << ", band " << band_m
                                   << ", occupied " << used.size() << ", not fine " << r.in_band_not_fine
                                   << ", fine off " << r.fine_off << ", far unmarked " << r.far_not_marked
                                   << ", stored wrongly " << r.stored_wrongly << ", coarse off " << r.coarse_off
                                   << ", worst fine " << r.worst_fine_error_m << ", worst coarse "
                                   << r.worst_coarse_error_m);
          }
          stored_seen += static_cast<long>(map.stored_bricks());
          absent_seen += static_cast<long>(BrickGrid(d).brick_count() - map.stored_bricks());
        }
        CHECK(failed == 0);
        CHECK(stored_seen > 0);
        CHECK(absent_seen > 0);  // the sample did leave bricks out
      }
    }
  }
}

namespace {

// A part-like template on a 69 x 61 x 45 grid (partial bricks on every axis): a plate turned 25 deg about y and
// 10 deg about x, scanned in lines 3 cells apart, with a round hole, plus 12 stray outlier cells.
std::vector<std::uint8_t> small_plate(const GridDims& d) {
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  const auto mark = [&](double fx, double fy, double fz) {
    const int x = static_cast<int>(std::floor(fx));
    const int y = static_cast<int>(std::floor(fy));
    const int z = static_cast<int>(std::floor(fz));
    if (x < 0 || y < 0 || z < 0 || x >= d.nx || y >= d.ny || z >= d.nz) return;
    occ[d.index(x, y, z)] = 1;
  };
  const double ay = 25.0 * std::numbers::pi / 180.0;
  const double ax = 10.0 * std::numbers::pi / 180.0;
  for (int across = 0; across <= 40; ++across) {
    for (int up = 0; up <= 16; ++up) {
      const double s = -20.0 + across;
      const double t = -24.0 + 3.0 * up;
      if (s * s + (t - 6.0) * (t - 6.0) < 8.0 * 8.0) continue;  // hole
      mark(34.0 + s * std::cos(ay), 30.0 + t * std::cos(ax), 20.0 + s * std::sin(ay) + t * std::sin(ax));
    }
  }
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> ux(0.0, d.nx);
  std::uniform_real_distribution<double> uy(0.0, d.ny);
  std::uniform_real_distribution<double> uz(0.0, d.nz);
  for (int i = 0; i < 12; ++i) {
    const Eigen::Vector3d p{ux(rng), uy(rng), uz(rng)};  // braces: drawn in this order
    mark(p.x(), p.y(), p.z());
  }
  return occ;
}

}  // namespace

SCENARIO("A sparse plate keeps exactly the bricks near its surface", "[distance_map][sparse]") {
  GIVEN("a 69 x 61 x 45 grid holding a tilted, holed plate and stray cells, and its brute-force distances") {
    const GridDims d{69, 61, 45, kResolutionM};
    const std::vector<std::uint8_t> occ = small_plate(d);
    const std::vector<Cell> sites = occupied_list(occ, d);
    REQUIRE(sites.size() > 400);
    const std::vector<double> truth_m = brute_force_field_m(sites, d);
    for (const double band_m : {0.0088, cellsight::algo::kDefaultBandM}) {
      WHEN("a map is built with a band of " << band_m * 1e3 << " mm") {
        const DistanceMap map = build_map(occ, d, Eigen::Vector3d(-0.1, 0.05, 0.2), band_m);
        THEN("every in-band cell is exact to half a unit, the stored set is the brute-force set, nodes are exact") {
          const BandReport r = check_band(map, truth_m, d, band_m);
          require_band_report_clean(r, map);
          CHECK(map.has_surface());
          CHECK(map.band_m() == band_m);
          // Sparse indeed: some bricks are left out, and the memory is what the arrays hold.
          const std::size_t bricks = BrickGrid(d).brick_count();
          CHECK(map.stored_bricks() < bricks);
          CHECK(map.stored_bricks() > 0);
          CHECK(map.memory_bytes() == bricks * 2 * sizeof(std::uint16_t) + map.stored_bricks() * 512);
        }
      }
    }
  }
}

SCENARIO("The coarse field is the distance at brick centres and carries the far field", "[distance_map][coarse]") {
  GIVEN("a 20 x 20 x 40 grid whose occupied cells form the plane z = 1, with a band of 17.6 mm") {
    const GridDims d{20, 20, 40, kResolutionM};
    const Eigen::Vector3d origin(0.2, -0.1, -0.05);
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    for (int y = 0; y < d.ny; ++y)
      for (int x = 0; x < d.nx; ++x) occ[d.index(x, y, 1)] = 1;
    const DistanceMap map = build_map(occ, d, origin, cellsight::algo::kDefaultBandM);
    const DistanceMapView view = map.view();
    const double plane_z_m = origin.z() + 1.5 * kResolutionM;  // centres of the occupied cells
    THEN("each node is the distance of its brick's centre to the plane, 8 b + 3.5 - 1 cells") {
      const BrickGrid grid(d);
      double worst_m = 0.0;
      for (int bz = 0; bz < grid.count(2); ++bz)
        for (int by = 0; by < grid.count(1); ++by)
          for (int bx = 0; bx < grid.count(0); ++bx) {
            const double truth_m = (kEdge * bz + 3.5 - 1.0) * kResolutionM;
            worst_m =
                std::max(worst_m, std::abs(map.coarse()[grid.brick_index(bx, by, bz)] * kDistanceUnitM - truth_m));
          }
      CHECK(worst_m <= kHalfUnitM + 1e-9);
    }
    WHEN("sampled at 5000 random points 30 to 60 mm above the plane (beyond the fine range: coarse field only)") {
      std::mt19937 rng(31);
      std::uniform_real_distribution<double> ux(origin.x() + kResolutionM, origin.x() + (d.nx - 1) * kResolutionM);
      std::uniform_real_distribution<double> uy(origin.y() + kResolutionM, origin.y() + (d.ny - 1) * kResolutionM);
      std::uniform_real_distribution<double> uh(0.030, 0.060);
      double worst_m = 0.0;
      double worst_gradient = 0.0;
      for (int i = 0; i < 5000; ++i) {
        const Eigen::Vector3d p{ux(rng), uy(rng), plane_z_m + uh(rng)};  // braces: drawn in this order
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        worst_m = std::max(worst_m, std::abs(s.distance_m - (p.z() - plane_z_m)));
        worst_gradient = std::max({worst_gradient, std::abs(s.grad_x), std::abs(s.grad_y)});
      }
      THEN("the distance is the analytic plane distance (linear between nodes) and the x/y gradient is 0") {
        CHECK(worst_m <= kHalfUnitM + 1e-9);
        CHECK(worst_gradient == 0.0);
      }
    }
  }
}

SCENARIO("A grid with no occupied cell gives an empty, saturated map", "[distance_map][sparse]") {
  GIVEN("a 17 x 9 x 5 grid with no occupied cell") {
    const GridDims d{17, 9, 5, kResolutionM};
    const DistanceMap map = build_map(std::vector<std::uint8_t>(d.cell_count(), 0), d, Eigen::Vector3d::Zero(),
                                      cellsight::algo::kDefaultBandM);
    THEN("the map says so, stores no brick and the coarse field saturates") {
      CHECK_FALSE(map.has_surface());
      CHECK(map.stored_bricks() == 0);
      long present = 0;
      for (std::uint16_t b : map.brick_table()) present += b == kAbsentBrick ? 0 : 1;
      CHECK(present == 0);
      long unsaturated = 0;
      for (std::uint16_t c : map.coarse()) unsaturated += c == kCoarseSaturated ? 0 : 1;
      CHECK(unsaturated == 0);
      CHECK(map.coarse().size() == BrickGrid(d).brick_count());
    }
    THEN("a sample inside is finite, the largest coarse distance, with zero gradient") {
      const MapSample s = map.view().sample(0.0123, 0.0071, 0.0052);
      CHECK(std::isfinite(s.distance_m));
      CHECK(s.distance_m == Approx(kMaxCoarseDistanceM).epsilon(1e-12));
      CHECK(s.grad_x == 0.0);
      CHECK(s.grad_y == 0.0);
      CHECK(map.view().fine(16, 8, 4) == kFineFar);
      CHECK(map.view().cell_distance_m(3, 4, 2) == Approx(kMaxCoarseDistanceM).epsilon(1e-12));
    }
  }
}

SCENARIO("Building refuses a bad band or origin with a message", "[distance_map][sparse]") {
  const GridDims d{9, 9, 9, kResolutionM};
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  occ[d.index(4, 4, 4)] = 1;
  EdtScratch scratch(d);
  std::vector<float> work(d.cell_count());
  DistanceMap map;
  const auto refused = [&](double band_m, const Eigen::Vector3d& origin, const char* word) {
    const auto status = build_distance_map(occ.data(), d, origin, band_m, scratch, work.data(), map);
    if (status.ok()) return false;
    INFO(status.error().message);
    CHECK(status.error().message.find(word) != std::string::npos);
    return true;
  };
  const Eigen::Vector3d zero = Eigen::Vector3d::Zero();
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  WHEN("the band is 0, negative, beyond the fine range, NaN or infinite") {
    CHECK(refused(0.0, zero, "band"));
    CHECK(refused(-0.001, zero, "band"));
    CHECK(refused(kMaxFineDistanceM + 1e-6, zero, "band"));
    CHECK(refused(kNaN, zero, "band"));
    CHECK(refused(kInf, zero, "band"));
  }
  WHEN("the origin has a NaN or infinite coordinate") {
    CHECK(refused(0.01, Eigen::Vector3d(0.0, kNaN, 0.0), "origin"));
    CHECK(refused(0.01, Eigen::Vector3d(0.0, 0.0, -kInf), "origin"));
  }
  WHEN("the grid itself is invalid") {
    const auto status = build_distance_map(occ.data(), {9, 0, 9, kResolutionM}, zero, 0.01, scratch, work.data(), map);
    CHECK_FALSE(status.ok());
  }
  WHEN("the band is exactly the fine range") {
    THEN("it is accepted and, on this small grid, every brick is stored") {
      CHECK_FALSE(refused(kMaxFineDistanceM, zero, "band"));
      CHECK(map.stored_bricks() == BrickGrid(d).brick_count());
    }
  }
}

namespace {

// Hand-filled sparse map on a 10 x 9 x 3 grid: 2 x 2 x 1 bricks, so interpolation cells around x, y = 7..8 take
// their corners from different bricks. Fine values are easy to interpolate by hand; coarse nodes are chosen freely.
struct HandMap {
  GridDims dims{10, 9, 3, 0.01};
  Eigen::Vector3d origin_m{0.1, -0.2, 0.05};
  BrickGrid grid{dims};
  std::vector<std::uint16_t> table;
  std::vector<std::uint16_t> coarse{400, 520, 610, 790};  // nodes (bx, by) = (0,0) (1,0) (0,1) (1,1)
  std::vector<std::uint8_t> bricks;

  // Stored brick numbers deliberately not in table order.
  HandMap() : table{2, 0, 3, 1}, bricks(4 * BrickGrid::kBrickCells, kFineFar) {
    for (int z = 0; z < dims.nz; ++z)
      for (int y = 0; y < dims.ny; ++y)
        for (int x = 0; x < dims.nx; ++x) set(x, y, z, value(x, y, z));
  }
  // At most 220 < kFineFar. Slopes per cell: x <= 9, y <= 32, z <= 13 units.
  [[nodiscard]] static std::uint8_t value(int x, int y, int z) {
    return static_cast<std::uint8_t>(5 + 7 * x + 2 * y * y + 11 * z + (x * y + z) % 3);
  }
  void set(int x, int y, int z, std::uint8_t q) {
    const std::size_t b = table[grid.brick_index(x / 8, y / 8, z / 8)];
    bricks[b * BrickGrid::kBrickCells + BrickGrid::in_brick(x, y, z)] = q;
  }
  [[nodiscard]] DistanceMapView view() const {
    return {dims, origin_m, SparseMapData{table.data(), coarse.data(), bricks.data(), 4}};
  }
  // Carrier-frame position of continuous cell-centre coordinates.
  [[nodiscard]] Eigen::Vector3d at(double cx, double cy, double cz) const {
    return origin_m + dims.resolution_m * Eigen::Vector3d(cx + 0.5, cy + 0.5, cz + 0.5);
  }
  [[nodiscard]] MapSample sample_at(const DistanceMapView& v, double cx, double cy, double cz) const {
    const Eigen::Vector3d p = at(cx, cy, cz);
    return v.sample(p.x(), p.y(), p.z());
  }
};

double lerp(double a, double b, double t) {
  return a + (b - a) * t;
}

// Trilinear interpolation of a cell function f at continuous cell coordinates (x0 + tx, y0 + ty, z0 + tz), written
// as nested lerps along x, then y, then z.
template <class F>
double trilinear(F&& f, int x0, int y0, int z0, double tx, double ty, double tz) {
  const auto plane = [&](int z) {
    return lerp(lerp(f(x0, y0, z), f(x0 + 1, y0, z), tx), lerp(f(x0, y0 + 1, z), f(x0 + 1, y0 + 1, z), tx), ty);
  };
  return lerp(plane(z0), plane(z0 + 1), tz);
}

}  // namespace

SCENARIO("Sampling a hand-filled sparse map matches hand computation", "[distance_map][sample]") {
  HandMap hand;
  const auto fine_m = [&](int x, int y, int z) { return HandMap::value(x, y, z) * kDistanceUnitM; };

  GIVEN("every brick stored") {
    const DistanceMapView view = hand.view();
    THEN("fine() and cell_distance_m() return the stored cells") {
      long wrong = 0;
      for (int z = 0; z < 3; ++z)
        for (int y = 0; y < 9; ++y)
          for (int x = 0; x < 10; ++x) {
            wrong += view.fine(x, y, z) == HandMap::value(x, y, z) ? 0 : 1;
            wrong += view.cell_distance_m(x, y, z) == fine_m(x, y, z) ? 0 : 1;
          }
      CHECK(wrong == 0);
    }
    THEN("at every cell centre the sample is the stored cell") {
      double worst = 0.0;
      for (int z = 0; z < 3; ++z)
        for (int y = 0; y < 9; ++y)
          for (int x = 0; x < 10; ++x) {
            worst = std::max(worst, std::abs(hand.sample_at(view, x, y, z).distance_m - fine_m(x, y, z)));
          }
      CHECK(worst < 1e-12);
    }
    THEN("at (7.25, 7.5, 1.75), corners in all four bricks, the distance is the nested lerp of the 8 corners") {
      const MapSample s = hand.sample_at(view, 7.25, 7.5, 1.75);
      CHECK(s.distance_m == Approx(trilinear(fine_m, 7, 7, 1, 0.25, 0.5, 0.75)).epsilon(1e-12));
      // By hand: corners (x, y, z) 7,7,1: 165  8,7,1: 170  7,8,1: 193  8,8,1: 202
      //                            7,7,2: 174  8,7,2: 182  7,8,2: 205  8,8,2: 211 (units of 0.1 mm),
      // so z = 1: lerp(166.25, 195.25, 0.5) = 180.75, z = 2: lerp(176, 206.5, 0.5) = 191.25, at 0.75: 188.625.
      CHECK(s.distance_m == Approx(188.625e-4).epsilon(1e-12));
      const double z1 = lerp(lerp(165, 170, 0.25), lerp(193, 202, 0.25), 0.5);
      const double z2 = lerp(lerp(174, 182, 0.25), lerp(205, 211, 0.25), 0.5);
      CHECK(s.distance_m == Approx(lerp(z1, z2, 0.75) * 1e-4).epsilon(1e-12));
      THEN("the gradient is the interpolant's derivative: lerped corner differences over the cell size") {
        const auto dx = [&](int x, int y, int z) { return fine_m(x + 1, y, z) - fine_m(x, y, z); };
        const auto dy = [&](int x, int y, int z) { return fine_m(x, y + 1, z) - fine_m(x, y, z); };
        const double gx = lerp(lerp(dx(7, 7, 1), dx(7, 8, 1), 0.5), lerp(dx(7, 7, 2), dx(7, 8, 2), 0.5), 0.75) / 0.01;
        const double gy = lerp(lerp(dy(7, 7, 1), dy(8, 7, 1), 0.25), lerp(dy(7, 7, 2), dy(8, 7, 2), 0.25), 0.75) / 0.01;
        CHECK(s.grad_x == Approx(gx).epsilon(1e-12));
        CHECK(s.grad_y == Approx(gy).epsilon(1e-12));
        // By hand: x steps (y 7, 8) 5, 9 at z = 1 and 8, 6 at z = 2 -> 7 and 7 -> 7 units per cell; y steps (x 7, 8)
        // 28, 32 and 31, 29 -> 29 and 30.5 -> 30.125.
        CHECK(s.grad_x == Approx(7e-4 / 0.01).epsilon(1e-12));
        CHECK(s.grad_y == Approx(30.125e-4 / 0.01).epsilon(1e-12));
        // z: the two layers' bilinear values above, 191.25 - 180.75 = 10.5 units per cell.
        CHECK(s.grad_z == Approx((z2 - z1) * 1e-4 / 0.01).epsilon(1e-12));
        CHECK(s.grad_z == Approx(10.5e-4 / 0.01).epsilon(1e-12));
      }
    }
  }
  GIVEN("brick (1, 1, 0) absent") {
    hand.table[hand.grid.brick_index(1, 1, 0)] = kAbsentBrick;
    const DistanceMapView view = hand.view();
    THEN("its cells read kFineFar and their distance is the coarse field") {
      CHECK(view.fine(8, 8, 0) == kFineFar);
      CHECK(view.fine(7, 8, 0) == HandMap::value(7, 8, 0));
      // Cell (8, 8, 0): nodes at 3.5 and 11.5 -> tx = ty = 4.5 / 8; the single z node is constant.
      CHECK(view.cell_distance_m(8, 8, 0) ==
            Approx(lerp(lerp(400, 520, 0.5625), lerp(610, 790, 0.5625), 0.5625) * 1e-4).epsilon(1e-12));
    }
    THEN("a point with a corner in it samples the coarse field, gradient included") {
      const MapSample s = hand.sample_at(view, 7.5, 7.25, 0.5);
      // tx = (7.5 - 3.5) / 8 = 0.5, ty = (7.25 - 3.5) / 8 = 0.46875.
      CHECK(s.distance_m == Approx(lerp(460.0, 700.0, 0.46875) * 1e-4).epsilon(1e-12));
      CHECK(s.grad_x == Approx(lerp(120.0, 180.0, 0.46875) / 8.0 * 1e-4 / 0.01).epsilon(1e-12));
      CHECK(s.grad_y == Approx((700.0 - 460.0) / 8.0 * 1e-4 / 0.01).epsilon(1e-12));
    }
    THEN("a point whose corners all lie in stored bricks still samples the fine cells") {
      const MapSample s = hand.sample_at(view, 6.5, 6.5, 0.5);
      CHECK(s.distance_m == Approx(trilinear(fine_m, 6, 6, 0, 0.5, 0.5, 0.5)).epsilon(1e-12));
    }
  }
  GIVEN("one cell of a stored brick beyond the fine range (kFineFar)") {
    hand.set(5, 5, 1, kFineFar);
    const DistanceMapView view = hand.view();
    THEN("the 8 interpolation cells around it fall back to the coarse field; their neighbours do not") {
      // (4.5, 5.5, 0.5): tx = 1 / 8, ty = 2 / 8 -> lerp(415, 632.5, 0.25) = 469.375 units; slopes per cell
      // lerp(120, 180, 0.25) / 8 = 16.875 and (632.5 - 415) / 8 = 27.1875 units.
      const MapSample s = hand.sample_at(view, 4.5, 5.5, 0.5);
      CHECK(s.distance_m == Approx(469.375e-4).epsilon(1e-12));
      CHECK(s.grad_x == Approx(16.875e-4 / 0.01).epsilon(1e-12));
      CHECK(s.grad_y == Approx(27.1875e-4 / 0.01).epsilon(1e-12));
      const MapSample next = hand.sample_at(view, 6.5, 5.5, 0.5);
      CHECK(next.distance_m == Approx(trilinear(fine_m, 6, 5, 0, 0.5, 0.5, 0.5)).epsilon(1e-12));
    }
  }
}

SCENARIO("Where the coarse field is clamped its gradient is that of the clamped distance: 0",
         "[distance_map][sample][coarse]") {
  GIVEN("the hand map with brick (0, 0, 0) absent: points less than 3.5 cells from the -x and -y faces") {
    HandMap hand;
    hand.table[hand.grid.brick_index(0, 0, 0)] = kAbsentBrick;
    const DistanceMapView view = hand.view();
    WHEN("sampled at (1.5, 1.5, 0.5) and 1e-3 cell either side along x and y") {
      const double h = 1e-3;
      const MapSample s = hand.sample_at(view, 1.5, 1.5, 0.5);
      const double fd_x =
          (hand.sample_at(view, 1.5 + h, 1.5, 0.5).distance_m - hand.sample_at(view, 1.5 - h, 1.5, 0.5).distance_m) /
          (2.0 * h * 0.01);
      const double fd_y =
          (hand.sample_at(view, 1.5, 1.5 + h, 0.5).distance_m - hand.sample_at(view, 1.5, 1.5 - h, 0.5).distance_m) /
          (2.0 * h * 0.01);
      THEN("the distance is node (0, 0) and constant around it, and the gradient is that derivative, 0") {
        CHECK(s.distance_m == Approx(400e-4).epsilon(1e-12));
        CHECK(fd_x == 0.0);
        CHECK(fd_y == 0.0);
        CHECK(s.grad_x == 0.0);
        CHECK(s.grad_y == 0.0);
      }
    }
  }
}

SCENARIO("The sampled gradient is the derivative of the sampled distance", "[distance_map][sample]") {
  GIVEN("the hand map with one brick absent (fine and coarse cells), and a map built from a plate") {
    HandMap hand;
    hand.table[hand.grid.brick_index(0, 0, 0)] = kAbsentBrick;
    const DistanceMapView hand_view = hand.view();
    const GridDims d{69, 61, 45, kResolutionM};
    const Eigen::Vector3d origin(-0.1, 0.05, 0.2);
    const DistanceMap plate = build_map(small_plate(d), d, origin, 0.0088);
    WHEN("central differences with h = 1e-3 cell are taken at 20000 random points inside interpolation cells") {
      // Inside an interpolation cell, and off the coarse field's kinks at node coordinates 8 b + 3.5, the distance
      // is one trilinear polynomial, linear along x and y: its central difference is exact up to rounding.
      std::mt19937 rng(41);
      std::uniform_real_distribution<double> frac(0.0, 1.0);
      const auto pick = [&](int cells) {
        std::uniform_int_distribution<int> cell(0, cells - 2);
        double t = 0.0;
        do t = frac(rng);
        while (std::abs(t - 0.5) < 0.01 || t < 0.01 || t > 0.99);
        return cell(rng) + t;
      };
      const auto check_view = [&](const DistanceMapView& view, long& fine_points, long& coarse_points) {
        const GridDims& g = view.dims();
        const double h = 1e-3;
        long bad = 0;
        for (int i = 0; i < 10000; ++i) {
          const double cx = pick(g.nx);
          const double cy = pick(g.ny);
          const double cz = pick(g.nz);
          const auto at = [&](double x, double y) {
            const Eigen::Vector3d p = view.origin_m() + g.resolution_m * Eigen::Vector3d(x + 0.5, y + 0.5, cz + 0.5);
            return view.sample(p.x(), p.y(), p.z());
          };
          bool fine = true;
          for (int corner = 0; corner < 8; ++corner) {
            fine = fine && view.fine(static_cast<int>(cx) + (corner & 1), static_cast<int>(cy) + ((corner >> 1) & 1),
                                     static_cast<int>(cz) + ((corner >> 2) & 1)) != kFineFar;
          }
          // The coarse field is clamped (constant) beyond its first and last node: see the scenario above.
          const auto clamped = [&](double c, int n) { return c < 3.5 || c > kEdge * (bricks_along(n) - 1) + 3.5; };
          if (!fine && (clamped(cx, g.nx) || clamped(cy, g.ny))) continue;
          const MapSample s = at(cx, cy);
          const double fd_x = (at(cx + h, cy).distance_m - at(cx - h, cy).distance_m) / (2.0 * h * g.resolution_m);
          const double fd_y = (at(cx, cy + h).distance_m - at(cx, cy - h).distance_m) / (2.0 * h * g.resolution_m);
          (fine ? fine_points : coarse_points) += 1;
          const double tolerance_x = 1e-9 * std::abs(fd_x) + 1e-9;
          const double tolerance_y = 1e-9 * std::abs(fd_y) + 1e-9;
          if (std::abs(s.grad_x - fd_x) > tolerance_x || std::abs(s.grad_y - fd_y) > tolerance_y) {
            ++bad;
            UNSCOPED_INFO("at cells (" << cx << ", " << cy << ", " << cz << "): grad " << s.grad_x << ", " << s.grad_y
                                       << " vs finite difference " << fd_x << ", " << fd_y);
          }
        }
        return bad;
      };
      long hand_fine = 0;
      long hand_coarse = 0;
      long plate_fine = 0;
      long plate_coarse = 0;
      const long hand_bad = check_view(hand_view, hand_fine, hand_coarse);
      const long plate_bad = check_view(plate.view(), plate_fine, plate_coarse);
      THEN("the gradient equals the finite difference to 1e-9 relative, on fine and on coarse cells") {
        CHECK(hand_bad == 0);
        CHECK(plate_bad == 0);
        CHECK(hand_fine > 1000);
        CHECK(hand_coarse > 1000);
        CHECK(plate_fine > 1000);
        CHECK(plate_coarse > 1000);
      }
    }
  }
}

SCENARIO("Sampling is continuous across cell and brick faces where the cells are fine", "[distance_map][sample]") {
  GIVEN("the hand map, every brick stored, and a walk along a skew line through it in steps of 1e-4 cell") {
    const HandMap hand;
    const DistanceMapView view = hand.view();
    THEN("no step changes the distance by more than the data's slope allows: no jump at any face") {
      // Slopes are at most 9, 32, 13 units (1e-4 m) per cell along x, y, z, so a step of 1e-4 along (1, 0.9, 0.25)
      // moves the interpolant by <= 4.2e-7 m; outside the box the added distance moves by <= 1.37e-6 m more. A jump
      // would be at least one 1e-4 m unit.
      double worst = 0.0;
      MapSample prev = hand.sample_at(view, -0.4, -0.3, -0.2);
      for (int i = 1; i <= 100000; ++i) {
        const double t = i * 1e-4;
        const MapSample s = hand.sample_at(view, -0.4 + t, -0.3 + 0.9 * t, -0.2 + 0.25 * t);
        worst = std::max(worst, std::abs(s.distance_m - prev.distance_m));
        prev = s;
      }
      CHECK(worst < 2e-6);
    }
    THEN("on both sides of each interior face the samples agree to the slope times the gap") {
      double worst = 0.0;
      for (int face = 1; face < 9; ++face) {
        const double gap = 1e-9;
        for (const double other : {0.3, 4.6, 7.9}) {
          worst = std::max(worst, std::abs(hand.sample_at(view, face - gap, other, 1.2).distance_m -
                                           hand.sample_at(view, face + gap, other, 1.2).distance_m));
          worst = std::max(worst, std::abs(hand.sample_at(view, other, face - gap, 0.7).distance_m -
                                           hand.sample_at(view, other, face + gap, 0.7).distance_m));
        }
      }
      CHECK(worst < 1e-11);
    }
  }
}

SCENARIO("A plane's map has the unit normal as gradient wherever the corners are fine", "[distance_map][sample]") {
  GIVEN("a 16 x 12 x 9 grid whose occupied cells form the plane x = 6 (every distance is a whole 22 units)") {
    const GridDims d{16, 12, 9, kResolutionM};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    for (int z = 0; z < d.nz; ++z)
      for (int y = 0; y < d.ny; ++y) occ[d.index(6, y, z)] = 1;
    const DistanceMap map = build_map(occ, d, Eigen::Vector3d(0.01, 0.02, 0.03), cellsight::algo::kDefaultBandM);
    const DistanceMapView view = map.view();
    THEN("inside the box of cell centres dD/dx = sign(x - 6), dD/dy = 0 and D = |x - 6| cells") {
      std::mt19937 rng(43);
      std::uniform_real_distribution<double> ux(0.0, d.nx - 1.0);
      std::uniform_real_distribution<double> uy(0.0, d.ny - 1.0);
      std::uniform_real_distribution<double> uz(0.0, d.nz - 1.0);
      double worst_gradient = 0.0;
      double worst_distance_m = 0.0;
      long coarse = 0;
      for (int i = 0; i < 5000; ++i) {
        const Eigen::Vector3d c{ux(rng), uy(rng), uz(rng)};  // braces: drawn in this order
        if (std::abs(c.x() - 6.0) < 1e-6) continue;          // the kink
        for (int corner = 0; corner < 8; ++corner) {
          const int x = std::min(static_cast<int>(c.x()) + (corner & 1), d.nx - 1);
          const int y = std::min(static_cast<int>(c.y()) + ((corner >> 1) & 1), d.ny - 1);
          const int z = std::min(static_cast<int>(c.z()) + ((corner >> 2) & 1), d.nz - 1);
          coarse += view.fine(x, y, z) == kFineFar ? 1 : 0;
        }
        const Eigen::Vector3d p = map.origin_m() + kResolutionM * (c + Eigen::Vector3d::Constant(0.5));
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        worst_gradient =
            std::max({worst_gradient, std::abs(s.grad_x - (c.x() > 6.0 ? 1.0 : -1.0)), std::abs(s.grad_y)});
        worst_distance_m = std::max(worst_distance_m, std::abs(s.distance_m - std::abs(c.x() - 6.0) * kResolutionM));
      }
      CHECK(coarse == 0);
      CHECK(worst_gradient < 1e-12);
      CHECK(worst_distance_m < 1e-12);
    }
  }
  GIVEN("a 9 x 15 x 6 grid whose occupied cells form the plane y = 10") {
    const GridDims d{9, 15, 6, kResolutionM};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    for (int z = 0; z < d.nz; ++z)
      for (int x = 0; x < d.nx; ++x) occ[d.index(x, 10, z)] = 1;
    const DistanceMap map = build_map(occ, d, Eigen::Vector3d::Zero(), cellsight::algo::kDefaultBandM);
    const DistanceMapView view = map.view();
    THEN("dD/dy = sign(y - 10) (positive upward, the carrier frame's y) and dD/dx = 0") {
      double worst = 0.0;
      for (double cy = 0.25; cy < d.ny - 1; cy += 0.5) {
        for (double cx = 0.1; cx < d.nx - 1; cx += 0.7) {
          const MapSample s = view.sample((cx + 0.5) * kResolutionM, (cy + 0.5) * kResolutionM, 2.3 * kResolutionM);
          worst = std::max({worst, std::abs(s.grad_y - (cy > 10.0 ? 1.0 : -1.0)), std::abs(s.grad_x)});
        }
      }
      CHECK(worst < 1e-12);
    }
  }
}

SCENARIO("Beyond the grid box the distance to the box is added", "[distance_map][sample]") {
  const HandMap hand;
  const DistanceMapView view = hand.view();
  const auto fine_m = [&](int x, int y, int z) { return HandMap::value(x, y, z) * kDistanceUnitM; };
  GIVEN("a point in the outer half cell beyond x = 9") {
    THEN("it holds the border value") {
      CHECK(hand.sample_at(view, 9.3, 4.0, 1.0).distance_m == Approx(fine_m(9, 4, 1)).epsilon(1e-12));
    }
  }
  GIVEN("a point 4 cells beyond the +x face") {
    // y off the cell centre: at a centre the interpolant has a kink and its y slope is either neighbour's.
    const MapSample s = hand.sample_at(view, 9.5 + 4.0, 4.25, 1.0);
    THEN("the distance is the border value plus 4 cells and the x gradient points away from the grid") {
      CHECK(s.distance_m == Approx(lerp(fine_m(9, 4, 1), fine_m(9, 5, 1), 0.25) + 4.0 * 0.01).epsilon(1e-12));
      CHECK(s.grad_x == Approx(1.0).epsilon(1e-12));
      CHECK(s.grad_y == Approx((fine_m(9, 5, 1) - fine_m(9, 4, 1)) / 0.01).epsilon(1e-12));
    }
  }
  GIVEN("a point 3 cells beyond the -x face and 4 beyond the -y face") {
    const MapSample s = hand.sample_at(view, -0.5 - 3.0, -0.5 - 4.0, 1.0);
    THEN("the Euclidean 5 cells are added and the gradient points along the outward diagonal") {
      CHECK(s.distance_m == Approx(fine_m(0, 0, 1) + 5.0 * 0.01).epsilon(1e-12));
      CHECK(s.grad_x == Approx(-0.6).epsilon(1e-12));
      CHECK(s.grad_y == Approx(-0.8).epsilon(1e-12));
    }
  }
  GIVEN("a point 2 cells above the +z face") {
    const MapSample inside = hand.sample_at(view, 4.25, 3.5, 2.0);
    const MapSample s = hand.sample_at(view, 4.25, 3.5, 2.5 + 2.0);
    THEN("the distance is the top slice's plus 2 cells and the x/y gradient is the top slice's") {
      CHECK(inside.distance_m == Approx(trilinear(fine_m, 4, 3, 1, 0.25, 0.5, 1.0)).epsilon(1e-12));
      CHECK(s.distance_m == Approx(inside.distance_m + 2.0 * 0.01).epsilon(1e-12));
      CHECK(s.grad_x == Approx(inside.grad_x).epsilon(1e-12));
      CHECK(s.grad_y == Approx(inside.grad_y).epsilon(1e-12));
    }
  }
  GIVEN("a NaN coordinate on any axis") {
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    THEN("the distance is NaN, not a wild read") {
      CHECK(std::isnan(view.sample(kNaN, 0.0, 0.1).distance_m));
      CHECK(std::isnan(view.sample(0.15, kNaN, 0.1).distance_m));
      CHECK(std::isnan(view.sample(0.15, -0.15, kNaN).distance_m));
    }
  }
}

SCENARIO("A map one cell thick samples bilinearly", "[distance_map][sample]") {
  GIVEN("a hand-filled 2 x 2 x 1 map") {
    const GridDims flat{2, 2, 1, 0.01};
    const std::vector<std::uint16_t> table{0};
    const std::vector<std::uint16_t> coarse{0};
    std::vector<std::uint8_t> cells(BrickGrid::kBrickCells, kFineFar);
    const std::uint8_t values[2][2] = {{10, 30}, {70, 150}};  // [y][x]
    for (int y = 0; y < 2; ++y)
      for (int x = 0; x < 2; ++x) cells[BrickGrid::in_brick(x, y, 0)] = values[y][x];
    const DistanceMapView view(flat, Eigen::Vector3d::Zero(),
                               SparseMapData{table.data(), coarse.data(), cells.data(), 1});
    THEN("a sample is the bilinear interpolation in x and y at any z inside the grid, gradient its derivative") {
      // Cell centres at 0.005 and 0.015 m: x = 0.0125 -> tx = 0.75, y = 0.0075 -> ty = 0.25.
      const double expected = lerp(lerp(10, 30, 0.75), lerp(70, 150, 0.75), 0.25) * 1e-4;
      for (const double z : {0.002, 0.009}) {
        const MapSample s = view.sample(0.0125, 0.0075, z);
        CHECK(s.distance_m == Approx(expected).epsilon(1e-12));
        CHECK(s.grad_x == Approx(lerp(20, 80, 0.25) * 1e-4 / 0.01).epsilon(1e-12));
        CHECK(s.grad_y == Approx(lerp(60, 120, 0.75) * 1e-4 / 0.01).epsilon(1e-12));
      }
    }
  }
}

SCENARIO("Sampling a built point-field map approximates the true distance", "[distance_map][sample]") {
  GIVEN("a 40 x 36 x 30 map of one occupied cell, origin off zero, band 25.4 mm") {
    const GridDims d{40, 36, 30, kResolutionM};
    const Cell site{17, 20, 13};
    const Eigen::Vector3d origin(0.31, -0.07, 0.9);
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    occ[d.index(site.x, site.y, site.z)] = 1;
    const DistanceMap map = build_map(occ, d, origin, kMaxFineDistanceM);
    const DistanceMapView view = map.view();
    const Eigen::Vector3d centre = origin + kResolutionM * Eigen::Vector3d(site.x + 0.5, site.y + 0.5, site.z + 0.5);
    WHEN("sampled at 20000 random points 4 to 10 cells from the site (all 8 corners within the fine range)") {
      std::mt19937 rng(99);
      std::uniform_real_distribution<double> ux(site.x - 10.0, site.x + 10.0);
      std::uniform_real_distribution<double> uy(site.y - 10.0, site.y + 10.0);
      std::uniform_real_distribution<double> uz(site.z - 10.0, site.z + 10.0);
      double worst_over = 0.0;  // sample - truth, in units of the bound
      double worst_under_m = 0.0;
      double worst_gradient = 0.0;  // |error| over its bound
      long tested = 0;
      AllocationWindow guard;
      while (tested < 20000) {
        const Eigen::Vector3d c{ux(rng), uy(rng), uz(rng)};  // braces: drawn in this order
        const Eigen::Vector3d p = origin + kResolutionM * (c + Eigen::Vector3d::Constant(0.5));
        const Eigen::Vector3d rel = (p - centre) / kResolutionM;
        const double r = rel.norm();
        if (r < 4.0 || r > 10.0) continue;
        ++tested;
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        const double truth_m = r * kResolutionM;
        const double r_min = r - 1.7321;  // every point of the interpolation cell is within sqrt(3) cells of p
        // |p| is convex, so its trilinear interpolant lies above it by at most (1/8) sum_a h^2 max|d2/da2| <=
        // (1/8) * 2 / r_min cells over the cell (the three second derivatives of |p| sum to 2/|p|).
        const double bound_m = kResolutionM * 0.25 / r_min + kHalfUnitM;
        worst_over = std::max(worst_over, (s.distance_m - truth_m) / bound_m);
        worst_under_m = std::max(worst_under_m, truth_m - s.distance_m);
        // d/dx of the interpolant is a mix of edge differences f(x1) - f(x0) = f_x at a point of the edge, within
        // sqrt(3) cells of p: off by at most sqrt(3) |Hessian row| <= sqrt(3) / r_min; each difference of two
        // rounded values adds at most one unit per cell.
        const double gradient_bound = 1.7321 / r_min + kDistanceUnitM / kResolutionM + 1e-6;
        worst_gradient = std::max({worst_gradient, std::abs(s.grad_x - rel.x() / r) / gradient_bound,
                                   std::abs(s.grad_y - rel.y() / r) / gradient_bound});
      }
      const long allocations = guard.count();
      THEN("the distance is above the truth by no more than the interpolation bound (less half a unit)") {
        CHECK(worst_over <= 1.0);
        CHECK(worst_under_m <= kHalfUnitM + 1e-9);
      }
      THEN("each gradient component is within its bound of (p - c) / |p - c|") {
        INFO("worst gradient error / bound " << worst_gradient);
        CHECK(worst_gradient <= 1.0);
      }
      THEN("sampling allocates nothing") {
        CHECK(allocations == 0);
      }
    }
  }
}
