// Perfect Match (thesis 2.7.3): pose (x, y, theta) of a scan against one template's distance map by RPROP on the
// robust cost E = sum 1 - Lc^2 / (Lc^2 + d^2) (eq. 2.56), gradient per eq. 2.57-2.66, trilinear map sampling.
// Accuracy is bounded by the map: a binary 2.2 mm occupancy places a straight axis-parallel edge or face only to half
// a cell, so such parts come out up to ~1 mm off; parts whose edges and relief cross the cells at many phases come
// out to 0.5 mm / 0.1 deg (tests/test_perfect_match.cpp, tests/bench/bench_perfect_match.cpp).
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "algo/decision.hpp"
#include "algo/distance_map.hpp"
#include "algo/scan.hpp"

namespace cellsight::algo {

struct PerfectMatchParams {
  // Lc of thesis eq. 2.56 for `error` (what the cascade compares between templates) and for the coarse level's fit,
  // whose wide bowl catches offsets of several centimetres.
  double lc_m = 0.4;
  // Lc of the pose fit at the fine level (of the only level without coarse-to-fine); <= 0: lc_m. With Lc = 0.4 m the
  // cost is least squares for every d that occurs, so anything that does not move with the part pulls the pose:
  // stray points, mixed pixels at edges, carrier remnants. Measured on reconstructed passes of the simulated cell
  // (tests/bench/bench_perfect_match.cpp --reconstructed, 5 passes each): worst errors 1.60 / 1.62 mm with
  // Lc = 0.4 m, 0.50 / 0.21 mm with Lc = 10 mm (plate_4h / chamfered_plate; the four other parts alike either way);
  // 5 and 20 mm give the same as 10 mm.
  double fit_lc_m = 0.01;
  double eta_plus = 1.2, eta_minus = 0.5;  // RPROP step growth / shrink (thesis eq. 2.67, 2.68)
  // Steps per parameter. A match has converged when every step has shrunk to its minimum: 10 um (and 1e-5 rad, 5 um
  // at 0.5 m from the centre) is far below what the 2.2 mm map resolves, and 1e-6 only costs ~25 % more iterations
  // for the same pose (tests/bench/bench_perfect_match.cpp).
  double step_initial_m = 0.002, step_min_m = 1e-5, step_max_m = 0.01;        // x, y
  double step_initial_rad = 0.002, step_min_rad = 1e-5, step_max_rad = 0.01;  // theta
  int max_iterations = 100;  // cap per match (all levels together when coarse-to-fine)
  int max_points = 1000;     // the scan is down-sampled to at most this many points (deterministic, no RNG)
  // Down-sampling (set_scan): the scan's x-y footprint is binned; points in bins at an outline or hole edge (an
  // empty neighbour bin) or on relief (z spans more than relief_m over the 3 x 3 bins, each bin's lowest and highest
  // point left out so that a lone stray point does not make relief of a flat sheet: ribs, flanges, louvres) are
  // "informative": they are what fixes x, y and theta, whereas a point inside a flat sheet has d = 0 for any small
  // in-plane shift. informative_fraction of max_points is spread evenly over those, the rest evenly over the others
  // (they keep the capture range for large offsets and the error meaningful for the cascade). Measured on six
  // catalogue parts, 1000 points: an even spread of all points leaves 1-2 % of them near an edge and gives
  // 0.9-6.1 mm / 0.18-0.75 deg worst errors; this selection 0.2-0.6 mm / 0.01-0.07 deg, about what all ~120 000
  // points give.
  double informative_fraction = 0.75;
  double feature_bin_m = 0.0044;  // two frame pitches of 2.2 mm, so no bin of a surface stays empty between frames
  double relief_m = 0.004;
  int max_feature_bins = 1 << 18;  // scratch; a larger footprint gets coarser bins
  // Coarse-to-fine: at most coarse_iterations iterations on an evenly spread subset of at most coarse_points of the
  // points (a prefix of points()), handing over once its steps have shrunk to 1/8 of the initial ones, then all of
  // them until max_iterations in total. coarse_points <= 0 or coarse_iterations <= 0: one level. Measured: same pose
  // as one level, 35-40 % less time per match (a 250-point iteration costs a quarter of a 1000-point one).
  int coarse_points = 250;
  int coarse_iterations = 70;
  // Depth levelling of the fine level. The planar pose (x, y, theta) does not model the part's swing about the
  // hook's vertical axis (+-2 deg in the simulated cell: up to 8 mm of depth at the edge of a 450 mm part) nor a
  // change of hook height, and on inclined relief (louvres, flanges, beads) a depth error can be traded for an
  // in-plane shift or turn, which biases the pose (measured on louvred_panel: theta off by 0.65 deg median). So the
  // fine level runs level_passes times; before each pass the depth offset of the scan from the template,
  // z_scan - z_template ~ a + b X + c Y (X, Y template frame about c), is fitted robustly at the current pose from
  // the used points that lie above or below a surface (see depth_plane()), and the template is then sampled at
  // z - (a + b X + c Y). level_passes <= 0: no levelling (the thesis's cost).
  int level_passes = 2;
  double level_clip_m = 0.008;  // points farther than this from the template surface do not enter the fit
  // Full pose (refine()): Gauss-Newton iterations on all six axes from the levelled planar pose, with the robust
  // (Cauchy) weights of refine_lc_m; the iterations stop when a step moves the part by less than refine_settle_m at
  // refine_lever_m from its centre. Measured on the simulated cell (README "Pose"): 3-5 iterations.
  int refine_iterations = 8;
  double refine_lc_m = 0.005;
  double refine_settle_m = 1e-6;
  double refine_lever_m = 0.2;
  double refine_max_step_m = 0.005;  // per iteration and axis (rotations: this at refine_lever_m)
  // The residual scale of the 1-sigma is at least this: below it the residuals say more about how exactly the scan's
  // points fit the template's cells than about where the part is (a noise-free scan of a flat strip fits its map to
  // microns, yet a 2.2 mm cell places a sheet only to a fraction of itself). It makes the sigma of an axis that only a
  // short lever fixes (the tilt of a strip a few cells high) large, as the geometry says.
  double refine_noise_floor_m = 0.0003;
};

// Depth offset of a scan from a template (see PerfectMatchParams::level_passes): z_scan - z_template =
// offset_m + slope_x X + slope_y Y, X, Y template-frame x-y about the template centroid.
struct DepthPlane {
  double offset_m = 0.0;
  double slope_x = 0.0;
  double slope_y = 0.0;
  int points = 0;  // points the fit used (0: no fit, the plane is zero)
};

struct PerfectMatchResult {
  PlanarPose pose{};  // DESIGN.md "Pose": p_scan = c + R(theta)(p_template - c) + (x, y, 0)
  // E / points: mean robust cost per used point, in [0, 1); 1 when there is nothing to match (no points, start not
  // finite). The used points over-represent edges and relief (informative_fraction), which is where two parts differ.
  double error = 1.0;
  double rms_distance_m = 0.0;  // of the used points at the final pose (diagnostics, thresholds)
  int iterations = 0;           // cost evaluations (= RPROP iterations) run
  int points = 0;               // scan points used (at the finest level)
  bool converged = false;       // steps fell under their minimum before the iteration cap
  DepthPlane depth{};           // the depth levelling of the last fine pass
  // match() stopped early: after kGiveUpIterations of the fine level the error was above its give_up_error. Measured
  // (3 056 candidate matches of the cascade on 6 development sets, 15-part random catalogues, plain and mixed): the
  // 1 490 matches that ended with an error at or below their template's learnt limit had, 5 iterations into the fine
  // level, at most 1.64 x that limit, so a match above twice the limit there ends above it (796 of the 2 516 wrong
  // candidates, 32 %, were).
  bool gave_up = false;
};

// The full pose of a scan against a template (refine()): p_scan = c + R_z(theta) R_y(ry) R_x(rx) (p_template - c) +
// (x, y, z), c the template's centroid in x, y and depth (DESIGN.md "Pose", algo/decision.hpp PoseAxis).
struct FullPose {
  std::array<double, kPoseAxes> axis{};  // PoseAxis order: x, y, z [m], rx, ry, theta [rad]
  [[nodiscard]] double operator[](PoseAxis a) const { return axis[static_cast<std::size_t>(a)]; }
  [[nodiscard]] double& operator[](PoseAxis a) { return axis[static_cast<std::size_t>(a)]; }
};

// Rotation and translation of a full pose about c, and back.
[[nodiscard]] Eigen::Matrix3d rotation_of(const FullPose& pose);
[[nodiscard]] FullPose full_pose_of(const Eigen::Matrix3d& rotation, const Eigen::Vector3d& translation_m);
// a o b: the pose that applies b first, then a (both about the same c).
[[nodiscard]] FullPose compose(const FullPose& a, const FullPose& b);
[[nodiscard]] FullPose inverse(const FullPose& pose);

struct FullPoseFit {
  FullPose pose{};
  // 1-sigma per axis from the robust cost's curvature at the optimum (Gauss-Newton: s^2 (J^T W J)^-1, s^2 the
  // weighted residual variance plus refine_noise_floor_m^2), taking the scan's points as independent: the caller scales
  // it to what the truth says (CascadeParams::pose_sigma_scale). Rotations in the template frame (equal to rx, ry,
  // theta's to first order).
  std::array<double, kPoseAxes> sigma{};
  double rms_m = 0.0;  // weighted rms distance at the optimum
  int points = 0;      // points with a fine-field distance (the others stay out: the coarse field is no surface)
  int iterations = 0;
  bool ok = false;  // false: too few points or a singular system; pose is the start, sigma NaN
};

// Cost of one pose and its gradient (thesis eq. 2.56, 2.57-2.66); what match() minimises, public for tests.
struct PerfectMatchCost {
  double cost = 0.0;                 // E = sum over points of 1 - Lc^2 / (Lc^2 + d^2), with the fit's Lc
  double grad[3] = {0.0, 0.0, 0.0};  // of cost: dE/dx [1/m], dE/dy [1/m], dE/dtheta [1/rad]
  double error_sum = 0.0;            // E with lc_m (PerfectMatchResult::error times points)
  double sum_d2_m2 = 0.0;            // sum of d^2 (for the rms distance)
};

// x-y mean of the finite points; (0, 0) when there is none. set_scan() uses it for centroid_start(). A template's c
// may be defined otherwise (formats/template_build: mean of the occupied cell centres): match() works with whatever
// c it is given, the start is then off by the difference, which RPROP removes like any other offset.
[[nodiscard]] Eigen::Vector2d centroid_xy_m(std::span<const ScanPoint> points);

// Holds the down-sampled scan; sized once, set_scan() and match() never allocate. Not thread-safe.
class PerfectMatcher {
 public:
  PerfectMatcher() : PerfectMatcher(PerfectMatchParams{}) {}
  explicit PerfectMatcher(const PerfectMatchParams& params);  // start-up: allocates for params.max_points

