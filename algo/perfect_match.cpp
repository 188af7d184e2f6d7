// Perfect Match (thesis 2.7.3): robust cost of a scan against a template's distance map and its RPROP minimisation.
#include "algo/perfect_match.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

namespace cellsight::algo {

namespace {

// One RPROP parameter (x, y or theta): its step and the previous derivative.
struct RpropState {
  double step = 0.0;
  double step_min = 0.0;
  double step_max = 0.0;
  double previous_grad = 0.0;
};

// iRprop- (Igel & Huesken 2000), the usual reading of thesis eq. 2.67-2.70: the step grows while the derivative
// keeps its sign and shrinks when it flips; after a flip the parameter stays put for one iteration (and the stored
// derivative is zeroed so the next one neither grows nor shrinks the step). The thesis words the test as a
// difference of successive derivatives; RPROP (Riedmiller & Braun 1993) tests the sign of their product, which is
// what "passed a local minimum" means.
[[nodiscard]] double rprop_update(RpropState& s, double grad, double eta_plus, double eta_minus) {
  const double product = grad * s.previous_grad;
  if (product > 0.0) {
    s.step = std::min(s.step * eta_plus, s.step_max);
  } else if (product < 0.0) {
    s.step = std::max(s.step * eta_minus, s.step_min);
    s.previous_grad = 0.0;
    return 0.0;
  }
  s.previous_grad = grad;
  if (grad > 0.0) return -s.step;  // thesis eq. 2.69
  if (grad < 0.0) return s.step;   // thesis eq. 2.70
  return 0.0;
}

constexpr int kMinFeatureBins = 64;
constexpr int kMinEdgeNeighbours = 2;
// When the coarse level hands over, its steps may have shrunk to their minimum: the fine level restarts them at
// this fraction of the initial step (the coarse pose is close, but not within a step minimum).
constexpr double kFineRestartStepFraction = 0.125;

// A scan point in the template frame: p_t = c + R(-theta)(p_scan - c - t) (inverse of eq. 2.55 with DESIGN.md's
// centre c); r = p_t - c, and the levelled depth z - depth(r).
struct TemplateFrame {
  double cos_t, sin_t, ox, oy;
  TemplateFrame(const Eigen::Vector2d& c, const PlanarPose& pose)
      : cos_t(std::cos(pose.theta_rad)), sin_t(std::sin(pose.theta_rad)), ox(c.x() + pose.x_m), oy(c.y() + pose.y_m) {}
  void map(const Eigen::Vector3f& p, const DepthPlane& depth, double& rx, double& ry, double& z) const {
    const double qx = static_cast<double>(p.x()) - ox;
    const double qy = static_cast<double>(p.y()) - oy;
    rx = cos_t * qx + sin_t * qy;
    ry = -sin_t * qx + cos_t * qy;
    z = static_cast<double>(p.z()) - (depth.offset_m + depth.slope_x * rx + depth.slope_y * ry);
  }
};
// depth_plane(): a point enters when its nearest surface lies above or below it (|dd/dz| >= 0.6 over samples that
// straddle it, x-y slope of the distance over one cell <= 0.5), at least 30 such points, spread over the part, and
// the normal equations are well conditioned.
constexpr double kLevelMinDepthGradient = 0.6;
constexpr double kLevelMaxSideGradient = 0.5;
constexpr int kLevelMinPoints = 30;
constexpr double kLevelMinRcond = 1e-9;
constexpr double kLevelMinSpread = 0.25;
// A part tilted several degrees against its template leaves only a strip across the line where the two planes meet
// within level_clip_m (shipped catalogue under `mixed`, plate_4h s990002: 5 deg about y, 34 % of the points in a strip
// of 0.24 of the part's x spread, no levelling, a Perfect Match error 1.8 x its limit at the right pose). A strip of
// at least kLevelStripSpread is levelled by as a step only: the fit is made again from it, at most kLevelStripRounds
// times, and only a fit over the part is kept.
constexpr double kLevelStripSpread = 0.1;
constexpr int kLevelStripRounds = 3;
constexpr double kLevelMinChangeCells = 0.25;

double variance_of(const Eigen::Matrix3d& m, int k) {  // of X (k = 1) or Y (k = 2), m: sums of v v^T, v = (1, X, Y)
  const double mean = m(0, k) / m(0, 0);
  return m(k, k) / m(0, 0) - mean * mean;
}

// Whether the points summed in `fit` (sums of v v^T, v = (1, X, Y)) spread over at least kLevelMinSpread of the
// standard deviation in X and in Y of those in `all`: a plane fitted to a strip of the part is extrapolated over the
// rest, where its slope across the strip is unfounded.
bool spans_part(const Eigen::Matrix3d& fit, const Eigen::Matrix3d& all, double spread = kLevelMinSpread) {
  const double f2 = spread * spread;
  return fit(0, 0) > 0.0 && all(0, 0) > 0.0 && variance_of(fit, 1) >= f2 * variance_of(all, 1) &&
         variance_of(fit, 2) >= f2 * variance_of(all, 2);
}

// The largest change a plane p (offset, slope X, slope Y) makes over the points summed in `all`: at their mean and
// two standard deviations out in X and Y.
double largest_change(const Eigen::Vector3d& p, const Eigen::Matrix3d& all) {
  const double mx = all(0, 1) / all(0, 0);
  const double my = all(0, 2) / all(0, 0);
  return std::abs(p[0] + p[1] * mx + p[2] * my) +
         2.0 * (std::abs(p[1]) * std::sqrt(std::max(variance_of(all, 1), 0.0)) +
                std::abs(p[2]) * std::sqrt(std::max(variance_of(all, 2), 0.0)));
}

// `prior` with a fit of what remained after it (offset, slope X, slope Y) added, from `points` points.
DepthPlane plus_fit(const DepthPlane& prior, const Eigen::Vector3d& fit, int points) {
  return {prior.offset_m + fit[0], prior.slope_x + fit[1], prior.slope_y + fit[2], points};
}

}  // namespace

Eigen::Vector2d centroid_xy_m(std::span<const ScanPoint> points) {
  double sx = 0.0;
  double sy = 0.0;
  std::size_t n = 0;
  for (const ScanPoint& p : points) {
    if (!finite_point(p)) continue;
    sx += p.x;
    sy += p.y;
    ++n;
  }
  if (n == 0) return Eigen::Vector2d::Zero();
  return {sx / static_cast<double>(n), sy / static_cast<double>(n)};
}

PerfectMatcher::PerfectMatcher(const PerfectMatchParams& params) : params_(params) {
  params_.max_points = std::max(params_.max_points, 1);
  params_.max_iterations = std::max(params_.max_iterations, 0);
  params_.informative_fraction = std::clamp(params_.informative_fraction, 0.0, 1.0);
  params_.max_feature_bins = std::max(params_.max_feature_bins, kMinFeatureBins);
  if (!(params_.feature_bin_m > 0.0)) params_.feature_bin_m = PerfectMatchParams{}.feature_bin_m;
  params_.step_max_m = std::max(params_.step_max_m, params_.step_min_m);
  params_.step_max_rad = std::max(params_.step_max_rad, params_.step_min_rad);
  params_.step_initial_m = std::clamp(params_.step_initial_m, params_.step_min_m, params_.step_max_m);
  params_.step_initial_rad = std::clamp(params_.step_initial_rad, params_.step_min_rad, params_.step_max_rad);
  const auto n = static_cast<std::size_t>(params_.max_points);
  points_.resize(n);
  level_.resize(n);
  picked_.resize(n);
  const auto bins = static_cast<std::size_t>(params_.max_feature_bins);
  bin_count_.resize(bins);
  bin_depth_.resize(bins);
  bin_informative_.resize(bins);
}

namespace {

// The finite points of a scan: how many, their x-y sums and their x-y bounds.
struct ScanFootprint {
  std::size_t finite = 0;
  double sx = 0.0;
  double sy = 0.0;
  double min_x = 0.0;
  double max_x = 0.0;
  double min_y = 0.0;
  double max_y = 0.0;
};

ScanFootprint measure_footprint(std::span<const ScanPoint> points) {
  ScanFootprint f;
  for (const ScanPoint& p : points) {
    if (!finite_point(p)) continue;
    if (f.finite == 0) {
      f.min_x = f.max_x = p.x;
      f.min_y = f.max_y = p.y;
    }
    f.min_x = std::min(f.min_x, static_cast<double>(p.x));
    f.max_x = std::max(f.max_x, static_cast<double>(p.x));
    f.min_y = std::min(f.min_y, static_cast<double>(p.y));
    f.max_y = std::max(f.max_y, static_cast<double>(p.y));
    f.sx += p.x;
    f.sy += p.y;
    ++f.finite;
  }
  return f;
}

}  // namespace

// x-y bins over the footprint with one empty bin of margin all round, so every occupied bin has 8 neighbours.
struct PerfectMatcher::BinGrid {
  double min_x = 0.0;
  double min_y = 0.0;
  double inv_bin = 0.0;
  int nbx = 0;
  int nby = 0;

