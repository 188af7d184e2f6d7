// The part's own frame: occupancy centroid, dominant outline direction (mod 90 deg), RANSAC sheet plane.
#include "algo/canonical.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "algo/splitmix.hpp"

namespace cellsight::algo {

namespace {

constexpr std::uint64_t kLevelSeed = 0x5EED5EEDULL;  // fixed: the same scan always maps the same way

struct PlaneFit {
  double a = 0.0, b = 0.0, c = 0.0;  // z = a (x - x0) + b (y - y0) + c
  bool ok = false;
};

// Least squares z = a dx + b dy + c over the sample points within band_m of `prior` (all of them when prior is
// not ok). Centred coordinates keep the 3 x 3 normal equations well conditioned.
PlaneFit least_squares(std::span<const ScanPoint> in, std::span<const std::uint32_t> sample, double x0, double y0,
                       const PlaneFit& prior, double band_m) {
  Eigen::Matrix3d ata = Eigen::Matrix3d::Zero();
  Eigen::Vector3d atz = Eigen::Vector3d::Zero();
  int used = 0;
  for (std::uint32_t i : sample) {
    const ScanPoint& p = in[i];
    const double dx = p.x - x0, dy = p.y - y0;
    if (prior.ok && std::abs(p.z - (prior.a * dx + prior.b * dy + prior.c)) > band_m) continue;
    const Eigen::Vector3d row(dx, dy, 1.0);
    ata += row * row.transpose();
    atz += row * static_cast<double>(p.z);
    ++used;
  }
  PlaneFit fit;
  if (used < 3) return fit;
  const Eigen::Vector3d s = ata.ldlt().solve(atz);
  if (!s.allFinite()) return fit;
  fit = {s.x(), s.y(), s.z(), true};
  return fit;
}

// Thesis 6.4.1.1 in spirit (the carrier's RANSAC, algo/support), for the part's own sheet: the near-vertical plane
// with the largest consensus over the subsample, then least squares on it (twice, the second on the refined band).
PlaneFit fit_sheet(std::span<const ScanPoint> in, std::span<const std::uint32_t> sample, double x0, double y0,
                   const CanonicalParams& params, double& inlier_fraction) {
  PlaneFit best;
  int best_count = -1;
  std::uint64_t state = kLevelSeed;
  const auto n = static_cast<std::uint64_t>(sample.size());
  for (int h = 0; h < params.level_hypotheses && n >= 3; ++h) {
    const ScanPoint& p0 = in[sample[splitmix64(state) % n]];
    const ScanPoint& p1 = in[sample[splitmix64(state) % n]];
    const ScanPoint& p2 = in[sample[splitmix64(state) % n]];
    Eigen::Matrix3d m;
    m << p0.x - x0, p0.y - y0, 1.0, p1.x - x0, p1.y - y0, 1.0, p2.x - x0, p2.y - y0, 1.0;
    const double det = m.determinant();
    if (std::abs(det) < 1e-9) continue;  // collinear triple (three points of one profile)
    const Eigen::Vector3d s = m.inverse() * Eigen::Vector3d(p0.z, p1.z, p2.z);
    if (std::abs(s.x()) > params.max_slope || std::abs(s.y()) > params.max_slope) continue;
    int count = 0;
    for (std::uint32_t i : sample) {
      const ScanPoint& p = in[i];
      count += std::abs(p.z - (s.x() * (p.x - x0) + s.y() * (p.y - y0) + s.z())) <= params.level_band_m ? 1 : 0;
    }
    if (count > best_count) {
      best_count = count;
      best = {s.x(), s.y(), s.z(), true};
    }
  }
  PlaneFit fit = least_squares(in, sample, x0, y0, best, params.level_band_m);
  if (fit.ok) fit = least_squares(in, sample, x0, y0, fit, params.level_band_m);
  if (!fit.ok) fit = least_squares(in, sample, x0, y0, PlaneFit{}, 0.0);  // no consensus: plain least squares
  int inliers = 0;
  for (std::uint32_t i : sample) {
    const ScanPoint& p = in[i];
    inliers += fit.ok && std::abs(p.z - (fit.a * (p.x - x0) + fit.b * (p.y - y0) + fit.c)) <= params.level_band_m;
  }
  inlier_fraction = sample.empty() ? 0.0 : static_cast<double>(inliers) / static_cast<double>(sample.size());
  return fit;
}

}  // namespace

std::string_view to_string(CanonicalStatus status) {
  switch (status) {
    case CanonicalStatus::kOk: return "ok";
    case CanonicalStatus::kEmpty: return "no point inside the grid";
    case CanonicalStatus::kOutputTooSmall: return "output buffer smaller than the scan";
  }
  return "invalid";
}

double canonical_sheet_depth_m(const GridSpec& spec, const CanonicalParams& params) {
  // The middle of a depth cell, so noise around the sheet does not split it over two depth levels.
  return spec.origin_m.z() + (std::floor(params.sheet_depth_fraction * spec.nz) + 0.5) * spec.resolution_m;
}

CanonicalScratch::CanonicalScratch(const GridSpec& spec)
    : mask_(static_cast<std::size_t>(spec.nx) * static_cast<std::size_t>(spec.ny), 0),
      rows_(mask_.size(), 0),
      smooth_(mask_.size(), 0) {
  constexpr std::size_t kSampleCapacity = 1U << 16;
  sample_.reserve(kSampleCapacity);
}

namespace {

struct Box {
  int x0, x1, y0, y1;  // occupied cells, inclusive; empty when x1 < x0
};

// x-y occupancy of the points turned by -turn about (cx, cy): each cell counts once, so centroid and outline follow
// the part's silhouette, not the point density of the scan (profile spacing, dropouts). Sums the cells for the
// centroid.
Box rasterise(std::span<const ScanPoint> in, const GridSpec& spec, double cx, double cy, double turn,
              std::vector<std::uint8_t>& mask, double& cells, double& sum_ix, double& sum_iy) {
  const int nx = spec.nx, ny = spec.ny;
  std::fill(mask.begin(), mask.end(), std::uint8_t{0});
  Box box{nx, -1, ny, -1};
  cells = sum_ix = sum_iy = 0.0;
  const double c = std::cos(-turn), s = std::sin(-turn);
  const double inv = 1.0 / spec.resolution_m;  // a product per point, not a division (it runs 3 x per decision)
  for (const ScanPoint& p : in) {
    const double dx = p.x - cx, dy = p.y - cy;
    const double fx = (cx + c * dx - s * dy - spec.origin_m.x()) * inv;
    const double fy = (cy + s * dx + c * dy - spec.origin_m.y()) * inv;
    if (!(fx >= 0.0 && fy >= 0.0 && fx < nx && fy < ny)) continue;  // also rejects NaN
    const int ix = static_cast<int>(fx), iy = static_cast<int>(fy);
    std::uint8_t& m = mask[static_cast<std::size_t>(iy) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(ix)];
    if (m != 0) continue;
    m = 1;
    cells += 1.0;
    sum_ix += ix;
    sum_iy += iy;
    box = {std::min(box.x0, ix), std::max(box.x1, ix), std::min(box.y0, iy), std::max(box.y1, iy)};
  }
  return box;
}

// Dominant edge direction of the silhouette (outline and holes) modulo 90 deg: the gradient angle phi of the
// box-filtered mask (Sobel), averaged as the vector (cos 4 phi, sin 4 phi) weighted by the gradient magnitude. A
// turned rectangle's four edge families all map onto 4 alpha; round holes average out. The cell staircase biases
// the estimate toward the grid axes by up to ~15 %: the caller iterates on the turned-back mask.
double edge_turn(const std::vector<std::uint8_t>& mask, std::vector<std::uint8_t>& rows,
                 std::vector<std::uint8_t>& smooth, int nx, int ny, const Box& box) {
  constexpr int kMargin = 3;  // box filter + Sobel reach two cells beyond the part; one more for the loop bounds
  const auto at = [nx](int ix, int iy) {
    return static_cast<std::size_t>(iy) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(ix);
  };
  // Cells 1 .. n-2 only, so every neighbour read below stays inside the grid (a part touching the grid's border
  // loses its outermost edge there, which the other edges outweigh).
  const int bx0 = std::max(1, box.x0 - kMargin), bx1 = std::min(nx - 2, box.x1 + kMargin);
  const int by0 = std::max(1, box.y0 - kMargin), by1 = std::min(ny - 2, box.y1 + kMargin);
  if (bx1 < bx0 || by1 < by0) return 0.0;
  // Separable 3 x 3 box sum (0 .. 9): along x into rows, then along y into smooth.
  for (int iy = by0 - 1; iy <= by1 + 1; ++iy) {
    const std::uint8_t* m = &mask[at(0, iy)];
    std::uint8_t* r = &rows[at(0, iy)];
    for (int ix = bx0 - 1; ix <= bx1 + 1; ++ix) {
      r[ix] = static_cast<std::uint8_t>((ix > 0 ? m[ix - 1] : 0) + m[ix] + (ix + 1 < nx ? m[ix + 1] : 0));
    }
  }
  for (int iy = by0; iy <= by1; ++iy) {
    const std::uint8_t* up = &rows[at(0, iy + 1)];
    const std::uint8_t* mid = &rows[at(0, iy)];
    const std::uint8_t* down = &rows[at(0, iy - 1)];
    std::uint8_t* out = &smooth[at(0, iy)];
    for (int ix = bx0 - 1; ix <= bx1 + 1; ++ix) out[ix] = static_cast<std::uint8_t>(up[ix] + mid[ix] + down[ix]);
  }
  double c4 = 0.0, s4 = 0.0;
  for (int iy = by0 + 1; iy < by1; ++iy) {
    const std::uint8_t* up = &smooth[at(0, iy + 1)];
    const std::uint8_t* mid = &smooth[at(0, iy)];
    const std::uint8_t* down = &smooth[at(0, iy - 1)];
    for (int ix = bx0 + 1; ix < bx1; ++ix) {
      const int gx = (up[ix + 1] + 2 * mid[ix + 1] + down[ix + 1]) - (up[ix - 1] + 2 * mid[ix - 1] + down[ix - 1]);
      const int gy = (up[ix - 1] + 2 * up[ix] + up[ix + 1]) - (down[ix - 1] + 2 * down[ix] + down[ix + 1]);
      if (gx == 0 && gy == 0) continue;  // inside the part or outside it: no edge
      const double g2 = static_cast<double>(gx * gx + gy * gy);
      const double cos2 = (gx * gx - gy * gy) / g2, sin2 = 2.0 * gx * gy / g2;
      const double w = std::sqrt(g2);
      c4 += w * (cos2 * cos2 - sin2 * sin2);
      s4 += w * 2.0 * sin2 * cos2;
    }
  }
  return 0.25 * std::atan2(s4, c4);
}

}  // namespace

CanonicalStatus canonicalise(std::span<const ScanPoint> in, const GridSpec& spec, const CanonicalParams& params,
                             CanonicalScratch& scratch, std::span<ScanPoint> out, CanonicalPose& pose) {
  constexpr int kTurnPasses = 2;  // the staircase bias shrinks with the remaining turn: two passes leave < 0.1 deg
  pose = {};
  if (out.size() < in.size()) return CanonicalStatus::kOutputTooSmall;
  double cells = 0.0, sum_ix = 0.0, sum_iy = 0.0;
  Box box = rasterise(in, spec, 0.0, 0.0, 0.0, scratch.mask_, cells, sum_ix, sum_iy);
  if (cells == 0.0) return CanonicalStatus::kEmpty;
  pose.centroid_x_m = spec.origin_m.x() + (sum_ix / cells + 0.5) * spec.resolution_m;
  pose.centroid_y_m = spec.origin_m.y() + (sum_iy / cells + 0.5) * spec.resolution_m;
  double turn = 0.0;
  for (int pass = 0; pass < kTurnPasses; ++pass) {
    if (pass > 0)
      box = rasterise(in, spec, pose.centroid_x_m, pose.centroid_y_m, turn, scratch.mask_, cells, sum_ix, sum_iy);
    turn += edge_turn(scratch.mask_, scratch.rows_, scratch.smooth_, spec.nx, spec.ny, box);
  }
  pose.measured_turn_rad = std::remainder(turn, 0.5 * std::numbers::pi);  // back into (-45, 45] deg
  pose.turn_rad = std::clamp(pose.measured_turn_rad, -params.max_turn_rad, params.max_turn_rad);

  // The sheet plane on an even subsample of the points.
  scratch.sample_.clear();
  const std::size_t capacity =
      std::min(scratch.sample_.capacity(), std::max<std::size_t>(params.level_sample_points, 3));
  const std::size_t stride = std::max<std::size_t>(1, (in.size() + capacity - 1) / capacity);
  for (std::size_t i = 0; i < in.size() && scratch.sample_.size() < capacity; i += stride)
    scratch.sample_.push_back(static_cast<std::uint32_t>(i));  // within the reserved capacity: no allocation
  const PlaneFit sheet =
      fit_sheet(in, scratch.sample_, pose.centroid_x_m, pose.centroid_y_m, params, pose.sheet_inlier_fraction);
  pose.slope_x = sheet.a;
  pose.slope_y = sheet.b;
  pose.offset_m = sheet.c - sheet.a * pose.centroid_x_m - sheet.b * pose.centroid_y_m;

  const double centre_x = spec.origin_m.x() + 0.5 * spec.nx * spec.resolution_m;
  const double centre_y = spec.origin_m.y() + 0.5 * spec.ny * spec.resolution_m;
  const double sheet_z = canonical_sheet_depth_m(spec, params);
  const double c = std::cos(-pose.turn_rad), s = std::sin(-pose.turn_rad);
  for (std::size_t i = 0; i < in.size(); ++i) {
    const ScanPoint& p = in[i];
    const double dx = p.x - pose.centroid_x_m, dy = p.y - pose.centroid_y_m;
    ScanPoint& q = out[i];
    q = p;
    q.x = static_cast<float>(centre_x + c * dx - s * dy);
    q.y = static_cast<float>(centre_y + s * dx + c * dy);
    q.z = static_cast<float>(p.z - (sheet.a * dx + sheet.b * dy + sheet.c) + sheet_z);
  }
  return CanonicalStatus::kOk;
}

}  // namespace cellsight::algo
