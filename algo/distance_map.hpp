// Exact 3D Euclidean distance transform of the occupancy grid and the x/y gradient maps of Perfect Match
// (thesis 2.7.3.1).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "algo/result.hpp"

namespace cellsight::algo {

// Shape of the world occupancy grid (DESIGN.md "Grid"); always from config, never hard-coded.
// Cell (x, y, z) covers [origin + i * resolution, origin + (i + 1) * resolution) on each axis, so its centre is at
// origin + (i + 0.5) * resolution. Storage is x fastest, then y, then z: index = x + nx * (y + ny * z).
// TODO(lead): move to algo/grid.hpp when the grid stage lands; this is the only definition for now.
struct GridDims {
  int nx = 0;
  int ny = 0;
  int nz = 0;
  double resolution_m = 0.0;

  [[nodiscard]] std::size_t cell_count() const {
    return static_cast<std::size_t>(nx) * static_cast<std::size_t>(ny) * static_cast<std::size_t>(nz);
  }
  [[nodiscard]] std::size_t index(int x, int y, int z) const {
    return static_cast<std::size_t>(x) +
           static_cast<std::size_t>(nx) *
               (static_cast<std::size_t>(y) + static_cast<std::size_t>(ny) * static_cast<std::size_t>(z));
  }
};

// Largest squared cell distance the transform may produce must stay exact in float (24-bit mantissa), because the
// volume that carries the passes is float. (nx-1)^2 + (ny-1)^2 + (nz-1)^2 < 2^24 allows e.g. 2000^3 cells.
inline constexpr std::int64_t kMaxExactSquaredCells = std::int64_t{1} << 24;

// Checks sizes, resolution and the exactness bound above; the message says which parameter is wrong.
[[nodiscard]] Status validate_dims(const GridDims& dims);

// Line and plane buffers for the transform and the gradient filters, sized once for one grid shape so that building
// a map allocates nothing. Reuse it for every template of the same grid.
struct EdtScratch {
  explicit EdtScratch(const GridDims& dims);
  [[nodiscard]] bool fits(const GridDims& dims) const;