  // Bins of feature_bin_m, made coarser until the footprint fits in max_feature_bins.
  static BinGrid over(const ScanFootprint& f, const PerfectMatchParams& params) {
    double bin_m = params.feature_bin_m;
    const auto capacity = static_cast<double>(params.max_feature_bins);
    while ((std::floor((f.max_x - f.min_x) / bin_m) + 3.0) * (std::floor((f.max_y - f.min_y) / bin_m) + 3.0) >
           capacity) {
      bin_m *= 1.25;
    }
    BinGrid g;
    g.min_x = f.min_x;
    g.min_y = f.min_y;
    g.nbx = static_cast<int>(std::floor((f.max_x - f.min_x) / bin_m)) + 3;
    g.nby = static_cast<int>(std::floor((f.max_y - f.min_y) / bin_m)) + 3;
    g.inv_bin = 1.0 / bin_m;
    return g;
  }
  [[nodiscard]] std::size_t bins() const { return static_cast<std::size_t>(nbx) * static_cast<std::size_t>(nby); }
  [[nodiscard]] std::size_t bin_of(const ScanPoint& p) const {
    const int bx = std::min(static_cast<int>((p.x - min_x) * inv_bin), nbx - 3) + 1;
    const int by = std::min(static_cast<int>((p.y - min_y) * inv_bin), nby - 3) + 1;
    return static_cast<std::size_t>(by) * static_cast<std::size_t>(nbx) + static_cast<std::size_t>(bx);
  }
};

void PerfectMatcher::set_scan(std::span<const ScanPoint> points) {
  used_ = 0;
  coarse_used_ = 0;
  scan_centroid_m_ = Eigen::Vector2d::Zero();

  const ScanFootprint footprint = measure_footprint(points);
  if (footprint.finite == 0) return;
  scan_centroid_m_ = {footprint.sx / static_cast<double>(footprint.finite),
                      footprint.sy / static_cast<double>(footprint.finite)};
  const BinGrid grid = BinGrid::over(footprint, params_);
  bin_depths(points, grid);
  mark_informative_bins(grid);
  pick_spread(points, grid, footprint.finite);
  order_coarse_first();
}

void PerfectMatcher::bin_depths(std::span<const ScanPoint> points, const BinGrid& grid) {
  std::fill_n(bin_count_.begin(), grid.bins(), 0U);
  for (const ScanPoint& p : points) {
    if (!finite_point(p)) continue;
    const std::size_t b = grid.bin_of(p);
    BinDepth& z = bin_depth_[b];
    if (bin_count_[b] == 0) z = {p.z, p.z, p.z, p.z};
    if (p.z < z.low) {
      z.second_low = z.low;
      z.low = p.z;
    } else if (p.z < z.second_low) {
      z.second_low = p.z;
    }
    if (p.z > z.high) {
      z.second_high = z.high;
      z.high = p.z;
    } else if (p.z > z.second_high) {
      z.second_high = p.z;
    }
    ++bin_count_[b];
  }
}

void PerfectMatcher::mark_informative_bins(const BinGrid& grid) {
  const int nbx = grid.nbx, nby = grid.nby;
  std::fill_n(bin_informative_.begin(), grid.bins(), std::uint8_t{0});
  for (int by = 1; by + 1 < nby; ++by) {
    for (int bx = 1; bx + 1 < nbx; ++bx) {
      const std::size_t b = static_cast<std::size_t>(by) * static_cast<std::size_t>(nbx) + static_cast<std::size_t>(bx);
      if (bin_count_[b] == 0) continue;
      int occupied_neighbours = 0;
      float z_lo = bin_depth_[b].second_low;
      float z_hi = bin_depth_[b].second_high;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const std::size_t n = b + static_cast<std::size_t>(static_cast<std::ptrdiff_t>(dy) * nbx + dx);
          if ((dx == 0 && dy == 0) || bin_count_[n] == 0) continue;
          ++occupied_neighbours;
          z_lo = std::min(z_lo, bin_depth_[n].second_low);
          z_hi = std::max(z_hi, bin_depth_[n].second_high);
        }
      }
      // An isolated bin is more likely a stray point than an edge: it gets no extra weight.
      const bool edge = occupied_neighbours < 8 && occupied_neighbours >= kMinEdgeNeighbours;
      const bool relief = static_cast<double>(z_hi - z_lo) > params_.relief_m;
      bin_informative_[b] = edge || relief ? 1 : 0;
    }
  }
}

