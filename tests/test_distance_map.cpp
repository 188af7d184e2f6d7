// Tests of algo/distance_map: exact EDT against brute force, gradient maps against analytic fields, trilinear sampling.
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <numbers>
#include <random>
#include <vector>

#include "algo/distance_map.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using cellsight::algo::BrickLayout;
using cellsight::algo::build_distance_map;
using cellsight::algo::distance_from_squared;
using cellsight::algo::DistanceMap;
using cellsight::algo::DistanceMapView;
using cellsight::algo::edt_squared;
using cellsight::algo::EdtScratch;
using cellsight::algo::GradientMethod;
using cellsight::algo::gradients_xy;
using cellsight::algo::GridDims;
using cellsight::algo::MapCell;
using cellsight::algo::MapSample;
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

// Distance field (metres) of a grid with the given occupied cells.
std::vector<float> distance_field(const GridDims& d, const std::vector<Cell>& sites) {
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  for (const Cell& s : sites) occ[d.index(s.x, s.y, s.z)] = 1;
  std::vector<float> field = run_edt(occ, d);
  distance_from_squared(d, field.data());
  return field;
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

SCENARIO("Building a map again for the same grid allocates nothing", "[distance_map][compact]") {
  GIVEN("a 60 x 50 x 40 grid with a few hundred random occupied cells, built once") {
    const GridDims d{60, 50, 40, kResolutionM};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    std::mt19937 rng(3);
    std::uniform_int_distribution<std::size_t> cell(0, d.cell_count() - 1);
    for (int i = 0; i < 300; ++i) occ[cell(rng)] = 1;
    EdtScratch scratch(d);
    std::vector<float> work(d.cell_count());
    DistanceMap map;
    const Eigen::Vector3d origin(-0.3, 0.1, 0.2);
    REQUIRE(build_distance_map(occ.data(), d, origin, GradientMethod::kSobelAveraged, scratch, work.data(), map).ok());
    WHEN("it is rebuilt with the same buffers (other content, other method)") {
      occ[cell(rng)] = 1;
      AllocationWindow guard;
      const auto status =
          build_distance_map(occ.data(), d, origin, GradientMethod::kCentralDifference, scratch, work.data(), map);
      const long allocations = guard.count();
      THEN("nothing is allocated and the map is 6 bytes per stored cell (grid padded to whole 8^3 bricks)") {
        REQUIRE(status.ok());
        CHECK(allocations == 0);
        CHECK(map.memory_bytes() == std::size_t{64} * 56 * 40 * 6);
        CHECK(map.has_surface());
      }
    }
  }
}

namespace {

// Component errors of a gradient map against the analytic gradient of the distance to one point, over cells at
// least min_r cells from it and away from the grid border (where differences are one-sided by design).
struct GradientError {
  double max_scaled = 0.0;  // max over cells of |error| * r^2 (r in cells): Taylor predicts a constant
  double rms = 0.0;
  double max_angle_deg = 0.0;     // in the site's z slice, where the x/y gradient has unit length
  double max_length_error = 0.0;  // ditto, | |g| - 1 |
};

GradientError point_field_error(const GridDims& d, const Cell& site, const std::vector<float>& gx,
                                const std::vector<float>& gy, double min_r) {
  GradientError e;
  double sum2 = 0.0;
  long n = 0;
  for (int z = 1; z < d.nz - 1; ++z)
    for (int y = 1; y < d.ny - 1; ++y)
      for (int x = 1; x < d.nx - 1; ++x) {
        const double dx = x - site.x;
        const double dy = y - site.y;
        const double dz = z - site.z;
        const double r = std::sqrt(dx * dx + dy * dy + dz * dz);
        if (r < min_r) continue;
        const std::size_t i = d.index(x, y, z);
        const double ex = gx[i] - dx / r;
        const double ey = gy[i] - dy / r;
        e.max_scaled = std::max({e.max_scaled, std::abs(ex) * r * r, std::abs(ey) * r * r});
        sum2 += ex * ex + ey * ey;
        n += 2;
        if (z == site.z) {
          const double angle = std::atan2(gx[i] * dy - gy[i] * dx, gx[i] * dx + gy[i] * dy);
          e.max_angle_deg = std::max(e.max_angle_deg, std::abs(angle) * 180.0 / std::numbers::pi);
          e.max_length_error = std::max(e.max_length_error, std::abs(std::hypot(gx[i], gy[i]) - 1.0));
        }
      }
  e.rms = std::sqrt(sum2 / static_cast<double>(n));
  return e;
}

}  // namespace

SCENARIO("Gradient maps of a point field point away from the point with unit slope", "[distance_map][gradient]") {
  GIVEN("a 41 x 41 x 41 grid with one occupied cell in the middle (its transform is |p - c| exactly)") {
    const GridDims d{41, 41, 41, kResolutionM};
    const Cell site{20, 20, 20};
    const std::vector<float> dist = distance_field(d, {site});
    EdtScratch scratch(d);
    std::vector<float> sx(d.cell_count());
    std::vector<float> sy(d.cell_count());
    std::vector<float> cx(d.cell_count());
    std::vector<float> cy(d.cell_count());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kSobelAveraged, scratch, sx.data(), sy.data()).ok());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kCentralDifference, scratch, cx.data(), cy.data()).ok());
    WHEN("compared with the analytic gradient (p - c) / |p - c| at cells 5 or more cells away") {
      const GradientError sobel = point_field_error(d, site, sx, sy, 5.0);
      const GradientError central = point_field_error(d, site, cx, cy, 5.0);
      INFO("sobel: max|e|r^2 " << sobel.max_scaled << " rms " << sobel.rms << " angle " << sobel.max_angle_deg
                               << " len " << sobel.max_length_error);
      INFO("central: max|e|r^2 " << central.max_scaled << " rms " << central.rms << " angle " << central.max_angle_deg
                                 << " len " << central.max_length_error);
      THEN("the central difference stays within its Taylor bound |r_xxx| / 6 <= 0.19 / r^2 (+10 % higher order)") {
        CHECK(central.max_scaled < 0.21);
      }
      THEN(
          "the Sobel average stays within its bound 0.19 + 1/4 + 1/3 = 0.78 / r^2 (the [1 2 1] and [1 1 1] "
          "smoothing adds h^2/4 r_xyy + h^2/3 r_xzz, each |.| <= 1 / r^2)") {
        CHECK(sobel.max_scaled < 0.86);
      }
      THEN("in the site's slice both point within 0.5 deg of the true direction, length 1 within |e_x| + |e_y|") {
        CHECK(central.max_angle_deg < 0.5);
        CHECK(sobel.max_angle_deg < 0.5);
        CHECK(central.max_length_error < 2.0 * 0.21 / 25.0);
        CHECK(sobel.max_length_error < 2.0 * 0.86 / 25.0);
      }
      THEN("the central difference has the smaller component error (its stencil has no cross-axis smoothing)") {
        CHECK(central.rms < 0.65 * sobel.rms);
        CHECK(central.max_scaled * 2.0 < sobel.max_scaled);
      }
    }
  }
}