  int max_line = 0;                    // longest axis, cells
  std::size_t plane_cells = 0;         // nx * ny
  std::vector<std::int32_t> line_f;    // squared distances entering a 1D pass
  std::vector<std::int32_t> line_out;  // squared distances leaving it
  std::vector<std::int32_t> sites;     // lower envelope: parabola apex positions
  std::vector<std::int32_t> starts;    // lower envelope: first cell where each parabola is lowest
  std::vector<float> plane;            // z-averaged slice for the Sobel variant of the gradients
};

// Exact squared Euclidean distance, in cells^2, from every cell centre to the nearest occupied cell centre.
// occupied: dims.cell_count() bytes, non-zero = occupied. out_d2_cells: dims.cell_count() floats; every value is an
// exact integer (see kMaxExactSquaredCells). A grid with no occupied cell at all yields +infinity everywhere.
// Separable lower envelope of parabolas (Felzenszwalb & Huttenlocher 2012, with Meijster's integer separator),
// along x, then y, then z: O(cells), no allocation.
[[nodiscard]] Status edt_squared(const std::uint8_t* occupied, const GridDims& dims, EdtScratch& scratch,
                                 float* out_d2_cells);

// In place: squared cell distances -> distances in metres (sqrt * resolution); +infinity stays +infinity.
void distance_from_squared(const GridDims& dims, float* d2_cells_to_distance_m);

// How the gradient maps are derived from the distance field.
enum class GradientMethod {
  // Thesis eq. 2.47-2.53: 2D Sobel in each z slice, averaged over slices z-1, z, z+1.
  kSobelAveraged,
  // Central difference of the distance field along the axis: estimates the derivative of the very field Perfect
  // Match evaluates (eq. 2.56-2.60 differentiate DistMap itself), without the Sobel's smoothing across y and z.
  // Measured (tests/test_distance_map.cpp asserts, tests/bench/bench_distance_map.cpp prints):
  //  - against the exact gradient of the transform it is the better one: half the component error on a point field
  //    (max 0.19 / r^2 vs 0.58 / r^2, r in cells) and a quarter near the ridges where two surface points are
  //    equally near (xy angle error 0.18 deg rms vs 1.4 deg), because its stencil straddles fewer ridges;
  //  - against the continuous surface a dense voxel surface came from (voxelised sphere, tilted plane) the Sobel
  //    average is better by 20-35 % rms (4.0 vs 6.0 deg on the plane): its smoothing hides the voxel staircase.
  // Which one gives the better pose is for Perfect Match's end-to-end tests to decide; both are stored alike.
  kCentralDifference,
};

// dD/dx and dD/dy (dimensionless, m per m) at every cell centre, in the carrier-frame axes (eq. 2.60 needs exactly
// these; the thesis' masks are written in image-row orientation). At the grid border the difference is one-sided
// and the smoothing replicates the border row. |component| <= 1 because a distance field is 1-Lipschitz.
// A field without any finite value (empty grid) gives zero gradients.
[[nodiscard]] Status gradients_xy(const float* distance_m, const GridDims& dims, GradientMethod method,
                                  EdtScratch& scratch, float* grad_x, float* grad_y);

// --- Compact map (what a template stores and Perfect Match reads) ---------------------------------------------------

// One cell of a stored map: 6 bytes instead of 12 for three floats (296 x 500 x 182 cells: 157 MiB instead of 308).
// The three values of a cell sit together so that a trilinear sample reads each corner from one place.
// distance: units of kDistanceUnitM, saturating at kDistanceSaturated (also the "no occupied cell" value).
// grad_x, grad_y: units of kGradientUnit (|g| <= 1 fits int16 with 3e-5 resolution).
struct MapCell {
  std::uint16_t distance;
  std::int16_t grad_x;
  std::int16_t grad_y;
};
static_assert(sizeof(MapCell) == 6, "MapCell is stored as-is in template files");

// 0.1 mm: rounding costs at most 0.05 mm (2 % of a 2.2 mm cell) and covers 6.55 m, far beyond any grid diagonal
// (1.34 m for the default grid) and the L_c = 0.4 m of eq. 2.56, where a point's cost is already ~1.
inline constexpr double kDistanceUnitM = 1e-4;
inline constexpr std::uint16_t kDistanceSaturated = std::numeric_limits<std::uint16_t>::max();
inline constexpr double kMaxDistanceM = kDistanceSaturated * kDistanceUnitM;
inline constexpr double kGradientScale = 32767.0;
inline constexpr double kGradientUnit = 1.0 / kGradientScale;

[[nodiscard]] inline std::uint16_t quantize_distance(double distance_m) {
  // Written so that NaN and +inf both saturate.
  if (!(distance_m < kMaxDistanceM)) return kDistanceSaturated;
  return static_cast<std::uint16_t>(std::lround(std::max(distance_m, 0.0) / kDistanceUnitM));
}
[[nodiscard]] inline std::int16_t quantize_gradient(double gradient) {
  if (!(gradient == gradient)) return 0;  // NaN: no direction
  return static_cast<std::int16_t>(std::lround(std::clamp(gradient, -1.0, 1.0) * kGradientScale));
}

// Where cell (x, y, z) of a map lives in its cell array: bricks of 8 x 8 x 8 cells (x fastest inside a brick; bricks
// x fastest, then y, then z), the grid padded up to whole bricks (padding cells hold kDistanceSaturated, 0, 0 and
// are never read by sample()). Why not plain x-fastest order: Perfect Match samples a few thousand points per
// iteration, and in x-fastest order the 8 corners of one sample lie on 2-4 different 4 KiB pages (a z step is
// nx * ny * 6 bytes), so those points touch more pages than the TLB holds and every sample walks the page tables.
// One brick is 3 KiB, so a sample's corners usually share one page. tests/bench/bench_distance_map.cpp, 2000 points
// x 500 iterations: 36-125 ns per sample against 107-212 ns for x-fastest order (1.7-3.5x, three runs on a shared,
// loaded machine); uniformly random samples over the whole map are 10-60 % slower (more index arithmetic, no page
// reuse to gain). Costs 2 % padding (296 x 504 x 184 stored cells).
class BrickLayout {
 public:
  static constexpr int kBrickShift = 3;
  static constexpr int kBrickEdge = 1 << kBrickShift;
  static constexpr int kInBrickMask = kBrickEdge - 1;

  BrickLayout() = default;
  explicit BrickLayout(const GridDims& dims);

