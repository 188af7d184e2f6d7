// Exact 3D Euclidean distance transform of the occupancy grid and the sparse distance map Perfect Match samples
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

// --- Sparse map (what a template stores and Perfect Match reads) ----------------------------------------------------
//
// Perfect Match reads the distance near the template's surface: its fine fit saturates a few centimetres out
// (fit_lc_m 10 mm), its coarse level and the cascade's error need no more than a smooth far field, and the pose search
// spans +-50 mm / +-5 deg. So a template keeps the exact distance only in bricks of 8 x 8 x 8 cells that lie within a
// band of its surface, and a coarse field (one node per brick) everywhere:
//  - fine bricks: one byte per cell, the distance in kDistanceUnitM (0.1 mm; rounding costs at most 0.05 mm, 2 % of a
//    2.2 mm cell) up to kMaxFineDistanceM (25.4 mm), kFineFar beyond. A brick is stored when its nearest cell lies
//    within the band (TemplateBuildParams::band_m, 17.6 mm by default), so every cell within the band is exact;
//  - a brick table (uint16 per brick of the grid: the stored brick's number, or kAbsentBrick);
//  - the coarse field: uint16 per brick, the mean distance of the brick's 8 central cells, taken as the distance at
//    the brick's centre.
// Measured on the demo's templates (296 x 500 x 182 cells, 53 613 bricks): 3 567 / 3 917 bricks within 17.6 mm of
// bracket_l / chamfered_plate, 1.8 / 2.0 MB of fine cells against 157 MB for the full 6-byte grid of version 1.
// The x/y gradient is the derivative of the same trilinear interpolant that gives the distance, so RPROP follows the
// slope of the very cost it evaluates (thesis eq. 2.56-2.60 differentiate DistMap itself); no gradient is stored.
// tests/test_distance_map.cpp compares distances with brute force, tests/bench/bench_perfect_match.cpp the poses.

inline constexpr double kDistanceUnitM = 1e-4;
inline constexpr std::uint8_t kFineFar = std::numeric_limits<std::uint8_t>::max();
inline constexpr double kMaxFineDistanceM = (kFineFar - 1) * kDistanceUnitM;
inline constexpr std::uint16_t kCoarseSaturated = std::numeric_limits<std::uint16_t>::max();
inline constexpr double kMaxCoarseDistanceM = kCoarseSaturated * kDistanceUnitM;
inline constexpr std::uint16_t kAbsentBrick = std::numeric_limits<std::uint16_t>::max();
inline constexpr std::size_t kMaxStoredBricks = kAbsentBrick;  // numbers 0 .. kAbsentBrick - 1
// Default band: 8 cells of the default grid. Perfect Match's depth levelling samples up to 2 * level_clip_m + one cell
// (18.2 mm) above and below a point, and the fine fit's cost has lost 95 % of its slope at 25 mm.
inline constexpr double kDefaultBandM = 0.0176;

// Written so that NaN and +inf both come out as "far".
[[nodiscard]] inline std::uint8_t quantize_fine(double distance_m) {
  if (!(distance_m < kMaxFineDistanceM + 0.5 * kDistanceUnitM)) return kFineFar;
  return static_cast<std::uint8_t>(std::lround(std::max(distance_m, 0.0) / kDistanceUnitM));
}
[[nodiscard]] inline std::uint16_t quantize_coarse(double distance_m) {
  if (!(distance_m < kMaxCoarseDistanceM)) return kCoarseSaturated;
  return static_cast<std::uint16_t>(std::lround(std::max(distance_m, 0.0) / kDistanceUnitM));
}

// The grid cut into bricks of 8 x 8 x 8 cells (the last brick of an axis may stick out of the grid); bricks are
// numbered x fastest, then y, then z, and so are the cells inside a brick.
class BrickGrid {
 public:
  static constexpr int kBrickShift = 3;
  static constexpr int kBrickEdge = 1 << kBrickShift;
  static constexpr int kInBrickMask = kBrickEdge - 1;
  static constexpr std::size_t kBrickCells = std::size_t{1} << (3 * kBrickShift);