SCENARIO("Near the ridges between sites the central difference follows the true gradient better",
         "[distance_map][gradient]") {
  GIVEN("a 32 x 32 x 32 grid with 24 random occupied cells: the field has ridges where two sites are equally near") {
    const GridDims d{32, 32, 32, kResolutionM};
    std::mt19937 rng(11);
    std::uniform_int_distribution<int> u(0, 31);
    std::vector<Cell> sites(24);
    for (Cell& c : sites) c = {u(rng), u(rng), u(rng)};
    const std::vector<float> dist = distance_field(d, sites);
    EdtScratch scratch(d);
    std::vector<float> sx(d.cell_count());
    std::vector<float> sy(d.cell_count());
    std::vector<float> cx(d.cell_count());
    std::vector<float> cy(d.cell_count());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kSobelAveraged, scratch, sx.data(), sy.data()).ok());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kCentralDifference, scratch, cx.data(), cy.data()).ok());
    WHEN(
        "both are compared with (p - q) / |p - q|, q the unique nearest site (cells whose second-nearest site is "
        "within 1.5 cells of the nearest are left out: there the field has a kink and no gradient)") {
      double sum_sobel = 0.0;
      double sum_central = 0.0;
      long n = 0;
      for (int z = 1; z < d.nz - 1; ++z)
        for (int y = 1; y < d.ny - 1; ++y)
          for (int x = 1; x < d.nx - 1; ++x) {
            double best = -1.0;
            double second = -1.0;
            Cell q{};
            for (const Cell& s : sites) {
              const double r =
                  std::sqrt(static_cast<double>((x - s.x) * (x - s.x) + (y - s.y) * (y - s.y) + (z - s.z) * (z - s.z)));
              if (best < 0.0 || r < best) {
                second = best;
                best = r;
                q = s;
              } else if (second < 0.0 || r < second) {
                second = r;
              }
            }
            if (best < 2.0 || second - best < 1.5) continue;
            const std::size_t i = d.index(x, y, z);
            const double tx = (x - q.x) / best;
            const double ty = (y - q.y) / best;
            sum_sobel += (sx[i] - tx) * (sx[i] - tx) + (sy[i] - ty) * (sy[i] - ty);
            sum_central += (cx[i] - tx) * (cx[i] - tx) + (cy[i] - ty) * (cy[i] - ty);
            ++n;
          }
      const double rms_sobel = std::sqrt(sum_sobel / n);
      const double rms_central = std::sqrt(sum_central / n);
      INFO("cells " << n << ", rms sobel " << rms_sobel << ", rms central " << rms_central);
      THEN(
          "the central difference's error is less than half the Sobel average's (its stencil straddles fewer "
          "ridges)") {
        REQUIRE(n > 5000);
        CHECK(rms_central < 0.5 * rms_sobel);
      }
    }
  }
}