  // Length of the cell array, padding included.
  [[nodiscard]] std::size_t cell_count() const { return cell_count_; }
  [[nodiscard]] std::size_t index(int x, int y, int z) const { return part_x(x) + part_y(y) + part_z(z); }
  // The index is a sum of one term per axis, so sample() computes 6 terms for its 8 corners.
  [[nodiscard]] std::size_t part_x(int x) const {
    return static_cast<std::size_t>(x >> kBrickShift) * brick_stride_[0] + static_cast<std::size_t>(x & kInBrickMask);
  }
  [[nodiscard]] std::size_t part_y(int y) const {
    return static_cast<std::size_t>(y >> kBrickShift) * brick_stride_[1] +
           static_cast<std::size_t>(y & kInBrickMask) * kBrickEdge;
  }
  [[nodiscard]] std::size_t part_z(int z) const {
    return static_cast<std::size_t>(z >> kBrickShift) * brick_stride_[2] +
           static_cast<std::size_t>(z & kInBrickMask) * kBrickEdge * kBrickEdge;
  }

 private:
  std::size_t brick_stride_[3] = {0, 0, 0};
  std::size_t cell_count_ = 0;
};

// What sample() returns: distance to the template surface and dD/dx, dD/dy at the point.
struct MapSample {
  double distance_m;
  double grad_x;
  double grad_y;
};

// Read-only view of a map: over a DistanceMap, or over cells memory-mapped from a template file (an array of
// BrickLayout(dims).cell_count() MapCells in brick order). Borrows the cells. Precomputes what sample() needs so that
// a sample is a clamp, 8 loads and a few multiply-adds.
class DistanceMapView {
 public:
  DistanceMapView() = default;
  DistanceMapView(const GridDims& dims, const Eigen::Vector3d& origin_m, const MapCell* cells);

  [[nodiscard]] const GridDims& dims() const { return dims_; }
  [[nodiscard]] const Eigen::Vector3d& origin_m() const { return origin_m_; }
  [[nodiscard]] const BrickLayout& layout() const { return layout_; }
  [[nodiscard]] const MapCell* cells() const { return cells_; }
  [[nodiscard]] const MapCell& cell(int x, int y, int z) const { return cells_[layout_.index(x, y, z)]; }

  // Trilinear interpolation of distance and both gradients at a carrier-frame point (metres).
  // Inside the box of cell centres: the trilinear interpolant. In the outer half cell of the grid: the border value
  // (clamp to edge). Beyond the grid box: the clamped value plus the Euclidean distance from the point to the grid
  // box, an upper bound of the true distance that stays continuous and keeps pulling stray points back in; along an
  // axis on which the point lies outside, the gradient is that added distance's derivative (pointing away from the
  // grid), on the other axes the clamped map gradient. NaN coordinates give a NaN distance (never a wild read).
  [[nodiscard]] inline MapSample sample(double x_m, double y_m, double z_m) const;

 private:
  GridDims dims_{};
  Eigen::Vector3d origin_m_ = Eigen::Vector3d::Zero();
  BrickLayout layout_{};
  const MapCell* cells_ = nullptr;
  double inv_resolution_ = 0.0;
  double offset_[3] = {0.0, 0.0, 0.0};     // origin / resolution + 0.5: point -> continuous cell-centre coordinate
  double max_coord_[3] = {0.0, 0.0, 0.0};  // n - 1
  int max_base_[3] = {0, 0, 0};            // n - 2 (0 when n == 1): last cell that has an upper neighbour
  int step_[3] = {0, 0, 0};                // 1, or 0 when n == 1 (the "upper neighbour" is the cell itself)
};

// Owning compact map built from an occupancy grid at teach time.
class DistanceMap {
 public:
  DistanceMap() = default;

  [[nodiscard]] const GridDims& dims() const { return dims_; }
  [[nodiscard]] const Eigen::Vector3d& origin_m() const { return origin_m_; }
  // In BrickLayout order, padding included: what a template file stores.
  [[nodiscard]] const std::vector<MapCell>& cells() const { return cells_; }
  // False when the grid had no occupied cell: every distance is kDistanceSaturated and every gradient 0.
  [[nodiscard]] bool has_surface() const { return has_surface_; }
  [[nodiscard]] std::size_t memory_bytes() const { return cells_.size() * sizeof(MapCell); }
  [[nodiscard]] DistanceMapView view() const { return {dims_, origin_m_, cells_.data()}; }