  // Takes a deterministic subset of the scan's finite points (carrier already removed; see informative_fraction) and
  // computes the x-y centroid of all its finite points. Call once per scan, then match() against as many templates as
  // needed. Four passes over the scan (~1.5 ms for 120 000 points).
  void set_scan(std::span<const ScanPoint> points);
  [[nodiscard]] Eigen::Vector2d scan_centroid_m() const { return scan_centroid_m_; }
  // The used points; the first coarse_count() of them are the coarse level's subset, spread like the whole.
  [[nodiscard]] std::span<const Eigen::Vector3f> points() const { return {points_.data(), used_}; }
  [[nodiscard]] std::size_t coarse_count() const { return coarse_used_; }

  // RPROP (iRprop-, thesis eq. 2.67-2.70) from `start` (typically centroid_start()) against one template;
  // `template_centroid_m` is c of the pose. Returns the pose with the lowest cost seen at the finest level. At most
  // max_iterations cost evaluations of at most max_points samples each.
  // `give_up_error`: the match stops after kGiveUpIterations of the fine level when its error (`error`'s measure, at
  // the best pose so far) is still above this; the result is then `gave_up`, its error that of the pose reached. Its
  // use: a caller that only needs to know whether the error ends below a limit (the cascade, for a candidate that
  // will fail on its error alone). The fine level refines the pose by millimetres and the error, a mean of squared
  // distances dominated by the points that lie centimetres from any surface of a wrong template, hardly moves with
  // it: see PerfectMatchResult::gave_up for what was measured.
  [[nodiscard]] PerfectMatchResult match(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                         const PlanarPose& start,
                                         double give_up_error = std::numeric_limits<double>::infinity()) const;
  static constexpr int kGiveUpIterations = 5;