SCENARIO("Against the continuous surface behind a voxel surface the Sobel average is the closer one",
         "[distance_map][gradient]") {
  GIVEN("a 48^3 grid holding the voxelised plane z = 20 + 0.35 x + 0.2 y (one occupied cell per column)") {
    const GridDims d{48, 48, 48, kResolutionM};
    std::vector<Cell> plane;
    for (int y = 0; y < d.ny; ++y)
      for (int x = 0; x < d.nx; ++x) {
        const int z = static_cast<int>(std::floor(20.0 + 0.35 * (x + 0.5) + 0.2 * (y + 0.5)));
        if (z < d.nz) plane.push_back({x, y, z});
      }
    const std::vector<float> dist = distance_field(d, plane);
    EdtScratch scratch(d);
    std::vector<float> sx(d.cell_count());
    std::vector<float> sy(d.cell_count());
    std::vector<float> cx(d.cell_count());
    std::vector<float> cy(d.cell_count());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kSobelAveraged, scratch, sx.data(), sy.data()).ok());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kCentralDifference, scratch, cx.data(), cy.data()).ok());
    WHEN(
        "both are compared with the plane's unit normal (sign by side) at cells 3 or more cells from the plane, "
        "in columns whose nearest plane point lies inside the grid") {
      const Eigen::Vector3d normal = Eigen::Vector3d(-0.35, -0.2, 1.0).normalized();
      double sum_sobel = 0.0;
      double sum_central = 0.0;
      long n = 0;
      for (int z = 1; z < d.nz - 1; ++z)
        for (int y = 6; y <= 30; ++y)
          for (int x = 6; x <= 30; ++x) {
            const double offset = ((z + 0.5) - (20.0 + 0.35 * (x + 0.5) + 0.2 * (y + 0.5))) * normal.z();
            if (std::abs(offset) < 3.0) continue;
            const double side = offset > 0.0 ? 1.0 : -1.0;
            const std::size_t i = d.index(x, y, z);
            const double tx = side * normal.x();
            const double ty = side * normal.y();
            sum_sobel += (sx[i] - tx) * (sx[i] - tx) + (sy[i] - ty) * (sy[i] - ty);
            sum_central += (cx[i] - tx) * (cx[i] - tx) + (cy[i] - ty) * (cy[i] - ty);
            ++n;
          }
      const double rms_sobel = std::sqrt(sum_sobel / n);
      const double rms_central = std::sqrt(sum_central / n);
      INFO("cells " << n << ", rms sobel " << rms_sobel << ", rms central " << rms_central);
      THEN(
          "the Sobel average's error is at least 20 % smaller (its smoothing hides the voxel staircase), and both "
          "stay below 0.1 per component") {
        REQUIRE(n > 10000);
        CHECK(rms_sobel < 0.8 * rms_central);
        CHECK(rms_central < 0.1);
      }
    }
  }
}