void PerfectMatcher::pick_spread(std::span<const ScanPoint> points, const BinGrid& grid, std::size_t finite) {
  std::size_t informative = 0;
  for (const ScanPoint& p : points) {
    if (finite_point(p)) informative += bin_informative_[grid.bin_of(p)];
  }
  const std::size_t others = finite - informative;
  used_ = std::min(finite, picked_.size());
  const auto wanted = static_cast<std::size_t>(std::lround(params_.informative_fraction * static_cast<double>(used_)));
  const std::size_t pick_informative = std::min(informative, std::max(wanted, used_ - std::min(used_, others)));
  const std::size_t pick_others = used_ - pick_informative;

  // Pick j of a class takes its point of rank floor(j * class size / picks): a fixed stride over the scan order
  // (frames along x, rows along the stripe), so the same scan always gives the same subset.
  struct Stride {
    std::size_t size = 0;   // points of the class
    std::size_t picks = 0;  // how many to take
    std::size_t first = 0;  // where its picks go in picked_
    std::size_t rank = 0, picked = 0, next = 0;
  };
  Stride classes[2] = {{others, pick_others, pick_informative}, {informative, pick_informative, 0}};
  for (const ScanPoint& p : points) {
    if (!finite_point(p)) continue;
    Stride& c = classes[bin_informative_[grid.bin_of(p)]];
    if (c.picked < c.picks && c.rank == c.next) {
      picked_[c.first + c.picked] = Eigen::Vector3f(p.x, p.y, p.z);
      ++c.picked;
      c.next = static_cast<std::size_t>(static_cast<std::uint64_t>(c.picked) * c.size / c.picks);
    }
    ++c.rank;
  }
}