  // Cost and gradient of the first `count` used points at `pose` (count is clamped to the used points), fitted with
  // `fit_lc_m` (<= 0: lc_m); error_sum always with lc_m. Default: the fine level's Lc.
  // `depth` levels the scan (the template is sampled at z - depth(X, Y)).
  [[nodiscard]] PerfectMatchCost cost(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                      const PlanarPose& pose, std::size_t count, double fit_lc_m,
                                      const DepthPlane& depth) const;
  [[nodiscard]] PerfectMatchCost cost(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                      const PlanarPose& pose, std::size_t count, double fit_lc_m) const {
    return cost(map, template_centroid_m, pose, count, fit_lc_m, DepthPlane{});
  }
  [[nodiscard]] PerfectMatchCost cost(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                      const PlanarPose& pose, std::size_t count) const {
    return cost(map, template_centroid_m, pose, count, params_.fit_lc_m);
  }

  // The depth offset of the used points from the template at `pose`. The map holds distances, not signed depths, so
  // a point's offset is read from two samples that straddle its surface, at z +- (2 d + one cell): for a surface
  // inclined by alpha they are (r + e) cos(alpha) and (r - e) cos(alpha), which give the depth e and cos(alpha). A
  // point above or below a sheet has cos(alpha) >= 0.6 and a small x-y gradient; points beside an edge (the nearest
  // surface sideways) or farther than level_clip_m are left out. (Sampled one cell either side, as before, a point
  // within a cell of its surface looked like one beside it: a well levelled scan lost its points to the fit.) Least
  // squares of the plane, refitted twice on the points within a shrinking band around it. Fewer than 30 points, a fit
  // over a strip of the part (its X or Y spread under a quarter of all points') or a degenerate system: the fit of
  // the band before, or the zero plane. A fit that changes the depth by less than a quarter of a cell over the part
  // (within the map's own depth sampling) leaves `prior` as it is.
  // `prior`: a plane found before (the previous pass's); the fit is of what remains after it, so points that were
  // beyond level_clip_m before levelling (the edges of a strongly swung part) enter once the prior has levelled them.
  // A fit over a strip only (a part tilted several degrees against its template) is a step: the fit is made again
  // from it, a few times at most, and only one over the part is returned (else `prior`).
  [[nodiscard]] DepthPlane depth_plane(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                       const PlanarPose& pose, const DepthPlane& prior = DepthPlane{}) const;