SCENARIO("Gradient maps of a plane are exactly the unit normal", "[distance_map][gradient]") {
  GIVEN("a 20 x 12 x 9 grid whose occupied cells form the plane x = 6") {
    const GridDims d{20, 12, 9, kResolutionM};
    std::vector<Cell> plane;
    for (int z = 0; z < d.nz; ++z)
      for (int y = 0; y < d.ny; ++y) plane.push_back({6, y, z});
    const std::vector<float> dist = distance_field(d, plane);
    EdtScratch scratch(d);
    THEN("both methods give dD/dx = sign(x - 6) (0 on the plane) and dD/dy = 0 everywhere, to float rounding") {
      for (GradientMethod method : {GradientMethod::kSobelAveraged, GradientMethod::kCentralDifference}) {
        std::vector<float> gx(d.cell_count());
        std::vector<float> gy(d.cell_count());
        REQUIRE(gradients_xy(dist.data(), d, method, scratch, gx.data(), gy.data()).ok());
        double worst = 0.0;
        for (int z = 0; z < d.nz; ++z)
          for (int y = 0; y < d.ny; ++y)
            for (int x = 0; x < d.nx; ++x) {
              const std::size_t i = d.index(x, y, z);
              const double expected = x > 6 ? 1.0 : (x < 6 ? -1.0 : 0.0);
              worst = std::max({worst, std::abs(gx[i] - expected), std::abs(static_cast<double>(gy[i]))});
            }
        CHECK(worst < 1e-5);
      }
    }
  }
  GIVEN("a 9 x 15 x 6 grid whose occupied cells form the plane y = 10") {
    const GridDims d{9, 15, 6, kResolutionM};
    std::vector<Cell> plane;
    for (int z = 0; z < d.nz; ++z)
      for (int x = 0; x < d.nx; ++x) plane.push_back({x, 10, z});
    const std::vector<float> dist = distance_field(d, plane);
    EdtScratch scratch(d);
    std::vector<float> gx(d.cell_count());
    std::vector<float> gy(d.cell_count());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kSobelAveraged, scratch, gx.data(), gy.data()).ok());
    THEN("dD/dy = sign(y - 10) (positive upward, the carrier frame's y) and dD/dx = 0") {
      double worst = 0.0;
      for (int z = 0; z < d.nz; ++z)
        for (int y = 0; y < d.ny; ++y)
          for (int x = 0; x < d.nx; ++x) {
            const std::size_t i = d.index(x, y, z);
            const double expected = y > 10 ? 1.0 : (y < 10 ? -1.0 : 0.0);
            worst = std::max({worst, std::abs(gy[i] - expected), std::abs(static_cast<double>(gx[i]))});
          }
      CHECK(worst < 1e-5);
    }
  }
}