  BrickGrid() = default;
  explicit BrickGrid(const GridDims& dims);

  [[nodiscard]] int count(int axis) const { return count_[axis]; }
  [[nodiscard]] std::size_t brick_count() const { return brick_count_; }
  [[nodiscard]] std::size_t brick_index(int bx, int by, int bz) const {
    return static_cast<std::size_t>(bx) +
           static_cast<std::size_t>(count_[0]) *
               (static_cast<std::size_t>(by) + static_cast<std::size_t>(count_[1]) * static_cast<std::size_t>(bz));
  }
  // Position of cell (x, y, z) inside its brick.
  [[nodiscard]] static std::size_t in_brick(int x, int y, int z) {
    return static_cast<std::size_t>(x & kInBrickMask) + (static_cast<std::size_t>(y & kInBrickMask) << kBrickShift) +
           (static_cast<std::size_t>(z & kInBrickMask) << (2 * kBrickShift));
  }

 private:
  int count_[3] = {0, 0, 0};
  std::size_t brick_count_ = 0;
};

// The arrays of a sparse map, borrowed (from a DistanceMap or from a memory-mapped template file).
struct SparseMapData {
  const std::uint16_t* brick_table = nullptr;  // BrickGrid::brick_count() entries
  const std::uint16_t* coarse = nullptr;       // BrickGrid::brick_count() entries, kDistanceUnitM
  const std::uint8_t* bricks = nullptr;        // stored_bricks x kBrickCells, kDistanceUnitM or kFineFar
  std::size_t stored_bricks = 0;
};

// What sample() returns: distance to the template surface and dD/dx, dD/dy at the point; fine: read from the fine
// cells (exact within the band), false when from the coarse field.
struct MapSample {
  double distance_m;
  double grad_x;
  double grad_y;
  double grad_z;  // dD/dz: the full pose's depth, tilt and swing (PerfectMatcher::refine); RPROP uses x and y only
  bool fine;
};

// One occupied cell of a template's grid: what the cascade's two-way check rasterises.
struct SurfaceCell {
  std::uint16_t x, y, z;
  friend bool operator==(const SurfaceCell&, const SurfaceCell&) = default;
};
static_assert(sizeof(SurfaceCell) == 6, "SurfaceCell is stored as-is in template files");

// Read-only view of a sparse map. Precomputes what sample() needs so that a sample is a clamp, 8 table and 8 cell
// loads and a few multiply-adds.
class DistanceMapView {
 public:
  DistanceMapView() = default;
  DistanceMapView(const GridDims& dims, const Eigen::Vector3d& origin_m, const SparseMapData& data);

  [[nodiscard]] const GridDims& dims() const { return dims_; }
  [[nodiscard]] const Eigen::Vector3d& origin_m() const { return origin_m_; }
  [[nodiscard]] const BrickGrid& bricks() const { return bricks_; }
  [[nodiscard]] const SparseMapData& data() const { return data_; }
  [[nodiscard]] bool valid() const { return data_.brick_table != nullptr; }

  // The stored value of a cell (kDistanceUnitM), kFineFar when its brick is not stored or it is beyond the fine range.
  [[nodiscard]] std::uint8_t fine(int x, int y, int z) const {
    const std::uint16_t b = data_.brick_table[bricks_.brick_index(
        x >> BrickGrid::kBrickShift, y >> BrickGrid::kBrickShift, z >> BrickGrid::kBrickShift)];
    if (b == kAbsentBrick) return kFineFar;
    return data_.bricks[static_cast<std::size_t>(b) * BrickGrid::kBrickCells + BrickGrid::in_brick(x, y, z)];
  }
  // Distance at a cell centre: the fine value, else the coarse field there.
  [[nodiscard]] double cell_distance_m(int x, int y, int z) const;

