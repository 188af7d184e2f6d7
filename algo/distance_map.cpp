// Exact 3D Euclidean distance transform (separable lower envelope of parabolas) and the sparse map of Perfect Match.
#include "algo/distance_map.hpp"

#include <string>

namespace cellsight::algo {
namespace {

// "No site on this line yet": larger than any real squared distance (< kMaxExactSquaredCells), and never added to.
constexpr std::int32_t kNoSite = std::numeric_limits<std::int32_t>::max();

[[nodiscard]] inline std::int32_t from_float(float d2) {
  return std::isinf(d2) ? kNoSite : static_cast<std::int32_t>(d2);
}
[[nodiscard]] inline float to_float(std::int32_t d2) {
  return d2 == kNoSite ? std::numeric_limits<float>::infinity() : static_cast<float>(d2);
}

// One 1D pass: out[x] = min over sites u (f[u] != kNoSite) of (x - u)^2 + f[u]; all kNoSite when there is no site.
// Lower envelope of the parabolas apexed at (u, f[u]) (Felzenszwalb & Huttenlocher), with Meijster's integer
// separator so that every value is exact: starts[k] is the first integer cell where sites[k] is the lowest parabola.
// Magnitudes stay below 2^24 (validate_dims), so int32 never overflows.
void lower_envelope(const std::int32_t* f, int n, std::int32_t* sites, std::int32_t* starts, std::int32_t* out) {
  int k = -1;
  for (int u = 0; u < n; ++u) {
    const std::int32_t fu = f[u];
    if (fu == kNoSite) continue;
    // Drop the parabolas that u beats at their first cell: they are then beaten everywhere to the right too.
    while (k >= 0) {
      const std::int32_t v = sites[k];
      const std::int32_t s = starts[k];
      if ((s - v) * (s - v) + f[v] <= (s - u) * (s - u) + fu) break;
      --k;
    }
    if (k < 0) {
      k = 0;
      sites[0] = u;
      starts[0] = 0;
      continue;
    }
    const std::int32_t v = sites[k];
    // u is strictly lower than v for x > (u^2 - v^2 + f[u] - f[v]) / (2 (u - v)). The loop above guarantees that
    // quotient is >= starts[k] >= 0, so integer division is the floor.
    const std::int32_t first = (u * u - v * v + fu - f[v]) / (2 * (u - v)) + 1;
    if (first < n) {
      ++k;
      sites[k] = u;
      starts[k] = first;
    }
  }
  if (k < 0) {
    std::fill(out, out + n, kNoSite);
    return;
  }
  for (int x = n - 1; x >= 0; --x) {
    const std::int32_t v = sites[k];
    out[x] = (x - v) * (x - v) + f[v];
    if (x == starts[k]) --k;
  }
}

// Runs the 1D pass on every line of the volume along one axis: lines of n cells, stride apart; the first cells of
// the lines are given by (a, b) -> a * a_step + b * b_step for a < a_count, b < b_count. Lines along y and z are
// gathered into the scratch line (the volume is x-fastest); consecutive lines are neighbours in x, so the cache lines
// a gather touches are reused by the next few lines.
void pass_along(float* volume, int n, std::size_t stride, int a_count, std::size_t a_step, int b_count,
                std::size_t b_step, EdtScratch& scratch) {
  std::int32_t* f = scratch.line_f.data();
  std::int32_t* out = scratch.line_out.data();
  for (int b = 0; b < b_count; ++b) {
    for (int a = 0; a < a_count; ++a) {
      float* line = volume + static_cast<std::size_t>(a) * a_step + static_cast<std::size_t>(b) * b_step;
      bool any_site = false;
      for (int i = 0; i < n; ++i) {
        f[i] = from_float(line[static_cast<std::size_t>(i) * stride]);
        any_site = any_site || f[i] != kNoSite;
      }
      if (!any_site) continue;  // stays +inf
      lower_envelope(f, n, scratch.sites.data(), scratch.starts.data(), out);
      for (int i = 0; i < n; ++i) line[static_cast<std::size_t>(i) * stride] = to_float(out[i]);
    }
  }
}

}  // namespace

Status validate_dims(const GridDims& dims) {
  if (dims.nx < 1 || dims.ny < 1 || dims.nz < 1) {
    return make_error("distance map: grid dimensions must be >= 1 cell on every axis, got " + std::to_string(dims.nx) +
                      " x " + std::to_string(dims.ny) + " x " + std::to_string(dims.nz));
  }
  if (!(dims.resolution_m > 0.0) || !std::isfinite(dims.resolution_m)) {
    return make_error("distance map: grid resolution must be a positive number of metres, got " +
                      std::to_string(dims.resolution_m));
  }
  // Each axis alone must keep its squared length below the bound before the three are summed: three squares of
  // axes near INT_MAX would overflow std::int64_t (found by fuzz_template on a header declaring such a grid).
  const auto sq = [](int n) { return static_cast<std::int64_t>(n - 1) * (n - 1); };
  const bool axis_too_long = sq(dims.nx) >= kMaxExactSquaredCells || sq(dims.ny) >= kMaxExactSquaredCells ||
                             sq(dims.nz) >= kMaxExactSquaredCells;
  if (axis_too_long || sq(dims.nx) + sq(dims.ny) + sq(dims.nz) >= kMaxExactSquaredCells) {
    return make_error("distance map: grid of " + std::to_string(dims.nx) + " x " + std::to_string(dims.ny) + " x " +
                      std::to_string(dims.nz) +
                      " cells is too large for an exact transform (squared diagonal must stay below 2^24 cells^2); "
                      "use a coarser resolution");
  }
  return {};
}

EdtScratch::EdtScratch(const GridDims& dims) {
  if (!validate_dims(dims)) return;  // fits() reports false; edt_squared refuses
  max_line = std::max({dims.nx, dims.ny, dims.nz});
  plane_cells = static_cast<std::size_t>(dims.nx) * static_cast<std::size_t>(dims.ny);
  const auto n = static_cast<std::size_t>(max_line);
  line_f.resize(n);
  line_out.resize(n);
  sites.resize(n);
  starts.resize(n);
}

bool EdtScratch::fits(const GridDims& dims) const {
  return max_line >= std::max({dims.nx, dims.ny, dims.nz}) &&
         plane_cells >= static_cast<std::size_t>(dims.nx) * static_cast<std::size_t>(dims.ny);
}

Status edt_squared(const std::uint8_t* occupied, const GridDims& dims, EdtScratch& scratch, float* out_d2_cells) {
  if (Status valid = validate_dims(dims); !valid) return valid;
  if (!scratch.fits(dims)) return make_error("distance map: scratch buffers were sized for a smaller grid");
  if (occupied == nullptr || out_d2_cells == nullptr) return make_error("distance map: null grid or output buffer");

  const int nx = dims.nx;
  const int ny = dims.ny;
  const int nz = dims.nz;
  const auto row = static_cast<std::size_t>(nx);
  const std::size_t plane = row * static_cast<std::size_t>(ny);

  // Along x, straight from the occupancy: occupied cells are sites at height 0.
  std::int32_t* f = scratch.line_f.data();
  std::int32_t* out = scratch.line_out.data();
  for (int z = 0; z < nz; ++z) {
    for (int y = 0; y < ny; ++y) {
      const std::size_t first = dims.index(0, y, z);
      for (int x = 0; x < nx; ++x) f[x] = occupied[first + static_cast<std::size_t>(x)] != 0 ? 0 : kNoSite;
      lower_envelope(f, nx, scratch.sites.data(), scratch.starts.data(), out);
      for (int x = 0; x < nx; ++x) out_d2_cells[first + static_cast<std::size_t>(x)] = to_float(out[x]);
    }
  }
  // Then along y and z on the partial squared distances (the minimum separates over the axes).
  pass_along(out_d2_cells, ny, row, nx, 1, nz, plane, scratch);
  pass_along(out_d2_cells, nz, plane, nx, 1, ny, row, scratch);
  return {};
}

void distance_from_squared(const GridDims& dims, float* d2_cells_to_distance_m) {
  const auto res = static_cast<float>(dims.resolution_m);
  const std::size_t count = dims.cell_count();
  for (std::size_t i = 0; i < count; ++i) d2_cells_to_distance_m[i] = std::sqrt(d2_cells_to_distance_m[i]) * res;
}

BrickGrid::BrickGrid(const GridDims& dims) {
  const int n[3] = {dims.nx, dims.ny, dims.nz};
  brick_count_ = 1;
  for (int a = 0; a < 3; ++a) {
    count_[a] = (std::max(n[a], 0) + kBrickEdge - 1) >> kBrickShift;
    brick_count_ *= static_cast<std::size_t>(count_[a]);
  }
}

DistanceMapView::DistanceMapView(const GridDims& dims, const Eigen::Vector3d& origin_m, const SparseMapData& data)
    : dims_(dims),
      origin_m_(origin_m),
      bricks_(dims),
      data_(data),
      inv_resolution_(1.0 / dims.resolution_m),
      fine_grad_scale_(kDistanceUnitM / dims.resolution_m) {
  const int n[3] = {dims.nx, dims.ny, dims.nz};
  for (int a = 0; a < 3; ++a) {
    offset_[a] = origin_m[a] * inv_resolution_ + 0.5;
    max_coord_[a] = n[a] - 1;
    max_base_[a] = std::max(n[a] - 2, 0);
    step_[a] = n[a] > 1 ? 1 : 0;
  }
}

MapSample DistanceMapView::coarse_sample(const double c[3]) const {
  // Node b of an axis sits at the centre of brick b: cell coordinate 8 b + 3.5.
  constexpr double kNodeOffset = 0.5 * (BrickGrid::kBrickEdge - 1);
  constexpr double kInvEdge = 1.0 / BrickGrid::kBrickEdge;
  double t[3];
  std::size_t part[3][2];
  bool
      sloped[3];  // false where the field is flat along the axis: one node, or clamped before the first / past the last
  std::size_t stride = 1;
  for (int a = 0; a < 3; ++a) {
    const int nodes = bricks_.count(a);
    const double unclamped = (c[a] - kNodeOffset) * kInvEdge;
    const double q = std::clamp(unclamped, 0.0, static_cast<double>(nodes - 1));
    sloped[a] = nodes > 1 && q == unclamped;
    const int lo = std::min(static_cast<int>(q), std::max(nodes - 2, 0));
    const int hi = std::min(lo + 1, nodes - 1);
    t[a] = q - lo;
    part[a][0] = static_cast<std::size_t>(lo) * stride;
    part[a][1] = static_cast<std::size_t>(hi) * stride;
    stride *= static_cast<std::size_t>(nodes);
  }
  double v[8];
  for (int k = 0; k < 2; ++k)
    for (int j = 0; j < 2; ++j)
      for (int i = 0; i < 2; ++i) v[i + 2 * j + 4 * k] = data_.coarse[part[0][i] + part[1][j] + part[2][k]];
  const Trilinear i = trilinear(v, t);
  const double grad_scale = fine_grad_scale_ * kInvEdge;
  return {i.value * kDistanceUnitM, sloped[0] ? i.slope_x * grad_scale : 0.0, sloped[1] ? i.slope_y * grad_scale : 0.0,
          sloped[2] ? i.slope_z * grad_scale : 0.0, false};
}

double DistanceMapView::cell_distance_m(int x, int y, int z) const {
  const std::uint8_t q = fine(x, y, z);
  if (q != kFineFar) return q * kDistanceUnitM;
  const double c[3] = {static_cast<double>(x), static_cast<double>(y), static_cast<double>(z)};
  return coarse_sample(c).distance_m;
}

Status build_distance_map(const std::uint8_t* occupied, const GridDims& dims, const Eigen::Vector3d& origin_m,
                          double band_m, EdtScratch& scratch, float* work_cells, DistanceMap& out) {
  if (!origin_m.allFinite()) return make_error("distance map: grid origin must be finite");
  if (!(band_m > 0.0 && band_m <= kMaxFineDistanceM)) {
    return make_error("distance map: band must be in (0, " + std::to_string(kMaxFineDistanceM) + "] m, got " +
                      std::to_string(band_m));
  }
  if (Status transformed = edt_squared(occupied, dims, scratch, work_cells); !transformed) return transformed;
  distance_from_squared(dims, work_cells);

  const BrickGrid grid(dims);
  const int n[3] = {dims.nx, dims.ny, dims.nz};
  constexpr int kEdge = BrickGrid::kBrickEdge;
  // The cells of brick (bx, by, bz) that lie inside the grid, as [lo, hi) per axis.
  const auto span_of = [&n](int axis, int b) { return std::pair{b * kEdge, std::min((b + 1) * kEdge, n[axis])}; };

  out.dims_ = dims;
  out.origin_m_ = origin_m;
  out.band_m_ = band_m;
  out.has_surface_ = !std::isinf(work_cells[0]);
  out.brick_table_.assign(grid.brick_count(), kAbsentBrick);
  out.coarse_.assign(grid.brick_count(), kCoarseSaturated);
  out.bricks_.clear();
  std::size_t stored = 0;
  for (int bz = 0; bz < grid.count(2); ++bz) {
    const auto [z0, z1] = span_of(2, bz);
    for (int by = 0; by < grid.count(1); ++by) {
      const auto [y0, y1] = span_of(1, by);
      for (int bx = 0; bx < grid.count(0); ++bx) {
        const auto [x0, x1] = span_of(0, bx);
        const std::size_t b = grid.brick_index(bx, by, bz);
        // Coarse node: the mean of the brick's 8 central cells (clamped into the grid for a partial brick).
        double sum = 0.0;
        for (int k = 0; k < 2; ++k)
          for (int j = 0; j < 2; ++j)
            for (int i = 0; i < 2; ++i) {
              const int x = std::min(bx * kEdge + kEdge / 2 - 1 + i, dims.nx - 1);
              const int y = std::min(by * kEdge + kEdge / 2 - 1 + j, dims.ny - 1);
              const int z = std::min(bz * kEdge + kEdge / 2 - 1 + k, dims.nz - 1);
              sum += work_cells[dims.index(x, y, z)];
            }
        out.coarse_[b] = quantize_coarse(sum / 8.0);
        float nearest = std::numeric_limits<float>::infinity();
        for (int z = z0; z < z1; ++z)
          for (int y = y0; y < y1; ++y)
            for (int x = x0; x < x1; ++x) nearest = std::min(nearest, work_cells[dims.index(x, y, z)]);
        if (!(nearest <= band_m)) continue;
        if (stored == kMaxStoredBricks) {
          return make_error("distance map: more than " + std::to_string(kMaxStoredBricks) +
                            " bricks lie within the band of " + std::to_string(band_m) +
                            " m; use a coarser grid or a narrower band");
        }
        out.brick_table_[b] = static_cast<std::uint16_t>(stored);
        out.bricks_.resize((stored + 1) * BrickGrid::kBrickCells, kFineFar);
        std::uint8_t* cells = out.bricks_.data() + stored * BrickGrid::kBrickCells;
        for (int z = z0; z < z1; ++z)
          for (int y = y0; y < y1; ++y)
            for (int x = x0; x < x1; ++x) {
              cells[BrickGrid::in_brick(x, y, z)] = quantize_fine(work_cells[dims.index(x, y, z)]);
            }
        ++stored;
      }
    }
  }
  return {};
}

}  // namespace cellsight::algo