SCENARIO("The compact map loses at most half a storage unit", "[distance_map][compact]") {
  GIVEN("the point field and its float gradients") {
    const GridDims d{33, 29, 25, kResolutionM};
    const Cell site{11, 17, 9};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    occ[d.index(site.x, site.y, site.z)] = 1;
    EdtScratch scratch(d);
    std::vector<float> work(d.cell_count());
    DistanceMap map;
    REQUIRE(build_distance_map(occ.data(), d, Eigen::Vector3d::Zero(), GradientMethod::kCentralDifference, scratch,
                               work.data(), map)
                .ok());
    const std::vector<float> dist = distance_field(d, {site});
    std::vector<float> gx(d.cell_count());
    std::vector<float> gy(d.cell_count());
    REQUIRE(gradients_xy(dist.data(), d, GradientMethod::kCentralDifference, scratch, gx.data(), gy.data()).ok());
    THEN("stored distances are within 0.05 mm of the analytic |p - c| and gradients within 1.6e-5 of the floats") {
      double worst_distance_m = 0.0;
      double worst_gradient = 0.0;
      for (int z = 0; z < d.nz; ++z)
        for (int y = 0; y < d.ny; ++y)
          for (int x = 0; x < d.nx; ++x) {
            const std::size_t i = d.index(x, y, z);
            const double truth_m =
                kResolutionM * std::sqrt(static_cast<double>((x - site.x) * (x - site.x) + (y - site.y) * (y - site.y) +
                                                             (z - site.z) * (z - site.z)));
            const MapCell& c = map.view().cell(x, y, z);
            worst_distance_m =
                std::max(worst_distance_m, std::abs(c.distance * cellsight::algo::kDistanceUnitM - truth_m));
            worst_gradient = std::max({worst_gradient, std::abs(c.grad_x * cellsight::algo::kGradientUnit - gx[i]),
                                       std::abs(c.grad_y * cellsight::algo::kGradientUnit - gy[i])});
          }
      CHECK(worst_distance_m <= 0.5 * cellsight::algo::kDistanceUnitM + 1e-9);
      CHECK(worst_gradient <= 0.5 * cellsight::algo::kGradientUnit + 1e-7);
      CHECK(map.has_surface());
    }
  }
  GIVEN("a grid with no occupied cell") {
    const GridDims d{7, 5, 3, kResolutionM};
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    EdtScratch scratch(d);
    std::vector<float> work(d.cell_count());
    DistanceMap map;
    REQUIRE(build_distance_map(occ.data(), d, Eigen::Vector3d::Zero(), GradientMethod::kSobelAveraged, scratch,
                               work.data(), map)
                .ok());
    THEN("the map says so, every distance saturates and every gradient is 0; a sample is finite") {
      CHECK_FALSE(map.has_surface());
      long wrong = 0;
      for (const MapCell& c : map.cells())
        wrong += (c.distance == cellsight::algo::kDistanceSaturated && c.grad_x == 0 && c.grad_y == 0) ? 0 : 1;
      CHECK(wrong == 0);
      const MapSample s = map.view().sample(0.004, 0.003, 0.002);
      CHECK(s.distance_m == Approx(cellsight::algo::kMaxDistanceM));
      CHECK(s.grad_x == 0.0);
    }
  }
}

SCENARIO("The brick layout stores every grid cell exactly once", "[distance_map][compact]") {
  GIVEN("grids whose sides are and are not whole bricks, down to one cell") {
    const GridDims shapes[] = {{1, 1, 1, kResolutionM},
                               {8, 8, 8, kResolutionM},
                               {9, 17, 3, kResolutionM},
                               {23, 5, 16, kResolutionM},
                               {1, 30, 2, kResolutionM}};
    THEN("the indices of all cells are distinct and inside the padded array of whole bricks") {
      for (const GridDims& d : shapes) {
        const BrickLayout layout(d);
        const auto bricks = [](int n) { return static_cast<std::size_t>((n + 7) / 8); };
        CHECK(layout.cell_count() == bricks(d.nx) * bricks(d.ny) * bricks(d.nz) * 512);
        std::vector<int> hits(layout.cell_count(), 0);
        long outside = 0;
        for (int z = 0; z < d.nz; ++z)
          for (int y = 0; y < d.ny; ++y)
            for (int x = 0; x < d.nx; ++x) {
              const std::size_t i = layout.index(x, y, z);
              if (i >= hits.size()) {
                ++outside;
              } else {
                ++hits[i];
              }
            }
        long duplicates = 0;
        long stored = 0;
        for (int h : hits) {
          duplicates += h > 1 ? 1 : 0;
          stored += h;
        }
        CHECK(outside == 0);
        CHECK(duplicates == 0);
        CHECK(stored == static_cast<long>(d.cell_count()));
      }
    }
  }
}