 private:
  friend Status build_distance_map(const std::uint8_t*, const GridDims&, const Eigen::Vector3d&, GradientMethod,
                                   EdtScratch&, float*, DistanceMap&);
  GridDims dims_{};
  Eigen::Vector3d origin_m_ = Eigen::Vector3d::Zero();
  std::vector<MapCell> cells_;
  bool has_surface_ = false;
};

// Teach time: transform, gradients and quantization into out. work_cells: dims.cell_count() floats of caller memory
// (the float distance field lives there; on return it holds the distances in metres, x-fastest order). out's
// storage is reused when the shape already fits, so rebuilding for the same grid allocates nothing.
[[nodiscard]] Status build_distance_map(const std::uint8_t* occupied, const GridDims& dims,
                                        const Eigen::Vector3d& origin_m, GradientMethod method, EdtScratch& scratch,
                                        float* work_cells, DistanceMap& out);

// --- inline sampling -------------------------------------------------------------------------------------------------

inline MapSample DistanceMapView::sample(double x_m, double y_m, double z_m) const {
  const double f[3] = {x_m * inv_resolution_ - offset_[0], y_m * inv_resolution_ - offset_[1],
                       z_m * inv_resolution_ - offset_[2]};
  double t[3];
  int lo[3];
  for (int a = 0; a < 3; ++a) {
    // Written so that NaN clamps to 0 (no undefined float -> int conversion).
    const double c = f[a] > 0.0 ? (f[a] < max_coord_[a] ? f[a] : max_coord_[a]) : 0.0;
    lo[a] = std::min(static_cast<int>(c), max_base_[a]);
    t[a] = c - lo[a];
  }
  const std::size_t x0 = layout_.part_x(lo[0]);
  const std::size_t x1 = layout_.part_x(lo[0] + step_[0]);
  const std::size_t y0 = layout_.part_y(lo[1]);
  const std::size_t y1 = layout_.part_y(lo[1] + step_[1]);
  const std::size_t z0 = layout_.part_z(lo[2]);
  const std::size_t z1 = layout_.part_z(lo[2] + step_[2]);
  const MapCell& c000 = cells_[x0 + y0 + z0];
  const MapCell& c100 = cells_[x1 + y0 + z0];
  const MapCell& c010 = cells_[x0 + y1 + z0];
  const MapCell& c110 = cells_[x1 + y1 + z0];
  const MapCell& c001 = cells_[x0 + y0 + z1];
  const MapCell& c101 = cells_[x1 + y0 + z1];
  const MapCell& c011 = cells_[x0 + y1 + z1];
  const MapCell& c111 = cells_[x1 + y1 + z1];
  const double tx = t[0];
  const double ty = t[1];
  const double tz = t[2];
  const double ux = 1.0 - tx;
  const double uy = 1.0 - ty;
  const double uz = 1.0 - tz;
  const double w000 = ux * uy * uz;
  const double w100 = tx * uy * uz;
  const double w010 = ux * ty * uz;
  const double w110 = tx * ty * uz;
  const double w001 = ux * uy * tz;
  const double w101 = tx * uy * tz;
  const double w011 = ux * ty * tz;
  const double w111 = tx * ty * tz;
  const auto mix = [&](auto member) {
    return w000 * (c000.*member) + w100 * (c100.*member) + w010 * (c010.*member) + w110 * (c110.*member) +
           w001 * (c001.*member) + w101 * (c101.*member) + w011 * (c011.*member) + w111 * (c111.*member);
  };
  MapSample s{mix(&MapCell::distance) * kDistanceUnitM, mix(&MapCell::grad_x) * kGradientUnit,
              mix(&MapCell::grad_y) * kGradientUnit};

  // Beyond the grid box (more than half a cell past the last centre on some axis): add the distance to the box.
  // Rare in Perfect Match, so it stays off the common path.
  double e[3];
  bool outside = false;
  for (int a = 0; a < 3; ++a) {
    const double low = -0.5;
    const double high = max_coord_[a] + 0.5;
    // Ordered so that NaN lands in the last branch and propagates into the distance.
    e[a] = f[a] >= low ? (f[a] <= high ? 0.0 : f[a] - high) : f[a] - low;
    outside = outside || e[a] != 0.0;
  }
  if (outside) {
    const double excess = std::sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);  // cells; NaN propagates
    s.distance_m += excess * dims_.resolution_m;
    if (e[0] != 0.0) s.grad_x = e[0] / excess;
    if (e[1] != 0.0) s.grad_y = e[1] / excess;
  }
  return s;
}

}  // namespace cellsight::algo