void PerfectMatcher::order_coarse_first() {
  // Every stride-th pick goes to the front, so the coarse level is a prefix that is itself spread like the whole.
  std::size_t stride = 1;
  if (params_.coarse_points > 0 && params_.coarse_iterations > 0) {
    const auto coarse = static_cast<std::size_t>(params_.coarse_points);
    stride = (used_ + coarse - 1) / coarse;
  }
  coarse_used_ = (used_ + stride - 1) / stride;
  for (std::size_t j = 0; j < used_; ++j) {
    const std::size_t dest = j % stride == 0 ? j / stride : coarse_used_ + j - j / stride - 1;
    points_[dest] = picked_[j];
  }
}

PlanarPose PerfectMatcher::centroid_start(const Eigen::Vector2d& template_centroid_m) const {
  const Eigen::Vector2d t = scan_centroid_m_ - template_centroid_m;
  return {t.x(), t.y(), 0.0};
}

PerfectMatchCost PerfectMatcher::cost(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                      const PlanarPose& pose, std::size_t count, double fit_lc_m,
                                      const DepthPlane& depth) const {
  count = std::min(count, used_);
  const double lc2 = fit_lc_m > 0.0 ? fit_lc_m * fit_lc_m : params_.lc_m * params_.lc_m;
  const double error_lc2 = params_.lc_m * params_.lc_m;
  const double cx = template_centroid_m.x();
  const double cy = template_centroid_m.y();

  // Each scan point goes back into the template frame, p_t = c + R(-theta)(p_scan - c - t) (inverse of eq. 2.55
  // with DESIGN.md's centre c), where the template's map is sampled. With r = p_t - c:
  //   dd/dt     = -R(theta) grad_t    (grad_t: the map's x/y gradient, eq. 2.60, 2.63, 2.64)
  //   dd/dtheta = grad_t . (r_y, -r_x)   (eq. 2.65 for the inverse rotation)
  // so the per-point weights are summed in the template frame and rotated once at the end.
  PerfectMatchCost out;
  double sum_gx = 0.0;
  double sum_gy = 0.0;
  double sum_gt = 0.0;
  const TemplateFrame frame(template_centroid_m, pose);
  for (std::size_t i = 0; i < count; ++i) {
    // The levelling plane is held fixed within a pass: its (small) dependence on the pose is not in the gradient.
    double rx = 0.0, ry = 0.0, z = 0.0;
    frame.map(points_[i], depth, rx, ry, z);
    const MapSample s = map.sample(cx + rx, cy + ry, z);
    const double d = s.distance_m;
    const double d2 = d * d;
    const double w = lc2 / (lc2 + d2);
    out.cost += d2 / (lc2 + d2);             // thesis eq. 2.56: 1 - w, without the cancellation for small d
    out.error_sum += d2 / (error_lc2 + d2);  // = 1 - Lc^2 / (Lc^2 + d^2) with the error's Lc
    out.sum_d2_m2 += d2;
    const double de_dd = 2.0 * d * w * w / lc2;  // 2 Lc^2 d / (Lc^2 + d^2)^2, thesis eq. 2.57
    const double gx = de_dd * s.grad_x;
    const double gy = de_dd * s.grad_y;
    sum_gx += gx;
    sum_gy += gy;
    sum_gt += gx * ry - gy * rx;
  }
  out.grad[0] = -(frame.cos_t * sum_gx - frame.sin_t * sum_gy);
  out.grad[1] = -(frame.sin_t * sum_gx + frame.cos_t * sum_gy);
  out.grad[2] = sum_gt;
  return out;
}