namespace {

// Hand-filled 3 x 3 x 2 map with values that are easy to interpolate by hand.
struct HandMap {
  GridDims dims{3, 3, 2, 0.01};
  Eigen::Vector3d origin_m{0.1, -0.2, 0.05};
  std::vector<MapCell> cells;
  HandMap() : cells(BrickLayout(dims).cell_count()) {
    const BrickLayout layout(dims);
    for (int z = 0; z < dims.nz; ++z)
      for (int y = 0; y < dims.ny; ++y)
        for (int x = 0; x < dims.nx; ++x) {
          MapCell& c = cells[layout.index(x, y, z)];
          c.distance = static_cast<std::uint16_t>(1000 + 100 * x + 30 * y * y + 7 * z + 11 * x * y * z);
          c.grad_x = static_cast<std::int16_t>(-2000 + 500 * x - 300 * z);
          c.grad_y = static_cast<std::int16_t>(1000 * y - 40 * x * z);
        }
  }
  [[nodiscard]] DistanceMapView view() const { return {dims, origin_m, cells.data()}; }
  // Carrier-frame position of continuous cell-centre coordinates.
  [[nodiscard]] Eigen::Vector3d at(double cx, double cy, double cz) const {
    return origin_m + dims.resolution_m * Eigen::Vector3d(cx + 0.5, cy + 0.5, cz + 0.5);
  }
};

double lerp(double a, double b, double t) {
  return a + (b - a) * t;
}

}  // namespace

