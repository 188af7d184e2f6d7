// Exact 3D Euclidean distance transform (separable lower envelope of parabolas) and the gradient maps of Perfect Match.
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

// Visits every cell once with its (dD/dx, dD/dy): sink(linear index, x, y, z, gx, gy). Shared by the float and the
// compact outputs.
template <class Sink>
void for_each_gradient(const float* d, const GridDims& dims, GradientMethod method, EdtScratch& scratch, Sink&& sink) {
  const int nx = dims.nx;
  const int ny = dims.ny;
  const int nz = dims.nz;
  const std::size_t plane_cells = static_cast<std::size_t>(nx) * static_cast<std::size_t>(ny);
  if (std::isinf(d[0])) {
    // The transform is either finite everywhere or +inf everywhere (no occupied cell): no direction to give.
    for (int z = 0; z < nz; ++z)
      for (int y = 0; y < ny; ++y)
        for (int x = 0; x < nx; ++x) sink(dims.index(x, y, z), x, y, z, 0.0, 0.0);
    return;
  }
  const double inv_res = 1.0 / dims.resolution_m;
  float* s = scratch.plane.data();
  for (int z = 0; z < nz; ++z) {
    const float* slice = d + plane_cells * static_cast<std::size_t>(z);
    if (method == GradientMethod::kSobelAveraged) {
      // Eq. 2.52/2.53 average the 2D Sobel of slices z-1, z, z+1; the Sobel is linear, so filter the averaged slice.
      // At the first and last slice the average runs over the slices that exist.
      const int z_lo = std::max(z - 1, 0);
      const int z_hi = std::min(z + 1, nz - 1);
      const float inv_count = 1.0f / static_cast<float>(z_hi - z_lo + 1);
      const float* lo = d + plane_cells * static_cast<std::size_t>(z_lo);
      const float* mid = slice;
      const float* hi = d + plane_cells * static_cast<std::size_t>(z_hi);
      for (std::size_t i = 0; i < plane_cells; ++i) {
        const float sum = (z_lo < z ? lo[i] : 0.0f) + mid[i] + (z_hi > z ? hi[i] : 0.0f);
        s[i] = sum * inv_count;
      }
    }
    for (int y = 0; y < ny; ++y) {
      const int y_lo = std::max(y - 1, 0);
      const int y_hi = std::min(y + 1, ny - 1);
      const double inv_span_y = y_hi > y_lo ? inv_res / (y_hi - y_lo) : 0.0;
      const std::size_t row = static_cast<std::size_t>(nx) * static_cast<std::size_t>(y);
      const std::size_t row_lo = static_cast<std::size_t>(nx) * static_cast<std::size_t>(y_lo);
      const std::size_t row_hi = static_cast<std::size_t>(nx) * static_cast<std::size_t>(y_hi);
      const std::size_t out_row = plane_cells * static_cast<std::size_t>(z) + row;
      for (int x = 0; x < nx; ++x) {
        const int x_lo = std::max(x - 1, 0);
        const int x_hi = std::min(x + 1, nx - 1);
        const double inv_span_x = x_hi > x_lo ? inv_res / (x_hi - x_lo) : 0.0;
        double gx = 0.0;
        double gy = 0.0;
        if (method == GradientMethod::kSobelAveraged) {
          // Eq. 2.50/2.51: H.N/8 and V.N/8 per cell; the [1 2 1] smoothing replicates the border row/column.
          const auto dx = [&](std::size_t r) { return static_cast<double>(s[r + x_hi]) - s[r + x_lo]; };
          const auto dy = [&](int c) { return static_cast<double>(s[row_hi + c]) - s[row_lo + c]; };
          gx = (dx(row_lo) + 2.0 * dx(row) + dx(row_hi)) * 0.25 * inv_span_x;
          gy = (dy(x_lo) + 2.0 * dy(x) + dy(x_hi)) * 0.25 * inv_span_y;
        } else {
          gx = (static_cast<double>(slice[row + x_hi]) - slice[row + x_lo]) * inv_span_x;
          gy = (static_cast<double>(slice[row_hi + x]) - slice[row_lo + x]) * inv_span_y;
        }
        sink(out_row + static_cast<std::size_t>(x), x, y, z, gx, gy);
      }
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
  plane.resize(plane_cells);
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

Status gradients_xy(const float* distance_m, const GridDims& dims, GradientMethod method, EdtScratch& scratch,
                    float* grad_x, float* grad_y) {
  if (Status valid = validate_dims(dims); !valid) return valid;
  if (!scratch.fits(dims)) return make_error("distance map: scratch buffers were sized for a smaller grid");
  if (distance_m == nullptr || grad_x == nullptr || grad_y == nullptr) {
    return make_error("distance map: null distance or gradient buffer");
  }
  for_each_gradient(distance_m, dims, method, scratch, [&](std::size_t i, int, int, int, double gx, double gy) {
    grad_x[i] = static_cast<float>(gx);
    grad_y[i] = static_cast<float>(gy);
  });
  return {};
}

BrickLayout::BrickLayout(const GridDims& dims) {
  const auto bricks = [](int n) {
    const int count = (std::max(n, 0) + kBrickEdge - 1) >> kBrickShift;
    return static_cast<std::size_t>(count);
  };
  constexpr int kBrickCells = kBrickEdge * kBrickEdge * kBrickEdge;
  brick_stride_[0] = kBrickCells;
  brick_stride_[1] = brick_stride_[0] * bricks(dims.nx);
  brick_stride_[2] = brick_stride_[1] * bricks(dims.ny);
  cell_count_ = brick_stride_[2] * bricks(dims.nz);
}

DistanceMapView::DistanceMapView(const GridDims& dims, const Eigen::Vector3d& origin_m, const MapCell* cells)
    : dims_(dims), origin_m_(origin_m), layout_(dims), cells_(cells), inv_resolution_(1.0 / dims.resolution_m) {
  const int n[3] = {dims.nx, dims.ny, dims.nz};
  for (int a = 0; a < 3; ++a) {
    offset_[a] = origin_m[a] * inv_resolution_ + 0.5;
    max_coord_[a] = n[a] - 1;
    max_base_[a] = std::max(n[a] - 2, 0);
    step_[a] = n[a] > 1 ? 1 : 0;
  }
}

Status build_distance_map(const std::uint8_t* occupied, const GridDims& dims, const Eigen::Vector3d& origin_m,
                          GradientMethod method, EdtScratch& scratch, float* work_cells, DistanceMap& out) {
  if (!origin_m.allFinite()) return make_error("distance map: grid origin must be finite");
  if (Status transformed = edt_squared(occupied, dims, scratch, work_cells); !transformed) return transformed;
  distance_from_squared(dims, work_cells);

  const BrickLayout layout(dims);
  out.dims_ = dims;
  out.origin_m_ = origin_m;
  // assign() keeps the capacity: no allocation when rebuilding for the same grid. Padding stays "far, no direction".
  out.cells_.assign(layout.cell_count(), MapCell{kDistanceSaturated, 0, 0});
  out.has_surface_ = !std::isinf(work_cells[0]);
  MapCell* cells = out.cells_.data();
  // Gradients from the float field, not the quantized one: 0.1 mm steps over a 4.4 mm span would cost 2 %.
  for_each_gradient(
      work_cells, dims, method, scratch,
      [cells, work_cells, &layout](std::size_t i, int x, int y, int z, double gx, double gy) {
        cells[layout.index(x, y, z)] = {quantize_distance(work_cells[i]), quantize_gradient(gx), quantize_gradient(gy)};
      });
  return {};
}

}  // namespace cellsight::algo