DepthPlane PerfectMatcher::depth_plane(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                       const PlanarPose& pose, const DepthPlane& prior) const {
  DepthPlane from = prior;
  for (int round = 0; round < kLevelStripRounds; ++round) {
    LevelFit kind = LevelFit::kNone;
    const DepthPlane plane = fit_depth_plane(map, template_centroid_m, pose, from, kind);
    if (kind == LevelFit::kPart) return plane;
    if (kind == LevelFit::kNone) break;
    from = plane;  // a strip: a step towards the part's plane, fitted again from there
  }
  return prior;
}

DepthPlane PerfectMatcher::fit_depth_plane(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                           const PlanarPose& pose, const DepthPlane& prior, LevelFit& kind) const {
  kind = LevelFit::kNone;
  DepthPlane plane;
  const double h = map.dims().resolution_m;
  if (!(h > 0.0) || used_ == 0) return plane;
  const double cx = template_centroid_m.x();
  const double cy = template_centroid_m.y();
  const TemplateFrame frame(template_centroid_m, pose);
  // Each used point once: its template-frame X, Y and, when it lies above or below its surface, the depth e of that
  // surface below it (NaN otherwise). The clip passes below only filter these.
  // The spread in X and Y of all used points (the part), to tell a fit over the part from one over a strip of it.
  Eigen::Matrix3d all = Eigen::Matrix3d::Zero();
  const double half_cell = 0.5 * h;
  for (std::size_t i = 0; i < used_; ++i) {
    double rx = 0.0, ry = 0.0, z = 0.0;
    frame.map(points_[i], prior, rx, ry, z);
    const Eigen::Vector3d v(1.0, rx, ry);
    all += v * v.transpose();
    level_[i] = Eigen::Vector3d(rx, ry, std::numeric_limits<double>::quiet_NaN());
    const double px = cx + rx;
    const double py = cy + ry;
    const MapSample s0 = map.sample(px, py, z);
    if (!(s0.distance_m <= params_.level_clip_m)) continue;
    // Beside an edge the nearest surface is sideways. The slope over one cell, not the interpolant's derivative at
    // the point: that one flips within a cell next to a voxel surface (louvred_panel swung by 1.5 deg: 0.14 deg
    // theta error and a 2.1e-3 slope error with it, 0.05 deg / 0.8e-3 with this).
    const double side_x = map.sample(px + half_cell, py, z).distance_m - map.sample(px - half_cell, py, z).distance_m;
    const double side_y = map.sample(px, py + half_cell, z).distance_m - map.sample(px, py - half_cell, z).distance_m;
    if (!(std::hypot(side_x, side_y) <= kLevelMaxSideGradient * h)) continue;
    // Samples that straddle the surface: a point e above a surface inclined by alpha has d = |e| cos(alpha), so
    // |e| < reach, and the two samples are (reach + e) cos(alpha) and (reach - e) cos(alpha).
    const double reach = 2.0 * s0.distance_m + h;
    const MapSample up = map.sample(px, py, z + reach);
    const MapSample down = map.sample(px, py, z - reach);
    if (!up.fine || !down.fine) continue;  // the coarse field is no depth gauge
    const double sum = up.distance_m + down.distance_m;
    if (!(sum >= 2.0 * reach * kLevelMinDepthGradient)) continue;     // cos(alpha): a surface above or below
    level_[i].z() = reach * (up.distance_m - down.distance_m) / sum;  // > 0: the scan point lies above it
  }
  Eigen::Vector3d fit = Eigen::Vector3d::Zero();
  bool have_fit = false;
  for (const double clip_fraction : {1.0, 0.4, 0.15}) {
    const double clip = clip_fraction * params_.level_clip_m;
    Eigen::Matrix3d a = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    int n = 0;
    for (std::size_t i = 0; i < used_; ++i) {
      const double rx = level_[i].x();
      const double ry = level_[i].y();
      const double e = level_[i].z();
      if (!std::isfinite(e)) continue;
      if (have_fit && !(std::abs(e - (fit[0] + fit[1] * rx + fit[2] * ry)) <= clip)) continue;
      const Eigen::Vector3d v(1.0, rx, ry);
      a += v * v.transpose();
      b += v * e;
      ++n;
    }
    if (n < kLevelMinPoints) break;
    const bool spans = spans_part(a, all);
    const bool strip = !have_fit && !spans && spans_part(a, all, kLevelStripSpread);
    if (!spans && !strip) break;
    const Eigen::LDLT<Eigen::Matrix3d> ldlt(a);
    if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > kLevelMinRcond)) break;
    fit = ldlt.solve(b);
    if (strip) {  // a step only (depth_plane fits again from it)
      if (!fit.allFinite()) break;
      kind = LevelFit::kStrip;
      return plus_fit(prior, fit, n);
    }
    have_fit = true;
    plane.points = n;
  }
  if (!have_fit || !fit.allFinite()) return prior;
  kind = LevelFit::kPart;
  if (largest_change(fit, all) < kLevelMinChangeCells * h) {
    // Below what the map resolves in depth: a sheet lies anywhere within its layer of cells, so the distances carry a
    // bias of that order, and levelling by it only trades the bias for noise in the pose (chamfered_plate scanned on
    // another lattice: a 0.1 mm offset turned theta by up to 0.11 deg instead of 0.08).
    DepthPlane kept = prior;
    kept.points = plane.points;
    return kept;
  }
  return plus_fit(prior, fit, plane.points);
}