  // Distance and gradient at a carrier-frame point (metres). Inside the box of cell centres: the trilinear interpolant
  // of the fine cells when all 8 corners are fine, else of the coarse field; the gradient is the interpolant's
  // derivative. In the outer half cell of the grid: clamped to the border. Beyond the grid box: the clamped value plus
  // the Euclidean distance from the point to the grid box, an upper bound of the true distance that stays continuous
  // and keeps pulling stray points back in; along an axis on which the point lies outside, the gradient is that added
  // distance's derivative (pointing away from the grid). NaN coordinates give a NaN distance (never a wild read).
  [[nodiscard]] inline MapSample sample(double x_m, double y_m, double z_m) const;

 private:
  [[nodiscard]] MapSample coarse_sample(const double c[3]) const;

  GridDims dims_{};
  Eigen::Vector3d origin_m_ = Eigen::Vector3d::Zero();
  BrickGrid bricks_{};
  SparseMapData data_{};
  double inv_resolution_ = 0.0;
  double fine_grad_scale_ = 0.0;           // kDistanceUnitM / resolution: cell value step -> dD/dx
  double offset_[3] = {0.0, 0.0, 0.0};     // origin / resolution + 0.5: point -> continuous cell-centre coordinate
  double max_coord_[3] = {0.0, 0.0, 0.0};  // n - 1
  int max_base_[3] = {0, 0, 0};            // n - 2 (0 when n == 1): last cell that has an upper neighbour
  int step_[3] = {0, 0, 0};                // 1, or 0 when n == 1 (the "upper neighbour" is the cell itself)
};

// Owning sparse map built from an occupancy grid at teach time.
class DistanceMap {
 public:
  DistanceMap() = default;

  [[nodiscard]] const GridDims& dims() const { return dims_; }
  [[nodiscard]] const Eigen::Vector3d& origin_m() const { return origin_m_; }
  [[nodiscard]] const std::vector<std::uint16_t>& brick_table() const { return brick_table_; }
  [[nodiscard]] const std::vector<std::uint16_t>& coarse() const { return coarse_; }
  [[nodiscard]] const std::vector<std::uint8_t>& bricks() const { return bricks_; }
  [[nodiscard]] std::size_t stored_bricks() const { return bricks_.size() / BrickGrid::kBrickCells; }
  [[nodiscard]] double band_m() const { return band_m_; }
  // False when the grid had no occupied cell: no brick is stored and the coarse field is saturated.
  [[nodiscard]] bool has_surface() const { return has_surface_; }
  [[nodiscard]] std::size_t memory_bytes() const {
    return (brick_table_.size() + coarse_.size()) * sizeof(std::uint16_t) + bricks_.size();
  }
  [[nodiscard]] DistanceMapView view() const {
    return {dims_, origin_m_, SparseMapData{brick_table_.data(), coarse_.data(), bricks_.data(), stored_bricks()}};
  }

 private:
  friend Status build_distance_map(const std::uint8_t*, const GridDims&, const Eigen::Vector3d&, double, EdtScratch&,
                                   float*, DistanceMap&);
  GridDims dims_{};
  Eigen::Vector3d origin_m_ = Eigen::Vector3d::Zero();
  std::vector<std::uint16_t> brick_table_;
  std::vector<std::uint16_t> coarse_;
  std::vector<std::uint8_t> bricks_;
  double band_m_ = 0.0;
  bool has_surface_ = false;
};

// Teach time: transform, band selection and quantization into out. work_cells: dims.cell_count() floats of caller
// memory (on return it holds the distances in metres, x-fastest order). band_m: bricks with a cell at most this far
// from the surface are stored (0 < band_m <= kMaxFineDistanceM). Refuses a band that needs more than kMaxStoredBricks.
[[nodiscard]] Status build_distance_map(const std::uint8_t* occupied, const GridDims& dims,
                                        const Eigen::Vector3d& origin_m, double band_m, EdtScratch& scratch,
                                        float* work_cells, DistanceMap& out);

// --- inline sampling -------------------------------------------------------------------------------------------------