  // Refines the planar result of match() (its pose and depth levelling) to the full pose against the same template:
  // Gauss-Newton on the used points' distances d(p) to the template surface, with the map's gradient in x, y and z
  // (d^2 is smooth through the surface, so point-to-surface Gauss-Newton converges in a few steps), robust weights
  // 1 / (1 + d^2 / refine_lc_m^2). `centroid_m`: c in x, y and depth. Allocation-free; ~0.3 ms per iteration.
  [[nodiscard]] FullPoseFit refine(const DistanceMapView& map, const Eigen::Vector3d& centroid_m,
                                   const PerfectMatchResult& planar) const;

  // Start by centroid alignment: x, y = scan centroid - template centroid, theta 0.
  [[nodiscard]] PlanarPose centroid_start(const Eigen::Vector2d& template_centroid_m) const;

  [[nodiscard]] const PerfectMatchParams& params() const { return params_; }

 private:
  PerfectMatchParams params_{};
  // set_scan() scratch, sized at construction.
  std::vector<Eigen::Vector3f> picked_;
  std::vector<std::uint32_t> bin_count_;
  // z extremes of a bin's points; the second lowest / highest (the extreme itself when the bin has one point) give a
  // depth range that one stray point does not widen.
  struct BinDepth {
    float low, second_low, second_high, high;
  };
  std::vector<BinDepth> bin_depth_;
  std::vector<std::uint8_t> bin_informative_;
  // set_scan()'s steps: bin the points' depths, mark the informative bins, pick the subset, put the coarse level first.
  struct BinGrid;
  void bin_depths(std::span<const ScanPoint> points, const BinGrid& grid);
  void mark_informative_bins(const BinGrid& grid);
  void pick_spread(std::span<const ScanPoint> points, const BinGrid& grid, std::size_t finite);
  void order_coarse_first();
  // depth_plane()'s one fit from `prior`: kPart, a fit over the part (or `prior` kept, the change below what the map
  // resolves); kStrip, over a strip of it only; kNone, no fit (`prior` returned).
  enum class LevelFit { kNone, kStrip, kPart };
  [[nodiscard]] DepthPlane fit_depth_plane(const DistanceMapView& map, const Eigen::Vector2d& template_centroid_m,
                                           const PlanarPose& pose, const DepthPlane& prior, LevelFit& kind) const;

  std::vector<Eigen::Vector3f> points_;
  // depth_plane()'s per-point scratch (X, Y, depth e or NaN), sized with points_; not state between calls.
  mutable std::vector<Eigen::Vector3d> level_;
  std::size_t used_ = 0;
  std::size_t coarse_used_ = 0;
  Eigen::Vector2d scan_centroid_m_ = Eigen::Vector2d::Zero();
};

}  // namespace cellsight::algo