Eigen::Matrix3d rotation_of(const FullPose& pose) {
  return (Eigen::AngleAxisd(pose[PoseAxis::kRz], Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(pose[PoseAxis::kRy], Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(pose[PoseAxis::kRx], Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

FullPose full_pose_of(const Eigen::Matrix3d& r, const Eigen::Vector3d& t) {
  // R = R_z(theta) R_y(ry) R_x(rx): R(2, 0) = -sin(ry), R(2, 1) / R(2, 2) = tan(rx), R(1, 0) / R(0, 0) = tan(theta).
  FullPose p;
  p[PoseAxis::kX] = t.x();
  p[PoseAxis::kY] = t.y();
  p[PoseAxis::kZ] = t.z();
  p[PoseAxis::kRy] = std::asin(std::clamp(-r(2, 0), -1.0, 1.0));
  p[PoseAxis::kRx] = std::atan2(r(2, 1), r(2, 2));
  p[PoseAxis::kRz] = std::atan2(r(1, 0), r(0, 0));
  return p;
}

namespace {
Eigen::Vector3d translation_of(const FullPose& p) {
  return {p[PoseAxis::kX], p[PoseAxis::kY], p[PoseAxis::kZ]};
}
}  // namespace

FullPose compose(const FullPose& a, const FullPose& b) {
  // a(b(p)) = c + R_a R_b (p - c) + R_a t_b + t_a
  const Eigen::Matrix3d ra = rotation_of(a);
  return full_pose_of(ra * rotation_of(b), ra * translation_of(b) + translation_of(a));
}

FullPose inverse(const FullPose& pose) {
  // q = c + R^T (p - c) - R^T t
  const Eigen::Matrix3d rt = rotation_of(pose).transpose();
  return full_pose_of(rt, -(rt * translation_of(pose)));
}

namespace {

constexpr int kMinRefinePoints = 30;
constexpr double kMinRefineRcond = 1e-12;
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

// Normal equations of the full pose at one pose: J^T W J and J^T W d over the points with a fine-field distance.
struct RefineSums {
  Matrix6d h = Matrix6d::Zero();
  Vector6d b = Vector6d::Zero();
  double weighted_d2 = 0.0;
  double weight = 0.0;
  int points = 0;
};

}  // namespace

FullPoseFit PerfectMatcher::refine(const DistanceMapView& map, const Eigen::Vector3d& centroid_m,
                                   const PerfectMatchResult& planar) const {
  // The start: the planar pose and its levelling plane. z_scan - z_template = offset + slope_x X + slope_y Y is what
  // R_y(ry) R_x(rx) makes of a sheet through c: slope_x = -tan(ry), slope_y = tan(rx) / cos(ry).
  FullPoseFit fit;
  fit.sigma.fill(std::numeric_limits<double>::quiet_NaN());
  FullPose& pose = fit.pose;
  pose[PoseAxis::kX] = planar.pose.x_m;
  pose[PoseAxis::kY] = planar.pose.y_m;
  pose[PoseAxis::kZ] = planar.depth.offset_m;
  pose[PoseAxis::kRz] = planar.pose.theta_rad;
  pose[PoseAxis::kRy] = -std::atan(planar.depth.slope_x);
  pose[PoseAxis::kRx] = std::atan(planar.depth.slope_y * std::cos(pose[PoseAxis::kRy]));
  if (used_ < static_cast<std::size_t>(kMinRefinePoints) || !map.valid()) return fit;

  Eigen::Matrix3d r = rotation_of(pose);
  Eigen::Vector3d t = translation_of(pose);
  const double lc2 = params_.refine_lc_m * params_.refine_lc_m;
  // Each scan point back into the template frame, q = R^T (p - c - t); a small motion of the template about c by
  // (delta, omega) (R' = R exp(omega), t' = t + R delta) moves it to q - delta - omega x q, so with g the map's
  // gradient at c + q: dd/ddelta = -g, dd/domega = g x q.
  const auto accumulate = [&]() {
    RefineSums sums;
    const Eigen::Matrix3d rt = r.transpose();
    for (std::size_t i = 0; i < used_; ++i) {
      const Eigen::Vector3d q = rt * (points_[i].cast<double>() - centroid_m - t);
      const Eigen::Vector3d at = centroid_m + q;
      const MapSample s = map.sample(at.x(), at.y(), at.z());
      if (!s.fine) continue;
      const Eigen::Vector3d g(s.grad_x, s.grad_y, s.grad_z);
      Vector6d j;
      j << -g, g.cross(q);
      const double d = s.distance_m;
      const double w = lc2 / (lc2 + d * d);
      // The full product, not selfadjointView().rankUpdate(): for a fixed 6x6 it costs 15 more multiply-adds per
      // point, and Eigen's rank update drew clang-analyzer's false "potential leak" from its stack temporary.
      sums.h.noalias() += (w * j) * j.transpose();
      sums.b += (w * d) * j;
      sums.weighted_d2 += w * d * d;
      sums.weight += w;
      ++sums.points;
    }
    return sums;
  };

  const double max_turn = params_.refine_max_step_m / params_.refine_lever_m;
  RefineSums sums;
  bool settled = false;
  for (int it = 0;; ++it) {
    sums = accumulate();
    if (sums.points < kMinRefinePoints) return fit;
    if (it == params_.refine_iterations || settled) break;
    const Eigen::LDLT<Matrix6d> ldlt(sums.h);
    if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > kMinRefineRcond)) return fit;
    const Vector6d step = -ldlt.solve(sums.b);
    if (!step.allFinite()) return fit;
    Eigen::Vector3d delta = step.head<3>();
    Eigen::Vector3d omega = step.tail<3>();
    // A step is clamped, never scaled as a whole: one badly fixed axis does not stall the others.
    for (int k = 0; k < 3; ++k) {
      delta[k] = std::clamp(delta[k], -params_.refine_max_step_m, params_.refine_max_step_m);
      omega[k] = std::clamp(omega[k], -max_turn, max_turn);
    }
    t += r * delta;
    const double angle = omega.norm();
    if (angle > 0.0) r = r * Eigen::AngleAxisd(angle, omega / angle).toRotationMatrix();
    fit.iterations = it + 1;
    settled = std::max(delta.cwiseAbs().maxCoeff(), omega.cwiseAbs().maxCoeff() * params_.refine_lever_m) <
              params_.refine_settle_m;
  }
  pose = full_pose_of(r, t);
  fit.points = sums.points;
  fit.rms_m = std::sqrt(sums.weighted_d2 / std::max(sums.weight, 1e-300));
  const Eigen::LDLT<Matrix6d> ldlt(sums.h);
  if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > kMinRefineRcond)) return fit;
  const double s2 = sums.weighted_d2 / std::max(sums.points - kPoseAxes, 1) +
                    params_.refine_noise_floor_m * params_.refine_noise_floor_m;
  const Matrix6d cov = s2 * ldlt.solve(Matrix6d::Identity());
  // delta is a translation in the template frame, t moves by R delta: the scan frame's covariance is R C R^T.
  const Eigen::Matrix3d cov_t = r * cov.topLeftCorner<3, 3>() * r.transpose();
  for (Eigen::Index k = 0; k < 3; ++k) {
    const auto axis = static_cast<std::size_t>(k);
    fit.sigma[axis] = std::sqrt(std::max(cov_t(k, k), 0.0));
    fit.sigma[axis + 3] = std::sqrt(std::max(cov(k + 3, k + 3), 0.0));
  }
  fit.ok = true;
  return fit;
}

PerfectMatchResult PerfectMatcher::match(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                         const PlanarPose& start, double give_up_error) const {
  PerfectMatchResult result;
  result.pose = start;
  result.points = static_cast<int>(used_);
  const bool finite_start = std::isfinite(start.x_m) && std::isfinite(start.y_m) && std::isfinite(start.theta_rad);
  if (used_ == 0 || params_.max_iterations == 0 || !finite_start) return result;  // error stays 1: no match

  RpropState state[3] = {
      {params_.step_initial_m, params_.step_min_m, params_.step_max_m},
      {params_.step_initial_m, params_.step_min_m, params_.step_max_m},
      {params_.step_initial_rad, params_.step_min_rad, params_.step_max_rad},
  };
  const double step_initial[3] = {params_.step_initial_m, params_.step_initial_m, params_.step_initial_rad};
  // Level 0 (coarse prefix) only when it is a real subset and leaves at least one iteration for all points.
  const bool coarse = coarse_used_ < used_ && params_.coarse_iterations > 0 && params_.max_iterations > 1;
  const int coarse_budget = coarse ? std::min(params_.coarse_iterations, params_.max_iterations - 1) : 0;

  double pose[3] = {start.x_m, start.y_m, start.theta_rad};
  double best_pose[3] = {pose[0], pose[1], pose[2]};
  double best_cost = 0.0;
  double best_error = 0.0;
  double best_d2 = 0.0;
  bool have_best = false;
  int evaluations = 0;
  // Levels: 0 = coarse, 1.. = the fine passes (one without levelling).
  const int fine_passes = std::max(params_.level_passes, 1);
  DepthPlane depth;
  for (int level = coarse ? 0 : 1; level <= fine_passes; ++level) {
    const bool fine = level >= 1;
    const std::size_t count = fine ? used_ : coarse_used_;
    // The fine passes share what the coarse level left; the last takes the rest.
    const int remaining = params_.max_iterations - evaluations;
    const int budget =
        fine ? (level == fine_passes ? remaining : remaining / (fine_passes - level + 1)) : coarse_budget;
    // The coarse level's wide bowl (lc_m) for capture, the fine level's robust one (fit_lc_m) for the pose.
    const double fit_lc = fine ? params_.fit_lc_m : params_.lc_m;
    if (fine && budget <= 0 && have_best) break;  // the cap is spent: keep the last pass's best
    if (fine && params_.level_passes > 0) {
      // Levelled at the best pose so far; the pass's costs are another function, so the best restarts with it.
      const PlanarPose at =
          have_best ? PlanarPose{best_pose[0], best_pose[1], best_pose[2]} : PlanarPose{pose[0], pose[1], pose[2]};
      depth = depth_plane(map, template_centroid_m, at, depth);
      if (have_best) std::copy(best_pose, best_pose + 3, pose);
      have_best = false;
    }
    if (fine && (coarse || level > 1)) {
      // The cost of all points is another function: its derivatives do not continue the coarse ones.
      for (int k = 0; k < 3; ++k) {
        state[k].previous_grad = 0.0;
        state[k].step = std::clamp(std::max(state[k].step, kFineRestartStepFraction * step_initial[k]),
                                   state[k].step_min, state[k].step_max);
      }
    }
    for (int i = 0; i < budget; ++i) {
      const PerfectMatchCost c = cost(map, template_centroid_m, {pose[0], pose[1], pose[2]}, count, fit_lc, depth);
      ++evaluations;
      if (fine && (!have_best || c.cost < best_cost)) {
        have_best = true;
        best_cost = c.cost;
        best_error = c.error_sum;
        best_d2 = c.sum_d2_m2;
        std::copy(pose, pose + 3, best_pose);
      }
      bool settled = true;
      for (int k = 0; k < 3; ++k) {
        pose[k] += rprop_update(state[k], c.grad[k], params_.eta_plus, params_.eta_minus);
        // The coarse level hands over as soon as its steps are below those the fine level restarts with.
        const double settle = fine ? state[k].step_min : kFineRestartStepFraction * step_initial[k];
        settled = settled && state[k].step <= settle;
      }
      if (level == 1 && i + 1 == kGiveUpIterations && best_error > give_up_error * static_cast<double>(used_)) {
        result.gave_up = true;
        break;
      }
      if (settled) {
        result.converged = fine;
        break;
      }
    }
    if (result.gave_up) break;  // (no levelling pass after it: the error stands as it was)
  }
  if (!have_best) return result;  // unreachable: the fine level always has at least one iteration
  const auto n = static_cast<double>(used_);
  result.pose = {best_pose[0], best_pose[1], best_pose[2]};
  result.error = best_error / n;
  result.rms_distance_m = std::sqrt(best_d2 / n);
  result.iterations = evaluations;
  result.depth = depth;
  return result;
}

}  // namespace cellsight::algo
