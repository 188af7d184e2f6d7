// Templates built from a scan: occupancy, centroid, Morton-ordered surface points and the distance map.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "formats/template_file.hpp"
#include "formats/template_grid.hpp"

namespace cellsight::formats {
namespace {

using template_grid::dims_of;
using template_grid::number;
using template_grid::validate_grid;

// Interleaves the low 21 bits of x, y, z (x lowest): the Morton (Z-order) key of a cell.
std::uint64_t spread_bits(std::uint32_t v) {
  std::uint64_t x = v & 0x1fffffu;
  x = (x | x << 32) & 0x1f00000000ffffULL;
  x = (x | x << 16) & 0x1f0000ff0000ffULL;
  x = (x | x << 8) & 0x100f00f00f00f00fULL;
  x = (x | x << 4) & 0x10c30c30c30c30c3ULL;
  x = (x | x << 2) & 0x1249249249249249ULL;
  return x;
}
std::uint64_t morton_key(int x, int y, int z) {
  return spread_bits(static_cast<std::uint32_t>(x)) | spread_bits(static_cast<std::uint32_t>(y)) << 1 |
         spread_bits(static_cast<std::uint32_t>(z)) << 2;
}

// Points beyond each side of the grid, counted as GridSpec::cell_of decides (a point may count on two sides).
struct OutsideCount {
  std::size_t below[3] = {0, 0, 0};
  std::size_t above[3] = {0, 0, 0};
  std::size_t not_finite = 0;
  std::size_t total = 0;
};
OutsideCount count_outside(std::span<const algo::ScanPoint> points, const algo::GridSpec& grid) {
  OutsideCount c;
  const int n[3] = {grid.nx, grid.ny, grid.nz};
  for (const algo::ScanPoint& p : points) {
    const double v[3] = {p.x, p.y, p.z};
    bool out = false;
    bool finite = true;
    for (int a = 0; a < 3; ++a) {
      const double f = (v[a] - grid.origin_m[a]) / grid.resolution_m;
      if (!std::isfinite(f)) {
        finite = false;
      } else if (f < 0.0) {
        ++c.below[a];
        out = true;
      } else if (f >= n[a]) {
        ++c.above[a];
        out = true;
      }
    }
    if (!finite) ++c.not_finite;
    if (out || !finite) ++c.total;
  }
  return c;
}

std::string describe_outside(const OutsideCount& c, std::size_t points, const algo::GridSpec& grid) {
  static constexpr const char* kAxis[3] = {"x", "y", "z"};
  const int n[3] = {grid.nx, grid.ny, grid.nz};
  std::string sides;
  const auto add = [&sides](const std::string& what, std::size_t count) {
    if (count == 0) return;
    if (!sides.empty()) sides += ", ";
    sides += what + ": " + std::to_string(count);
  };
  std::string span;
  for (int a = 0; a < 3; ++a) {
    const double lo = grid.origin_m[a];
    const double hi = grid.origin_m[a] + n[a] * grid.resolution_m;
    add(std::string(kAxis[a]) + " < " + number(lo) + " m", c.below[a]);
    add(std::string(kAxis[a]) + " >= " + number(hi) + " m", c.above[a]);
    span += std::string(a == 0 ? "" : ", ") + kAxis[a] + " [" + number(lo) + ", " + number(hi) + ")";
  }
  add("not finite", c.not_finite);
  return std::to_string(c.total) + " of " + std::to_string(points) + " points lie outside the grid (" + sides +
         "); the grid spans " + span +
         " m: the part does not fit, so its template would be cut off. Check the "
         "support removal and the part's position, or move/enlarge the grid in the configuration";
}

}  // namespace

Expected<TemplateModel> build_template(std::span<const algo::ScanPoint> points, const algo::GridSpec& grid,
                                       const TemplateBuildParams& params) {
  if (Status g = validate_grid(grid); !g) return g.error();
  if (params.max_surface_points == 0) return make_error("template: max_surface_points must be at least 1");
  if (points.empty()) return make_error("template: the scan has no points (after carrier removal); nothing to teach");
  const OutsideCount outside = count_outside(points, grid);
  if (outside.total > params.max_outside_points || outside.total == points.size()) {
    return make_error("template: " + describe_outside(outside, points.size(), grid));
  }

  TemplateModel model;
  model.grid = grid;
  model.outside_points = outside.total;

  algo::OccupancyGrid occupancy(grid, points.size());
  if (const std::size_t missed = occupancy.accumulate(points); missed != outside.total) {
    return make_error("template: internal error: " + std::to_string(missed) + " points fell outside the grid, " +
                      std::to_string(outside.total) + " expected");
  }

  // Occupied cells: centroid of all of them (x-y), Morton keys for the surface subsample.
  struct KeyedCell {
    std::uint64_t key;
    std::uint32_t x, y, z;
  };
  std::vector<KeyedCell> occupied;
  occupied.reserve(std::min(points.size(), grid.cells()));
  const std::uint8_t* cells = occupancy.data();
  double sum_x = 0.0;
  double sum_y = 0.0;
  double sum_z = 0.0;
  for (int z = 0; z < grid.nz; ++z) {
    for (int y = 0; y < grid.ny; ++y) {
      const std::uint8_t* row = cells + grid.index(0, y, z);
      for (int x = 0; x < grid.nx; ++x) {
        if (row[x] == 0) continue;
        occupied.push_back({morton_key(x, y, z), static_cast<std::uint32_t>(x), static_cast<std::uint32_t>(y),
                            static_cast<std::uint32_t>(z)});
        sum_x += x + 0.5;
        sum_y += y + 0.5;
        sum_z += z + 0.5;
      }
    }
  }
  const auto n = occupied.size();
  model.occupied_cells = n;
  model.centroid_m =
      grid.origin_m.head<2>() + grid.resolution_m * Eigen::Vector2d(sum_x, sum_y) / static_cast<double>(n);
  model.centroid_z_m = grid.origin_m.z() + grid.resolution_m * sum_z / static_cast<double>(n);

  std::sort(occupied.begin(), occupied.end(), [](const KeyedCell& a, const KeyedCell& b) { return a.key < b.key; });
  const std::size_t m = std::min(n, params.max_surface_points);
  model.surface_cells.reserve(m);
  for (std::size_t k = 0; k < m; ++k) {
    // The centre of the k-th of m equal strata of the Morton order (every cell when m == n).
    const std::size_t i = (2 * k + 1) * n / (2 * m);
    const KeyedCell& c = occupied[i];
    // validate_dims keeps every axis below 2^12 cells, so the indices fit SurfaceCell's uint16.
    model.surface_cells.push_back(
        {static_cast<std::uint16_t>(c.x), static_cast<std::uint16_t>(c.y), static_cast<std::uint16_t>(c.z)});
  }
  occupied = {};  // release before the big buffers below

  const algo::GridDims dims = dims_of(grid);
  algo::EdtScratch scratch(dims);
  std::vector<float> work(dims.cell_count());
  if (Status built =
          algo::build_distance_map(cells, dims, grid.origin_m, params.band_m, scratch, work.data(), model.map);
      !built) {
    return make_error("template: " + built.error().message);
  }
  return model;
}

}  // namespace cellsight::formats