// Trilinear interpolation of 8 corner values (corner (i, j, k) at v[i + 2 j + 4 k]) at fractions t, and the
// interpolant's slopes along x, y and z per unit of t. Shared by the fine cells and the coarse field.
struct Trilinear {
  double value, slope_x, slope_y, slope_z;
};
[[nodiscard]] inline Trilinear trilinear(const double v[8], const double t[3]) {
  const double tx = t[0];
  const double ty = t[1];
  const double tz = t[2];
  const double ux = 1.0 - tx;
  const double uy = 1.0 - ty;
  const double uz = 1.0 - tz;
  // Along x first: the four x-edges, then their y-z bilinear mix; the x slope is the mix of the edges' steps.
  const double e00 = ux * v[0] + tx * v[1], e10 = ux * v[2] + tx * v[3];
  const double e01 = ux * v[4] + tx * v[5], e11 = ux * v[6] + tx * v[7];
  const double y0 = uy * e00 + ty * e10;
  const double y1 = uy * e01 + ty * e11;
  return {uz * y0 + tz * y1,
          uz * (uy * (v[1] - v[0]) + ty * (v[3] - v[2])) + tz * (uy * (v[5] - v[4]) + ty * (v[7] - v[6])),
          uz * (e10 - e00) + tz * (e11 - e01), y1 - y0};
}

inline MapSample DistanceMapView::sample(double x_m, double y_m, double z_m) const {
  const double f[3] = {x_m * inv_resolution_ - offset_[0], y_m * inv_resolution_ - offset_[1],
                       z_m * inv_resolution_ - offset_[2]};
  double c[3];
  double t[3];
  int lo[3];
  for (int a = 0; a < 3; ++a) {
    // Written so that NaN clamps to 0 (no undefined float -> int conversion).
    c[a] = f[a] > 0.0 ? (f[a] < max_coord_[a] ? f[a] : max_coord_[a]) : 0.0;
    lo[a] = std::min(static_cast<int>(c[a]), max_base_[a]);
    t[a] = c[a] - lo[a];
  }
  // Table and in-brick parts of the corners' positions, per axis: low corner [0], high corner [1].
  std::size_t table_part[3][2];
  std::size_t cell_part[3][2];
  std::size_t table_stride = 1;
  for (int a = 0; a < 3; ++a) {
    const int hi = lo[a] + step_[a];
    table_part[a][0] = static_cast<std::size_t>(lo[a] >> BrickGrid::kBrickShift) * table_stride;
    table_part[a][1] = static_cast<std::size_t>(hi >> BrickGrid::kBrickShift) * table_stride;
    cell_part[a][0] = static_cast<std::size_t>(lo[a] & BrickGrid::kInBrickMask) << (a * BrickGrid::kBrickShift);
    cell_part[a][1] = static_cast<std::size_t>(hi & BrickGrid::kInBrickMask) << (a * BrickGrid::kBrickShift);
    table_stride *= static_cast<std::size_t>(bricks_.count(a));
  }
  double v[8];  // corner (i, j, k) at v[i + 2 j + 4 k]
  bool fine_ok = true;
  for (int k = 0; k < 2; ++k) {
    for (int j = 0; j < 2; ++j) {
      for (int i = 0; i < 2; ++i) {
        const std::uint16_t b = data_.brick_table[table_part[0][i] + table_part[1][j] + table_part[2][k]];
        std::uint8_t q = kFineFar;
        if (b != kAbsentBrick) {
          q = data_.bricks[static_cast<std::size_t>(b) * BrickGrid::kBrickCells + cell_part[0][i] + cell_part[1][j] +
                           cell_part[2][k]];
        }
        fine_ok = fine_ok && q != kFineFar;
        v[i + 2 * j + 4 * k] = q;
      }
    }
  }
  MapSample s{};
  if (fine_ok) {
    const Trilinear i = trilinear(v, t);
    s.distance_m = i.value * kDistanceUnitM;
    s.grad_x = step_[0] != 0 ? i.slope_x * fine_grad_scale_ : 0.0;
    s.grad_y = step_[1] != 0 ? i.slope_y * fine_grad_scale_ : 0.0;
    s.grad_z = step_[2] != 0 ? i.slope_z * fine_grad_scale_ : 0.0;
    s.fine = true;
  } else {
    s = coarse_sample(c);
  }

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
    if (e[2] != 0.0) s.grad_z = e[2] / excess;
  }
  return s;
}

}  // namespace cellsight::algo