SCENARIO("Trilinear sampling matches hand computation and is continuous", "[distance_map][sample]") {
  const HandMap hand;
  const DistanceMapView view = hand.view();
  const auto stored = [&](int x, int y, int z) { return view.cell(x, y, z); };

  GIVEN("points exactly at cell centres") {
    THEN("the sample is the stored cell") {
      for (int z = 0; z < 2; ++z)
        for (int y = 0; y < 3; ++y)
          for (int x = 0; x < 3; ++x) {
            const Eigen::Vector3d p = hand.at(x, y, z);
            const MapSample s = view.sample(p.x(), p.y(), p.z());
            CHECK(s.distance_m == Approx(stored(x, y, z).distance * 1e-4).margin(1e-12));
            CHECK(s.grad_x == Approx(stored(x, y, z).grad_x / 32767.0).margin(1e-12));
            CHECK(s.grad_y == Approx(stored(x, y, z).grad_y / 32767.0).margin(1e-12));
          }
    }
  }
  GIVEN("the point at cell-centre coordinates (1.25, 0.5, 0.75)") {
    const Eigen::Vector3d p = hand.at(1.25, 0.5, 0.75);
    const MapSample s = view.sample(p.x(), p.y(), p.z());
    THEN("the distance is the nested linear interpolation along x, then y, then z of the 8 corners") {
      const auto d = [&](int x, int y, int z) { return stored(x, y, z).distance * 1e-4; };
      const double z0 = lerp(lerp(d(1, 0, 0), d(2, 0, 0), 0.25), lerp(d(1, 1, 0), d(2, 1, 0), 0.25), 0.5);
      const double z1 = lerp(lerp(d(1, 0, 1), d(2, 0, 1), 0.25), lerp(d(1, 1, 1), d(2, 1, 1), 0.25), 0.5);
      CHECK(s.distance_m == Approx(lerp(z0, z1, 0.75)).epsilon(1e-12));
      // By hand: corner values 1100 1200 1130 1230 / 1107 1207 1148 1259 (units of 0.1 mm).
      CHECK(s.distance_m == Approx(((1125 + 1155) / 2.0 * 0.25 + (1132 + 1175.75) / 2.0 * 0.75) * 1e-4));
    }
    THEN("the gradients interpolate the same way") {
      const auto gx = [&](int x, int y, int z) { return stored(x, y, z).grad_x / 32767.0; };
      const double z0 = lerp(lerp(gx(1, 0, 0), gx(2, 0, 0), 0.25), lerp(gx(1, 1, 0), gx(2, 1, 0), 0.25), 0.5);
      const double z1 = lerp(lerp(gx(1, 0, 1), gx(2, 0, 1), 0.25), lerp(gx(1, 1, 1), gx(2, 1, 1), 0.25), 0.5);
      CHECK(s.grad_x == Approx(lerp(z0, z1, 0.75)).epsilon(1e-12));
    }
  }
  GIVEN("a walk along a skew line through the grid in steps of 1e-4 cell") {
    THEN("no step changes the distance by more than the data's slope allows: no jump at any cell boundary") {
      // The data's slopes are at most 0.0122, 0.0172, 0.0051 m per cell along x, y, z, so a step of 1e-4 along the
      // direction (1, 0.9, 0.5) moves the interpolant by <= 3.0e-6 m (the added outside distance by less); a jump at
      // a boundary would be at least one 1e-4 m storage unit.
      double worst = 0.0;
      MapSample prev =
          view.sample(hand.at(-0.4, -0.3, -0.2).x(), hand.at(-0.4, -0.3, -0.2).y(), hand.at(-0.4, -0.3, -0.2).z());
      for (int i = 1; i <= 30000; ++i) {
        const double t = i * 1e-4;
        const Eigen::Vector3d p = hand.at(-0.4 + t, -0.3 + 0.9 * t, -0.2 + 0.5 * t);
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        worst = std::max({worst, std::abs(s.distance_m - prev.distance_m)});
        prev = s;
      }
      CHECK(worst < 3.1e-6);
    }
  }
  GIVEN("a map one cell thick in z (2 x 2 x 1)") {
    const GridDims flat{2, 2, 1, 0.01};
    std::vector<MapCell> cells(BrickLayout(flat).cell_count(), MapCell{0, 0, 0});
    const DistanceMapView flat_view(flat, Eigen::Vector3d::Zero(), cells.data());
    const std::uint16_t values[2][2] = {{100, 300}, {700, 1500}};  // [y][x]
    for (int y = 0; y < 2; ++y)
      for (int x = 0; x < 2; ++x) cells[BrickLayout(flat).index(x, y, 0)].distance = values[y][x];
    THEN("a sample is the bilinear interpolation in x and y at any z inside the grid") {
      // Cell centres at 0.005 and 0.015 m: x = 0.0125 -> tx = 0.75, y = 0.0075 -> ty = 0.25.
      const double expected = lerp(lerp(100, 300, 0.75), lerp(700, 1500, 0.75), 0.25) * 1e-4;
      CHECK(flat_view.sample(0.0125, 0.0075, 0.002).distance_m == Approx(expected));
      CHECK(flat_view.sample(0.0125, 0.0075, 0.009).distance_m == Approx(expected));
    }
  }
  GIVEN("points beyond the grid") {
    const MapCell border = stored(2, 1, 1);
    const Eigen::Vector3d skirt = hand.at(2.3, 1.0, 1.0);                 // in the outer half cell
    const Eigen::Vector3d out = hand.at(2.5 + 4.0, 1.0, 1.0);             // 4 cells beyond the +x face
    const Eigen::Vector3d corner = hand.at(-0.5 - 3.0, -0.5 - 4.0, 1.0);  // 5 cells from the x-y edge
    THEN("the outer half cell holds the border value") {
      CHECK(view.sample(skirt.x(), skirt.y(), skirt.z()).distance_m == Approx(border.distance * 1e-4));
    }
    THEN("beyond the face the distance to the grid is added and the x gradient points away from the grid") {
      const MapSample s = view.sample(out.x(), out.y(), out.z());
      CHECK(s.distance_m == Approx(border.distance * 1e-4 + 4.0 * 0.01));
      CHECK(s.grad_x == Approx(1.0));
      CHECK(s.grad_y == Approx(border.grad_y / 32767.0));
    }
    THEN("beyond an edge the Euclidean distance to the edge is added, gradient along the outward diagonal") {
      const MapSample s = view.sample(corner.x(), corner.y(), corner.z());
      CHECK(s.distance_m == Approx(stored(0, 0, 1).distance * 1e-4 + 5.0 * 0.01));
      CHECK(s.grad_x == Approx(-0.6));
      CHECK(s.grad_y == Approx(-0.8));
    }
    THEN("a NaN coordinate gives a NaN distance, not a wild read") {
      const MapSample s = view.sample(std::numeric_limits<double>::quiet_NaN(), 0.0, 0.0);
      CHECK(std::isnan(s.distance_m));
    }
  }
}

SCENARIO("Sampling a built point-field map approximates the true distance", "[distance_map][sample]") {
  GIVEN("a 40 x 36 x 30 map of one occupied cell, origin off zero") {
    const GridDims d{40, 36, 30, kResolutionM};
    const Cell site{17, 20, 13};
    const Eigen::Vector3d origin(0.31, -0.07, 0.9);
    std::vector<std::uint8_t> occ(d.cell_count(), 0);
    occ[d.index(site.x, site.y, site.z)] = 1;
    EdtScratch scratch(d);
    std::vector<float> work(d.cell_count());
    DistanceMap map;
    REQUIRE(
        build_distance_map(occ.data(), d, origin, GradientMethod::kCentralDifference, scratch, work.data(), map).ok());
    const DistanceMapView view = map.view();
    const Eigen::Vector3d centre = origin + kResolutionM * Eigen::Vector3d(site.x + 0.5, site.y + 0.5, site.z + 0.5);
    WHEN(
        "sampled at 20000 random points at least 4 cells from the site and between the second and the "
        "second-to-last cell centre (the border cells hold one-sided differences, O(h / r) by design)") {
      std::mt19937 rng(99);
      std::uniform_real_distribution<double> ux(1.0, d.nx - 2.0);
      std::uniform_real_distribution<double> uy(1.0, d.ny - 2.0);
      std::uniform_real_distribution<double> uz(1.0, d.nz - 2.0);
      double worst_over = 0.0;  // sample - truth, in units of the bound
      double worst_under_m = 0.0;
      double worst_gradient = 0.0;  // |error| * r_min^2, r in cells
      long tested = 0;
      AllocationWindow guard;
      while (tested < 20000) {
        const Eigen::Vector3d p =
            origin + kResolutionM * (Eigen::Vector3d{ux(rng), uy(rng), uz(rng)} + Eigen::Vector3d::Constant(0.5));
        const Eigen::Vector3d rel = (p - centre) / kResolutionM;
        const double r = rel.norm();
        if (r < 4.0) continue;
        ++tested;
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        const double truth_m = r * kResolutionM;
        // |p| is convex, so its trilinear interpolant lies above it by at most (1/8) sum_a h^2 max|d2/da2| <=
        // (1/8) * 2 / r_min cells (the three second derivatives of |p| sum to 2/|p|), r_min = r - sqrt(3)/2.
        const double bound_m = kResolutionM * 0.25 / (r - 0.87) + 0.5e-4;
        worst_over = std::max(worst_over, (s.distance_m - truth_m) / bound_m);
        worst_under_m = std::max(worst_under_m, truth_m - s.distance_m);
        const double r_min = r - 0.87;
        worst_gradient = std::max({worst_gradient, std::abs(s.grad_x - rel.x() / r) * r_min * r_min,
                                   std::abs(s.grad_y - rel.y() / r) * r_min * r_min});
      }
      const long allocations = guard.count();
      THEN("the distance is above the truth by no more than the interpolation bound (less 0.05 mm rounding)") {
        CHECK(worst_over <= 1.0);
        CHECK(worst_under_m <= 0.5e-4 + 1e-9);
      }
      THEN("each gradient component is within (0.21 + 0.4) / r_min^2 of (p - c) / |p - c|") {
        // 0.21 / r^2: the central difference at the corners (see the point-field scenario); 0.4 / r^2: trilinear
        // interpolation error (1/8) sum_a max|d2 g / da2| with |d2(x/r)/dx2| <= 1.16 / r^2, the other two <= 1 / r^2.
        CHECK(worst_gradient < 0.61);
      }
      THEN("sampling allocates nothing") {
        CHECK(allocations == 0);
      }
    }
  }
}
