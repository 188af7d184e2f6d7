// Decision stage (thesis 5.3, 6.4.4): SVM probabilities + Perfect Match over the k best classes, every accepted class
// verified against its template by a two-way surface check that also sees material the scan LACKS.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <span>
#include <vector>

#include "algo/decision.hpp"
#include "algo/distance_map.hpp"
#include "algo/grid.hpp"
#include "algo/perfect_match.hpp"
#include "algo/scan.hpp"
#include "algo/svm.hpp"

namespace cellsight::algo {

inline constexpr double kRadPerDeg = std::numbers::pi / 180.0;

// The version of what `train` learns beside the SVM (the gates' limits, the size's and edges' models, look-alikes),
// recorded in the model database (formats::Manifest::learn_version). Raised when the check or learn_thresholds
// change so that limits learnt before no longer keep near twins apart: a database learnt by another version is
// stale until `train` learns it again. Catalogue 11357's database learnt on b09fc00 gave 7b903f5 a wrong id (rnd11,
// 5 mm taller, taken for rnd09) that the same build's own training rejects (rnd09's edge 2.6 mm against 1.0).
// 1: recorded from 7b903f5 on (databases without it count as 0). 2: isolation drops a flange's end seen edge-on
// (the own scans' figures change) and the edges' floors widen for fewer than 12 taught passes. 3: a strip of lost
// data with a few lone residue cells counts as lost (the own scans' missing areas change). 4: a ghost floating beside
// the part goes before matching (PartIsolator::drop_ghosts; a taught scan with one measured differently). 5: the far
// half of a part a glare band cut in two beside a neighbour's sheet at the field's end stays (mark_end_pieces).
inline constexpr std::uint32_t kLearnVersion = 5;

// The outline's four edges in the template frame (MatchReport::edge_m, TemplateThresholds): x low and high, y low
// and high.
enum class Edge : std::uint8_t { kLeft, kRight, kBottom, kTop };
inline constexpr std::size_t kEdges = 4;

struct CascadeParams {
  // Candidate policy (issue 10; the thesis's 6.4.4 verified only the SVM's best k = 2). Candidates are verified in
  // the SVM's rank order, at most pm_candidates of them and while verify_budget_ms lasts (the first always), until
  // one passes. Then what could also pass is verified before anything is accepted: the passing class's look-alikes
  // (TemplateModel::confusable) and every candidate at least stop_ratio times as probable (0 = none). When several
  // pass, the one with the least evidence against it wins only with a clear margin (see margin_ratio); otherwise the
  // scan is unknown. accept_p1 / accept_p2_max only label a decision "svm" (the SVM alone was sure, thesis 6.4.4):
  // every class, however sure the SVM is, is verified.
  // The budget counts from when the decision began (decide()'s `began`: the recogniser passes the scan's arrival, so
  // scan preparation and the SVM are inside it), and a candidate is not started when the longest check of this
  // decision so far would end beyond it: the decision's time is bounded by the budget, not by the budget plus the
  // candidates that happened to start just before its end (issue 11: 204 ms at 300 parts with 200 ms of budget).
  // The search in rank order for a first passing candidate has a budget of its own, search_budget_ms (counted the
  // same way, at most verify_budget_ms): a scan that no candidate has passed by then is unknown. The SVM's
  // kFirstRanked most probable are verified within verify_budget_ms all the same, and so is every candidate while
  // every check that ran has found lost data (verify_all_lost_m2) on the scan: glare is where the SVM ranks the true
  // class lower (a 35 ms search alone lost 3 of ~1 000 passes under `mixed` and `glare`, each with the true class
  // ranked 3rd-9th and lost data on the scan). Once one passes, what could also pass is verified within
  // verify_budget_ms. The search's tail is where time goes and answers do not: the true class is among the SVM's two
  // most probable for >= 98 % of scans even under `mixed`, while a scan whose own template fails narrowly (or an
  // untaught part) verified every candidate (issue 11: 15 of 15 taught parts under a PLC, worst cycle 75.9 ms; a
  // single 45 ms budget bounded it but also cut the look-alikes of a passing candidate short, 6 more unknown passes).
  double accept_p1 = 0.70;
  double accept_p2_max = 0.06;
  int pm_candidates = 16;
  double verify_budget_ms = 200.0;
  double search_budget_ms = 35.0;
  double stop_ratio = 0.5;
  // Two passing candidates: the winner's evidence (MatchReport::evidence_m2) must be at most margin_ratio times the
  // runner-up's and smaller by at least margin_floor_m2; else "ambiguous" (unknown). Near twins differ by a hole or a
  // rib: hundreds of mm^2 against the tens a matching template leaves.
  double margin_ratio = 0.5;
  double margin_floor_m2 = 100e-6;
  // A look-alike of the winner that failed with every figure within this factor of its limit leaves no clear margin
  // either (the scan is unknown); its outer size counts as near within (factor - 1) * size_floor_m of its limit.
  double near_fail_factor = 1.5;

  // Two-way check (see Cascade). A template cell counts as seen when the scan has a surface within blob_window_m
  // (x-y, rounded to whole cells, at least one) whose depth is within depth_tolerance_m of the template's; the same
  // the other way round for scan cells. The window absorbs the pose error (Perfect Match on simulated scans: < 1 mm;
  // the outline pose below: ~2 mm along x) and the scan's sampling (one profile per cell along x, so a rotated scan
  // leaves single empty cells). A hole of radius R leaves a blob of about pi (R - 1.2 (window + cell / 2))^2.
  double blob_window_m = 0.0044;
  double depth_tolerance_m = 0.005;
  // ... and not only within the hull of the window's depths (which admits any depth between a relief's lowest and
  // highest cell) but, where the other surface has cells within fine_window_m, within fine_depth_tolerance_m of one
  // of them (see Cascade::depth_contradicted).
  bool per_cell_depth = true;
  double fine_window_m = 0.0022;
  double fine_depth_tolerance_m = 0.0025;
  // Perfect Match's pose can be millimetres off on a flat sheet (its cost there is mostly depth, sampled sparsely),
  // so the check also aligns the x-y outlines (the scan's outline points to the distance transform of the template's
  // outline, truncated least squares, Gauss-Newton from Perfect Match's pose) and keeps whichever of the two poses
  // leaves the smaller blobs: the surfaces agree when some plausible alignment makes them agree, and a real
  // difference (a hole, a rib) shows at either. The outline pose is only as good as the outline sampling (one
  // profile per 2.2 mm along x: up to ~2 mm in x), so Decision::pose stays Perfect Match's unless
  // decision_pose_from_outline. refine_iterations = 0 checks at Perfect Match's pose only.
  int refine_iterations = 12;
  double refine_cutoff_m = 0.010;         // outline points farther than this are ignored in the first iterations ...
  double refine_final_cutoff_m = 0.0035;  // ... and farther than this in the last ones
  bool decision_pose_from_outline = false;
  // Full pose (issue 13): the accepted candidate's planar pose refined to x, y, z, rx, ry, theta
  // (PerfectMatcher::refine). Published per PoseAxis: sigma = sqrt((pose_sigma_scale * s)^2 + pose_sigma_floor^2), s
  // the refinement's 1-sigma (points taken as independent). The first term is this scan's error: its points are not
  // independent (neighbours share the map's cells; along x the part is sampled one profile per 2.2 mm). The floor is
  // the template's own: a template is one taught scan, and its error is in every pose measured against it. Both were
  // fitted on the simulated cell, per axis, to the spread of the true errors within and between parts (README
  // "Pose"), so that the true error lies within 2 sigma for ~95 % of parts. An axis whose published sigma exceeds
  // max_sigma_m / max_sigma_rad is not fixed by the geometry (a strip a few millimetres high gives no tilt about x):
  // its value is NaN (invalid on the PLC), never a guess. x, y and theta stay published whatever their sigma (the
  // thesis's planar pose).
  bool full_pose = true;
  std::array<double, kPoseAxes> pose_sigma_scale = {1.7, 1.1, 1.05, 1.0, 0.9, 1.2};
  std::array<double, kPoseAxes> pose_sigma_floor = {
      0.09e-3, 0.11e-3, 0.03e-3, 0.014 * kRadPerDeg, 0.012 * kRadPerDeg, 0.015 * kRadPerDeg};
  // The robot's accuracy need (issue 13: z 0.5 mm, tilt and swing 0.15 deg): a 1-sigma above it is no measurement.
  double max_sigma_m = 0.0005;
  double max_sigma_rad = 0.15 * kRadPerDeg;
  // The full pose is refined from the check's pose too (check_pose, the one the gates verified) when Perfect Match's
  // lies further from it than this, at the template's centroid; the closer fit is published. The outline pose is
  // known to a profile step along x (2.2 mm); a theta of 0.5 deg moves a corner 300 mm out 2.6 mm.
  double pose_agree_m = 0.003;
  double pose_agree_rad = 0.5 * kRadPerDeg;
  // Before the depth comparison the scan's depth is levelled onto the template's by a robust plane fit
  // (z offset + slopes in x and y): the swing about the hook's vertical axis (+-2 deg, up to 16 mm of depth at the
  // edge of a 450 mm part between two passes) is not part of the planar pose; a local difference (a rib) is.
  bool level_depth = true;

  // learn_thresholds(): threshold = own-class maximum * factor + floor. The factor covers what N training scans
  // did not show (the maximum of 35 samples is about their 97th percentile); the floor keeps a template usable
  // when its training scans happened to be alike.
  // Error floor: the planar pose does not model the swing about the hook (+-2 deg in the simulated cell), so two
  // passes of the same part differ in depth by x tan(dswing); over a 480 mm sheet at dswing = 4 deg that is a mean
  // d^2 of (0.48^2 / 12) tan^2(4 deg) = 9.4e-5 m^2, an error of 5.9e-4 at Lc = 0.4 m. The error threshold is a coarse
  // gate (unrelated shapes); the two-way check is what tells near-identical parts apart.
  // Area floor: own-class blobs stay under ~65 mm^2 (reconstructed scans, tests/bench/bench_cascade.cpp), a 40 mm
  // hole leaves ~500 mm^2 with the default window; 150 mm^2 (31 cells of 2.2 mm) sits between them.
  double error_factor = 2.0;
  double error_floor = 6e-4;
  // The margin to the runner-up (learn_thresholds step 3) measures how far another part's scan stands above the own
  // class by the own maximum, floored so that own scans that are all alike do not make a hair's difference look
  // clear: a quarter of the floor for the areas and shares, but this for the error. Levelled, an own-class match
  // errs by 3-9e-6 on the simulated cell, and a twin whose relief differs only in depth shape (louvres where the
  // other has ribs: areas within the depth tolerance) by 1.6e-5 and more; the coarse error_floor (unlevelled swing)
  // would hide that difference.
  double error_margin_floor = 6e-6;
  double area_factor = 1.5;
  double area_floor_m2 = 150e-6;
  // The largest blob misses a difference spread over many small places: two perforated sheets whose hole patterns
  // differ (14 mm holes against 24 mm ones) leave blobs of only 60-80 mm^2 each, but 1.3 % of the template
  // uncovered. So the shares of uncovered template cells and of outlying scan cells are gated as well. Own-class
  // shares on the 12-part simulated catalogue stay below 0.05 % (acceptance run, README); 0.3 % sits well between.
  double share_factor = 1.5;
  double share_floor = 0.003;
  // Hole pattern (issue 11): the window that absorbs the pose error also hides holes narrower than about 13 mm (a
  // hole of radius R leaves pi (R - 6.6 mm)^2 of blob), so two perforated sheets whose 11 mm hole fields lie 42 mm
  // apart (a mirrored twin) left blobs of 30-40 mm^2 and 99.97 % coverage. Each side's holes are therefore compared
  // as holes: a compact hole of one surface, clean (solid material around it), where the other surface is solid
  // within hole_match_radius_m of its centre, counts with its area (the scan's holes where the template is solid,
  // the template's holes the scan covers at the template's depth). A pose error of a millimetre or two moves a hole
  // by as much, so the same hole pattern counts nothing. Threshold: own-class maximum * area_factor + this floor
  // (one 11 mm hole is ~80 mm^2 of cells).
  double hole_pattern_floor_m2 = 120e-6;
  double hole_match_radius_m = 0.0044;
  // Evidence is judged by its shape. A blob of missing or extra cells that is a thin band (elongation >=
  // band_elongation) touching the outside (missing) or the matched scan (extra) only at its ends (share of its boundary
  // <= band_contact_max) is what glare, a dropout line, a chain or a hook leave: it counts with weak_evidence_weight
  // (0: missing data is no evidence against a part; a band wide enough to matter is not thin). An enclosed blob (a
  // hole the template lacks, a template hole covered) and a blob along an edge (a wider or narrower part) count fully.
  double weak_evidence_weight = 0.0;
  double band_elongation = 3.0;
  double band_contact_max = 0.35;
  // ... and no wider than this (glare bands of strength 1 are 15-35 mm, chains 6-10 mm): a wider region beyond a
  // template's outline is a larger part, not an artefact.
  double band_max_width_m = 0.045;
  // A passing candidate whose check counted this much template area as lost data may pass only because the data
  // that tells it from a twin is lost (a glare band over the one rib they differ by): then every candidate is
  // verified (within the budget), not only its learnt look-alikes, and any other that passes needs the margin.
  double verify_all_lost_m2 = 0.0003;
  // Outer size (TemplateThresholds::max_size_dev_m): the own-class maximum deviation * size_factor + size_floor_m,
  // at least three robust sigmas of the own deviations (a bent flange's end: learn_thresholds, tail_limit).
  // A scan's extent is sampled: across profiles at the profile spacing (2.2 mm), along them at the sensor's row
  // spacing (~1.6 mm), so a scan whose part lies square to the sampling is off by up to a step (its own scans show
  // it in their maximum); a turned part averages it out over the lines. A part 5 mm taller deviates by ~5 mm: the
  // maximum plus a floor, not a multiple, keeps the gate under that. The width has a floor of its own, a profile
  // step: a few taught passes turned a little need not show it (fresh catalogue 11350 taught with 5: rnd00's within
  // 0.44 mm, a pass square to the profiles 2.1 mm narrower, the step that every line of it lost alike).
  double size_factor = 1.0;
  double size_floor_m = 0.0015;
  double size_floor_x_m = 0.0022;
  // Edges (TemplateThresholds::max_edge_dev_m): the own-class maximum deviation * size_factor + edge_floor_m. A
  // part 5 mm taller whose other end is a bent flange (seen 0-8 mm short of the sheet's end as the part swings and
  // turns) has a height no tighter than the flange's scatter, but its clean edge lies 2.5-5 mm off the twin's
  // template's against the holes, where an edge of the own scans is off by up to a row step (1.6 mm: where the last
  // row of points falls) and the holes' shift by ~0.25 mm. The floor covers what a few taught scans did not show.
  // Left and right have a floor of their own: across the profiles (x, the conveyor's direction, one profile per
  // 2.2 mm, a cell) a hole's centre is known to about a cell only, the same for every hole (where the profiles fall
  // against the raster): the holes' shift came out 1.5 mm off in x (11301 under `mixed`, rnd05 s910008).
  double edge_floor_m = 0.0008;
  double edge_floor_x_m = 0.0015;
  // learn_thresholds(): an own-class scan whose figure lies more than robust_k robust standard deviations (1.4826
  // MAD) above the median disagrees with the others (glare, a stray edge, a wrong part taught): it is flagged and
  // does not widen the thresholds.
  double robust_k = 4.0;
};

struct MatchReport;

// What a template must meet for its class to be accepted; learnt per template at training (learn_thresholds).
// Zero thresholds accept only a perfect match: an unlearnt template is effectively never accepted.
struct TemplateThresholds {
  double max_error = 0.0;            // Perfect Match error per point (PerfectMatchResult::error)
  double max_missing_area_m2 = 0.0;  // largest connected template area the scan lacks
  double max_extra_area_m2 = 0.0;    // largest connected scan area the template lacks
  double max_uncovered = 0.0;        // share of the template's cells the scan lacks (1 - coverage), all blobs together
  double max_outliers = 0.0;         // share of the scan's cells the template lacks (scan_outliers)
  double max_hole_pattern_m2 = 0.0;  // holes of one surface where the other is solid, all together (hole_pattern_m2)
  // Outer size: the scan's width and height less the template's (MatchReport::size_dx_m / size_dy_m) are expected at
  // these centres (own-class medians: sampling and the template's cells bias them); a deviation beyond its axis's
  // limit fails. Each axis has its own: a part's width and height scatter differently (a 58 mm flange along a side
  // edge projects up to 6 mm more or less width as the part swings on its hook; its height does not move), and a
  // twin 5 mm taller must not hide in the width's scatter (catalogue 11002, rnd05 / rnd09). The default never fails
  // (thresholds learnt before the size was measured).
  double size_centre_x_m = 0.0;
  double size_centre_y_m = 0.0;
  double max_size_dev_x_m = std::numeric_limits<double>::infinity();
  double max_size_dev_y_m = std::numeric_limits<double>::infinity();
  double max_size_dev_m = std::numeric_limits<double>::infinity();  // the larger of the two (what `parts list` shows)
  // The larger deviation of a report's width / height from the centres (at its slopes: size_gain_x_m); NaN when the
  // report could not measure them.
  [[nodiscard]] double size_deviation(const MatchReport& r) const;
  // Whether the width or the height deviates by more than `factor` x its limit plus `slack_m` (an unmeasured size,
  // NaN, does not).
  [[nodiscard]] bool size_beyond(const MatchReport& r, double factor = 1.0, double slack_m = 0.0) const;
  // Edges: each edge's outward offset beyond the template's, against the holes (MatchReport::edge_m), is expected at
  // its centre (the own-class median, or its line in the slope: edge_gain_m) within its limit: a clean edge gets a
  // tight limit, a flange's end the wide one its own scans show (the size, the sum of two edges' offsets, only the
  // wider). The default never fails (thresholds learnt before the edges were measured).
  std::array<double, kEdges> edge_centre_m{};
  std::array<double, kEdges> max_edge_dev_m = {
      std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
      std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity()};
  // Swing and tilt: beside a flange the sheet's visible end is where the wall's laser shadow ends, and that moves
  // with the part's swing (x) or tilt (y) against the template's. 11315's rnd03 (56 mm flanges left and right): its
  // right edge came out 1.0 mm - 80 mm x the depth levelling's slope along x, within 0.5 mm, over +-3 deg of swing;
  // as a scatter about one centre that is +-5 mm, and its two most swung taught scans were flagged as disagreeing.
  // Where the own scans show such a line (learn_thresholds), the centre is taken at the report's slope (MatchReport::
  // depth_slope_x for the width and the left and right edges, depth_slope_y for the others): centre + gain x slope.
  // Metres per unit of slope; 0 (the default, and every template learnt before): the centre alone.
  double size_gain_x_m = 0.0;
  double size_gain_y_m = 0.0;
  std::array<double, kEdges> edge_gain_m{};
  // Where an edge's line explains its own scans only in part (learn_thresholds), also the band they span about their
  // median (the centre and limit the edge would have without the line): a report within either passes. Beside a
  // flange the shadow's end may follow the swing as a step rather than a line (shipped channel_u: its left edge
  // -2.3..-0.5 mm at slopes 0-0.006, +0.9..+2.1 mm at 0.046-0.088 over 12 taught passes; the line through them says
  // +2.6 mm at 0.095 where a fresh pass measured -0.7), and a pass the line misses but the taught passes' own
  // scatter holds is no evidence against the part. A line that explains its scans closely stands alone (a twin's
  // offset shows against it), and so does the size's: a twin 5 mm longer shows there. 0 limit (the default, an
  // edge without such a line, a template learnt before): no band.
  std::array<double, kEdges> edge_median_m{};
  std::array<double, kEdges> max_edge_dev_median_m{};
  // The centres at a report's slopes.
  [[nodiscard]] double size_centre_x_at(const MatchReport& r) const;
  [[nodiscard]] double size_centre_y_at(const MatchReport& r) const;
  [[nodiscard]] double edge_centre_at(std::size_t edge, const MatchReport& r) const;
  // An edge's deviation from its centre, metres, against max_edge_dev_m[edge]; with a band about the median, the
  // smaller of that and the band's deviation shifted to the same limit (0 at least): it exceeds the limit by as much
  // as the nearer of the two exceeds its own. NaN for an unmeasured edge.
  [[nodiscard]] double edge_deviation_at(std::size_t edge, const MatchReport& r) const;
  // The largest of a report's edges' deviations (edge_deviation_at), metres; unmeasured (NaN) edges are left out (0
  // when none is measured).
  [[nodiscard]] double edge_deviation(const MatchReport& r) const;
  // Whether an edge deviates by more than its limit plus a slack (left and right: slack_x_m; an unmeasured edge, NaN,
  // does not).
  [[nodiscard]] bool edge_beyond(const MatchReport& r, double slack_x_m = 0.0, double slack_y_m = 0.0) const;
};

// One taught class as the cascade sees it. Borrows everything (the real map is a memory-mapped template file).
struct TemplateModel {
  int class_index = -1;  // must equal its position in the span given to decide()
  int part_id = 0;       // PLC id
  DistanceMapView map;
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();  // c of the pose (centroid_xy_m of the template scan)
  // c's depth (the full pose's centre): mean depth of the template's occupied cells. NaN: no full pose (x, y, theta
  // of Perfect Match only, no z, rx, ry).
  double centroid_z_m = std::numeric_limits<double>::quiet_NaN();
  // The template scan's occupied cells, in the map's grid (surface_cells_from_map() recovers them from a map).
  std::span<const SurfaceCell> surface_cells;
  TemplateThresholds thresholds;
  // Classes whose scans came near passing this template at training, or whose template this class's scans came near
  // passing (learn_confusable): when this class passes, they are verified too before anything is accepted.
  std::span<const int> confusable;
};

// Perfect Match plus the two-way check of one scan against one template.
struct MatchReport {
  PerfectMatchResult pm;
  double missing_area_m2 = 0.0;  // largest 4-connected blob of template cells the scan lacks
  double extra_area_m2 = 0.0;    // largest 4-connected blob of scan cells the template lacks
  double coverage = 0.0;         // template cells seen in the scan / template cells
  double scan_outliers = 1.0;    // scan cells without template / scan cells (cells outside the raster included)
  // Depth levelling applied to the scan (z_scan - z_template ~ offset + slope_x * (x - c_x) + slope_y * (y - c_y),
  // template frame): diagnostics; slope_x ~ -tan(swing difference).
  double depth_offset_m = 0.0;
  double depth_slope_x = 0.0;
  double depth_slope_y = 0.0;
  PlanarPose check_pose{};     // the pose the reported check ran at (Perfect Match's or the outline pose)
  double outline_rms_m = 0.0;  // outline distances within the final cutoff, at the outline pose
  // Outer size: the median over the template's rows of the scan's width there less the template's (dx), and over
  // its columns of the heights (dy), metres. A part 5 mm taller shows dy ~ +5 mm whatever the pose (an extent does
  // not move with the part), which the cell-based areas cannot see. NaN when too few rows / columns hold both.
  double size_dx_m = std::numeric_limits<double>::quiet_NaN();
  double size_dy_m = std::numeric_limits<double>::quiet_NaN();
  // Edges (Edge order): how far the scan's edge lies beyond the template's, outwards (so that the width's dx is
  // about left + right), the windowed mean over the same lines as the size, metres, with the scan placed on
  // the template by their holes (Cascade::edges_against_holes: an edge moves with the pose, and a flat sheet's pose
  // is pulled by its edges). NaN when not measured (lines ending in lost data, or no hole to place it by).
  std::array<double, kEdges> edge_m = {
      std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN(),
      std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()};
  int template_cells = 0;
  int scan_cells = 0;
  // Hole pattern: the area of the scan's small holes where the template is solid plus that of the template's holes
  // the scan covers (see CascadeParams::hole_pattern_floor_m2), which the window-based blobs cannot see.
  double hole_pattern_m2 = 0.0;
  // Weighted evidence against the template: the largest weighted missing plus extra blob, plus the hole pattern.
  double evidence_m2 = 0.0;
  // Template area the scan lacks that counted as lost data (glare, a dropout band): where it lies, a feature that
  // tells this part from a twin may be hidden (CascadeParams::verify_all_lost_m2). Cells within the check's window
  // of a template depth step of kShadowStepM (a relief wall, whose foot the laser's shadow hides in some poses) are
  // left out: every ribbed part's scan has such strips.
  double lost_area_m2 = 0.0;
  // The two-way check's part of the thresholds. Written so that NaN fails.
  [[nodiscard]] bool check_passes(const TemplateThresholds& t) const {
    // The size and the edges are the figures an unmeasurable (NaN) value passes: a scan too fragmentary to measure
    // them fails the areas and shares anyway, and a part without holes has no edges to measure.
    return missing_area_m2 <= t.max_missing_area_m2 && extra_area_m2 <= t.max_extra_area_m2 &&
           1.0 - coverage <= t.max_uncovered && scan_outliers <= t.max_outliers &&
           hole_pattern_m2 <= t.max_hole_pattern_m2 && !t.size_beyond(*this) && !t.edge_beyond(*this);
  }
  [[nodiscard]] bool passes(const TemplateThresholds& t) const { return pm.error <= t.max_error && check_passes(t); }
};

// Training time: whether another class's report against a template came near passing it (every figure within
// `factor` times its threshold): such classes are the template's look-alikes (TemplateModel::confusable).
[[nodiscard]] bool near_pass(const MatchReport& report, const TemplateThresholds& t, double factor);

// Training time: thresholds of one template from the reports of its own class's scans against it. Own-class scans
// that disagree with the others (robust_k, see CascadeParams) are flagged and left out; the rest give max * factor +
// floor. Then every other class's scan that would still pass is pushed out: the figure that separates it best from
// the own class is lowered to halfway between them (a margin to the runner-up). An empty span gives the floors.
struct ThresholdLearning {
  TemplateThresholds thresholds;
  std::vector<int> flagged;         // indices into own_class of scans that disagree with the others
  int other_scans_rejected = 0;     // other-class scans the thresholds reject
  int other_scans_inseparable = 0;  // other-class scans no figure tells from the own class
};
[[nodiscard]] ThresholdLearning learn_thresholds(std::span<const MatchReport> own_class,
                                                 std::span<const MatchReport> other_classes,
                                                 const CascadeParams& params);
[[nodiscard]] inline TemplateThresholds learn_thresholds(std::span<const MatchReport> own_class,
                                                         const CascadeParams& params) {
  return learn_thresholds(own_class, {}, params).thresholds;
}

// The first threshold a report fails, with its value and limit (kNone when it passes). NaN fails.
[[nodiscard]] RejectReason first_failed_gate(const MatchReport& report, const TemplateThresholds& t, double& value,
                                             double& limit);

// Start-up / test helper: a map's occupied cells (distance 0), x fastest. Allocates; reads every stored brick.
void surface_cells_from_map(const DistanceMapView& map, std::vector<SurfaceCell>& out);

// The decision stage. Everything is sized at construction for one grid; decide() never allocates. Not thread-safe.
//
// Policy (issue 10): candidates are verified (Perfect Match + two-way check against their template's learnt
// thresholds) in the SVM's rank order, so the true class is verified even when the SVM ranks it low. The search ends
// when a passing candidate is clearly more probable than the next (stop_ratio), after pm_candidates, or when
// verify_budget_ms is spent (search_budget_ms while none has passed yet). Exactly one passing candidate, or one with a
// clear margin of evidence over every other passing one (margin_ratio, margin_floor_m2) -> accepted: kSvm when the SVM
// alone was sure (p1 >= accept_p1, p2 <= accept_p2_max, its best class won), else kPm. Two passing without a margin ->
// kUnknown (ambiguous). None -> kUnknown. A budget that ends while an unverified candidate is still as probable as
// stop_ratio allows -> kUnknown: the accepted class could have had a twin there. The deadline is checked before every
// Perfect Match; when it has passed the decision is kTimeout. Never a guess. A candidate whose Perfect Match error is
// already over its threshold is not checked further (its report's areas, coverage and outliers are NaN).
//
// Decision fields: probability = the SVM's for the chosen class (its best class when unknown or timeout); pm_error,
// pose, template_coverage, scan_outliers of the chosen candidate (unknown: those of the most probable verified
// candidate, for the log; no pose); second_class_index = the most probable other verified candidate;
// candidates = every candidate looked at, in rank order, with its outcome; pm_ms = Perfect Match plus checks;
// total_ms = all of decide(). features_ms and svm_ms are the caller's to fill.
//
// Two-way check: one-way matching (scan -> template distances, eq. 2.56) cannot see a scan that lacks material the
// template has (a 40 mm hole is ~1 % of a plate's points and each sits at most 20 mm from the template). In the
// template frame at the Perfect Match pose both surfaces are rasterised on the grid's x-y cells (per cell the depth
// range); a template cell is "missing" when no scan cell within the window has a compatible depth, a scan cell is
// "extra" when no template cell does. The largest 4-connected blob of each is compared with the template's learnt
// maxima. Depth makes a pressed rib (20 mm) visible, which a flat x-y mask is blind to.
class Cascade {
 public:
  // decide() checks the SVM's this many most probable candidates without the gross-failure shortcut, at both poses
  // and with the wide outline fit (check_prepared); train matches a scan's closest rivals the same way.
  static constexpr std::size_t kFirstRanked = 2;

  Cascade(const CascadeParams& params, const PerfectMatchParams& pm_params, const GridSpec& grid);  // allocates

  // svm_best_first: SvmModel::predict's output. templates_by_class[i] is class i's template.
  // scan_without_carrier: the part's points after support removal, carrier frame.
  // began: when the decision began, from which verify_budget_ms counts (default: now, decide()'s own start).
  [[nodiscard]] Decision decide(std::span<const ClassProbability> svm_best_first,
                                std::span<const TemplateModel> templates_by_class,
                                std::span<const ScanPoint> scan_without_carrier,
                                std::chrono::steady_clock::time_point deadline,
                                std::chrono::steady_clock::time_point began = {});

  // Perfect Match from the centroid start plus the two-way check (training: the reports learn_thresholds() takes).
  // The check also tries the outline pose and keeps the better figures. With `gross_limits`, a check that fails one
  // of them by far at Perfect Match's pose is not retried there, as decide() does with the learnt thresholds: train
  // passes a template's own-class limits, which learn_thresholds() only ever lowers, so decide() skips the retry of
  // that scan too and sees the same figures (issue 11: 10.7 instead of 17.6 min of rival matching at 297 parts).
  // decide() retries its first-ranked candidates (kFirstRanked) even so; train passes no limits for a scan's closest
  // rivals likewise.
  [[nodiscard]] MatchReport evaluate(const TemplateModel& model, std::span<const ScanPoint> scan,
                                     const TemplateThresholds* gross_limits = nullptr);
  // An own-class scan (training's and teach's reports of a part's own scans): evaluate() with Perfect Match also from
  // the two turned starts, the lowest error kept, as decide() matches the candidate the SVM ranks first when the
  // unturned start misses its limit (the limit being learnt here, all three are run). 11315's rnd03: two taught
  // scans swung 3 deg against the template settled 170 times the others' error from the unturned start and were
  // flagged as disagreeing; at run time the turned start recognises such a pass.
  [[nodiscard]] MatchReport evaluate_own(const TemplateModel& model, std::span<const ScanPoint> scan);
  // The same for one scan against several templates (training's rival matching): set_scan() once, then
  // evaluate_prepared() with that same scan per template. Saves the matcher's subsampling (four passes over the scan)
  // and the scan's outline per template; the reports equal evaluate()'s.
  void set_scan(std::span<const ScanPoint> scan);
  [[nodiscard]] MatchReport evaluate_prepared(const TemplateModel& model, std::span<const ScanPoint> scan,
                                              const TemplateThresholds* gross_limits = nullptr);

  // The two-way check alone, from a given pose (it also tries the outline pose; the report's pm is left default).
  // Exposed for tests and diagnostics.
  [[nodiscard]] MatchReport two_way_check(const TemplateModel& model, std::span<const ScanPoint> scan,
                                          const PlanarPose& pose);

  // Decision's full pose and sigmas from an accepted candidate's report (CascadeParams::full_pose): Perfect Match's
  // planar result refined, and refined from the check's pose too when Perfect Match's lies apart from it
  // (CascadeParams::pose_agree_m). The report must be of the scan the matcher holds (the last evaluate() or match).
  // Exposed for tests and diagnostics.
  void publish_full_pose(const TemplateModel& t, const MatchReport& r, Decision& d) const;

  [[nodiscard]] const CascadeParams& params() const { return params_; }
  [[nodiscard]] int window_cells() const { return window_cells_; }

 private:
  struct Roi {
    int x0, y0, x1, y1;  // inclusive-exclusive cell range of the raster
    [[nodiscard]] bool empty() const { return x1 <= x0 || y1 <= y0; }
  };
  struct Candidate {
    int class_index = -1;
    double probability = 0.0;
    bool evaluated = false;
    bool passed = false;
    bool twin_decided = false;  // won a tie with its twin by what the scan shows where they differ (tell_twins_apart)
    double twin_seen = 0.0, twin_expected = 0.0;  // tell_twins_apart's cells seen / expected in the twin's hole
    double ms = 0.0;
    MatchReport report;
  };
  struct BlobEvidence {
    double largest_cells = 0.0;  // weighted area of the heaviest blob
    double total_cells = 0.0;    // weighted area of all blobs
    double weak_cells = 0.0;     // area the shape rules weighed down (lost data, thin bands), beside no relief wall
  };

  // decide()'s steps (cascade.cpp): verification in rank order, then of what could also pass (false when the deadline
  // passed), the verified candidates ranked by evidence, and the decision filled in (accepted, unknown, timeout).
  struct DecideState;
  struct Ranking;
  [[nodiscard]] bool verify(DecideState& s, std::size_t j);
  [[nodiscard]] bool verify_in_rank_order(DecideState& s, std::size_t& first_pass);
  [[nodiscard]] bool verify_look_alikes(DecideState& s, std::size_t first_pass);
  [[nodiscard]] bool could_also_pass(const DecideState& s, std::size_t j, double best_p) const;
  [[nodiscard]] bool clear_margin(double best_evidence_m2, double runner_evidence_m2) const;
  [[nodiscard]] Ranking rank_verified(const DecideState& s) const;
  [[nodiscard]] bool clear_of_near_misses(const DecideState& s, const Candidate& best) const;
  // Two passing candidates without a clear margin: the one the scan shows where their templates differ (see the
  // definition); nullptr when the scan does not tell, or the budget would end.
  [[nodiscard]] const Candidate* tell_twins_apart(DecideState& s, const Ranking& rk);
  void accept_winner(DecideState& s, const Candidate& best);
  [[nodiscard]] bool poses_agree(const PlanarPose& a, const PlanarPose& b) const;
  void report_unknown(DecideState& s, const Ranking& ranking);
  void report_timeout(DecideState& s);
  void report_candidates(DecideState& s, const Candidate* winner, bool ambiguous) const;
  // Perfect Match + check of the scan set in matcher_; false when the deadline passed before it could start.
  // first_ranked: one of the SVM's most probable candidates (kFirstRanked), checked without the gross-failure
  // shortcut (check_prepared); rescue_short: such a candidate also gets rematch_short_end (no candidate passed yet).
  bool evaluate_candidate(std::span<const TemplateModel> templates, std::span<const ScanPoint> scan,
                          std::chrono::steady_clock::time_point deadline, bool first_ranked, bool rescue_short,
                          Candidate& out);
  // Perfect Match from the centroid start turned by turn_rad (evaluate_candidate's and evaluate_own's further starts).
  [[nodiscard]] PerfectMatchResult match_turned(const TemplateModel& model, double turn_rad,
                                                double give_up_error) const;
  // A failing first-ranked candidate whose check settled on a pose far from Perfect Match's: Perfect Match once
  // more from that pose, and its check, replace the report when they leave less evidence.
  void rematch_from_outline(const TemplateModel& model, std::span<const ScanPoint> scan, Candidate& c);
  // A failing first-ranked candidate whose Perfect Match met its error limit at once: the turned starts too, each
  // checked, replace the report when they leave less evidence (see the definition).
  void rematch_turned(const TemplateModel& model, std::span<const ScanPoint> scan,
                      std::chrono::steady_clock::time_point deadline, Candidate& c);
  // A failing first-ranked candidate whose scan is short of its template along x or y by more than the size's limit
  // (an end lost to glare): Perfect Match from the scan placed flush with either end, each checked (see the
  // definition).
  void rematch_short_end(const TemplateModel& model, std::span<const ScanPoint> scan,
                         std::chrono::steady_clock::time_point deadline, Candidate& c);
  // The rematches' last step: a further Perfect Match of a failing candidate within its error limit is checked,
  // and its report replaces the candidate's when it leaves less evidence.
  void check_again(const TemplateModel& model, std::span<const ScanPoint> scan, const PerfectMatchResult& again,
                   Candidate& c);
  // The check proper (takes the scan's outline when it first needs it and outline_valid_ is false). With
  // thresholds, a gross failure at `pose` ends it when settle_on_gross, and so does a pass when settle_on_pass (the
  // outline pose is only tried when the given one fails).
  [[nodiscard]] MatchReport check_prepared(const TemplateModel& model, std::span<const ScanPoint> scan,
                                           const PlanarPose& pose, const TemplateThresholds* thresholds,
                                           bool settle_on_pass = true, bool settle_on_gross = true);
  void prepare_scan_outline(std::span<const ScanPoint> scan);
  [[nodiscard]] bool prepare_template_outline(const Roi& template_box);
  [[nodiscard]] double outline_cost(const Eigen::Vector2d& centre_m, const PlanarPose& pose, double cutoff_m,
                                    int* inliers) const;
  [[nodiscard]] PlanarPose refine_on_outline(const Eigen::Vector2d& centre_m, const PlanarPose& start,
                                             double first_cutoff_m, double last_cutoff_m, int iterations,
                                             double& rms_m);
  // check_prepared()'s steps: whether a check fails its gates by far (kGrossFailure x a limit), and the outline fit
  // from a pose with the check at its result (kept in `best` when it finds less evidence); `wide` holds a wide cutoff
  // over several steps before the usual fit (kWideCutoffM, kWideIterations).
  [[nodiscard]] static bool gross_failure(const MatchReport& report, const TemplateThresholds& thresholds);
  // Whether a gross failure looks like a misplaced alignment (material missing and extra, the size agreeing), which
  // a wide outline fit may mend: only then do the first-ranked candidates get one.
  [[nodiscard]] static bool displaced(const MatchReport& report, const TemplateThresholds& thresholds);
  // Whether the outer size is off by far (kGrossFailure x its limit), which no alignment mends.
  [[nodiscard]] static bool off_in_size(const MatchReport& report, const TemplateThresholds& thresholds);
  // covered_hole_cells: whether a template cell at least `raised` deep lies within `reach` cells of `cell` (in the
  // box).
  [[nodiscard]] bool near_raised(const Roi& roi, std::int32_t cell, int reach, float raised) const;
  [[nodiscard]] double recheck_on_outline(const TemplateModel& model, std::span<const ScanPoint> scan,
                                          const PlanarPose& pose, const Roi& template_box, bool wide,
                                          MatchReport& best);
  void outline_mask(const std::vector<float>& lo, const std::vector<float>& hi, const Roi& roi);
  void closed_mask(const std::vector<float>& lo, const std::vector<float>& hi, const Roi& roi,
                   std::vector<std::uint8_t>& out);
  [[nodiscard]] Roi grow(const Roi& roi, int cells) const;
  [[nodiscard]] Roi rasterise_template(const TemplateModel& model);
  [[nodiscard]] Roi rasterise_scan(std::span<const ScanPoint> scan, const Eigen::Vector2d& centre_m,
                                   const PlanarPose& pose, int& outside_points);
  void level_scan_depth(const Roi& roi, const Eigen::Vector2d& centre_m, MatchReport& report);
  void window_range(const std::vector<float>& lo, const std::vector<float>& hi, const Roi& roi);
  // Whether `other` has occupied cells within fine_window_m of (x, y) but none with depths within tol of [lo, hi],
  // unless both surfaces cross a relief wall there (`own_lo` / `own_hi`: this cell's surface).
  [[nodiscard]] bool depth_contradicted(int x, int y, float lo, float hi, const std::vector<float>& own_lo,
                                        const std::vector<float>& own_hi, const std::vector<float>& other_lo,
                                        const std::vector<float>& other_hi, float tol) const;
  // MatchReport::size_dx_m / size_dy_m and edge_m from the rasters. Per template column: the scan's height there (its
  // points' own y extent, continuous) less the template's (its occupied cells' centres: a surface spanning [a, b]
  // gives floor(b) - floor(a), b - a on average); the mean over the columns that both hold within 1.5 cells of their
  // median (windowed_mean in the .cpp: a turned edge's staircase in its shares), away from
  // the template's left and right ends (slanted there by a turn). The same per row for the width. Extents do not
  // move with the pose, so Perfect Match splitting a 5 mm difference into 2.5 mm at either edge (which no area sees)
  // leaves it whole here. Glare, a chain or a hook spoils some columns; the window leaves them out. Each line's
  // ends also give the two edges across it (outward offsets, scan less template; edges_against_holes places them).
  void measure_size(const Roi& roi, MatchReport& r);
  // Marks the missing cells that lie in a region of lost data (kLost): see the definition.
  void mark_lost_data(const Roi& roi);
  // mark_lost_data()'s steps: window counts along rows (false: no template cell) and columns (with glare's residue),
  // the template's outside, the groups of missing and sparse cells, and the laser shadow beside relief walls.
  struct CellGroup;
  [[nodiscard]] bool scan_occupies(std::size_t i) const;
  [[nodiscard]] bool sparse_window(std::size_t i, double typical) const;
  [[nodiscard]] bool row_window_counts(const Roi& roi, double& typical);
  void column_window_counts(const Roi& roi, double typical);
  void mark_template_outside(const Roi& roi);
  [[nodiscard]] bool joins_group(std::size_t i, double typical) const;
  [[nodiscard]] CellGroup grow_group(const Roi& roi, std::size_t seed, double typical);
  [[nodiscard]] bool is_lost_data(const CellGroup& group) const;
  void empty_depth(const Roi& roi);
  void mark_group_lost(const CellGroup& group);
  void protect_holes(const CellGroup& group);
  struct EmptyRectangle {
    double side = 0.0;      // cells across the axis
    double along_lo = 0.0;  // the run of deep cells along the axis, cells from the start (<= 0) ...
    double along_hi = 0.0;  // ... and (>= 0): the rectangle is side + along_hi - along_lo long
  };
  [[nodiscard]] EmptyRectangle empty_rectangle(const Eigen::Vector2d& p, const Eigen::Vector2d& axis,
                                               float depth) const;
  void follow_lost_bands(const Roi& roi);
  struct LostBand;
  void mark_band_strip(const Roi& roi, const LostBand& band, double t_lo, double t_hi, double half_width);
  void mark_laser_shadow(const Roi& roi);
  // The largest of the template's holes (cells) that the scan's material covers, densely or porously (after
  // mark_lost_data, before blob_evidence): see the definition.
  [[nodiscard]] double covered_hole_cells(const Roi& roi);
  // MatchReport::hole_pattern_m2 in cells (after mark_lost_data; see CascadeParams::hole_pattern_floor_m2).
  [[nodiscard]] double hole_pattern_cells(const Roi& roi);
  // hole_pattern_cells()'s half for one side: the unmatched holes (cells) of the scan, or of the template.
  [[nodiscard]] double unmatched_hole_cells(const Roi& roi, bool scan_holes);
  // unmatched_hole_cells()'s test of one hole (centre and equivalent radius in cells): clean (its own surface solid
  // around it in every direction) and unmatched (the other surface solid where it lies).
  [[nodiscard]] bool clean_unmatched_hole(const Roi& roi, const Eigen::Vector2d& centre, double radius,
                                          bool scan_holes) const;
  // The edges (MatchReport::edge_m, measured by measure_size) taken against the part's holes (after
  // hole_pattern_cells: uses mask_b_ and kVisited); `scan` is the one rasterise_scan placed last.
  void edges_against_holes(const Roi& roi, std::span<const ScanPoint> scan, MatchReport& r);
  // edges_against_holes' centre of the scan's paired holes along y from the scan's own points (see the definition):
  // shift_y[p] of pair p becomes the chords' centre less the template's, where enough chords were measured.
  void hole_chord_centres(const Roi& roi, std::span<const ScanPoint> scan, std::size_t pairs);
  // edges_against_holes' last step: the pairs' mean shift, weighted by area, moves the edges (kMinPairedCells paired
  // at least, else they are unmeasured).
  void edges_by_pairs(std::size_t pairs, MatchReport& r) const;
  // unmatched_hole_cells()'s empty cells of one side into mask_b_.
  void mark_empty_cells(const Roi& roi, bool scan_side);
  // Whether raster cell i holds a point of the scan (scan_side) or of the template.
  [[nodiscard]] bool occupied(std::size_t i, bool scan_side) const;
  // Clears `bit` in flags_ over the box.
  void clear_flag(const Roi& roi, std::uint8_t bit);
  // Flood-fills the blobs of `bit` (kMissing, or kExtra with `extra`) and weighs each by its shape
  // (CascadeParams::weak_evidence_weight).
  [[nodiscard]] BlobEvidence blob_evidence(const Roi& roi, std::uint8_t bit, bool extra);
  // blob_evidence()'s holes beside lost data: see the definition.
  [[nodiscard]] double solid_unlost_cells(std::size_t count, double& largest);
  [[nodiscard]] MatchReport check_at(const Eigen::Vector2d& centre_m, std::span<const ScanPoint> scan,
                                     const PlanarPose& pose, const Roi& template_box);
  // tell_twins_apart's count, in check_at while its flags hold the lost data (TwinVotes).
  void count_twin_votes(const Roi& roi);
  void reset_scan(const Roi& roi);
  void reset_template(const Roi& roi);

  // tell_twins_apart: with `other` set, check_at counts (count_twin_votes) the cells well inside both this template's
  // material and a hole of `other` (at other_pose), "the hole": inside lost data and clearly beyond it, and how many
  // the scan holds at this template's depth; and the same for the cells of both templates' material (the scan's
  // residue inside lost data and its coverage just beyond, from which the hole's expected count follows).
  struct TwinVotes {
    const TemplateModel* other = nullptr;
    PlanarPose other_pose{};
    int hole_lost = 0, hole_beyond = 0, hole_seen = 0;
    int both_lost = 0, both_lost_seen = 0, both_beyond = 0, both_beyond_seen = 0;
  };

  // (Fields in an order without padding holes: Eigen's Vector2d first, the ints as one group.)
  Eigen::Vector2d raster_origin_m_ = Eigen::Vector2d::Zero();
  TwinVotes twin_votes_;
  CascadeParams params_;
  PerfectMatcher matcher_;
  // x-y raster of the grid plus a margin (scan points rotated and shifted by the pose may leave the grid).
  double resolution_m_ = 0.0;
  int margin_cells_ = 0;
  int width_ = 0, height_ = 0;
  int window_cells_ = 1;
  std::vector<std::array<int, 2>> window_offsets_;  // (dx, dy) of the window's cells, nearest first
  std::vector<float> t_lo_, t_hi_;                  // template depth range per cell (+inf / -inf when empty)
  std::vector<float> s_lo_, s_hi_;                  // scan depth range per cell, template frame
  std::vector<float> w_lo_, w_hi_;                  // window min / max of one of them
  std::vector<float> tmp_lo_, tmp_hi_;              // separable-filter intermediate
  std::vector<std::uint8_t> flags_;                 // kMissing | kExtra per cell
  std::vector<std::int32_t> stack_;                 // flood fill, one entry per cell at most
  // Outline refinement: masks, the template outline's distance transform over a box, the scan's outline points.
  std::vector<std::uint8_t> mask_a_, mask_b_;
  std::vector<std::uint8_t> mask_s_;  // two-way check: the scan's closed mask
  // Outer size: the scan's continuous extent per raster column (y) and row (x); the template's per line; medians.
  std::vector<float> col_lo_, col_hi_, row_lo_, row_hi_;
  std::vector<int> size_lo_, size_hi_;
  std::vector<double> size_work_, edge_lo_work_, edge_hi_work_;
  struct HoleRef {
    double x, y, cells;  // a template hole's centre (raster cells) and area
  };
  static constexpr std::size_t kMaxEdgeHoles = 256;  // edges_against_holes pairs at most this many
  std::vector<HoleRef> holes_;
  // edges_against_holes' pairs: the template hole's centre row (cells), the scan piece's first column and the
  // pair's y shift (cells); per pair and column (at most kMaxHoleColumns), the highest scan point below the piece
  // and the lowest above it (hole_chord_centres); per raster cell the pair whose piece holds it (1-based, 0: none).
  struct HolePair {
    double template_y = 0.0, cells = 0.0, shift_x = 0.0, shift_y = 0.0;
    int x0 = 0;
  };
  static constexpr int kMaxHoleColumns = 128;  // a compact piece of kMaxCells (12 000) spans ~110
  std::vector<HolePair> hole_pairs_;
  std::vector<float> chord_below_, chord_above_;
  std::vector<std::uint16_t> hole_label_;
  // rasterise_scan's map of the last scan into continuous cell coordinates (its pose and the raster's scale), which
  // hole_chord_centres applies to the same points again.
  struct ScanMap {
    double axx = 0, axy = 0, bx = 0, ayx = 0, ayy = 0, by = 0;
    [[nodiscard]] double fx(const ScanPoint& p) const { return axx * p.x + axy * p.y + bx; }
    [[nodiscard]] double fy(const ScanPoint& p) const { return ayx * p.x + ayy * p.y + by; }
  };
  ScanMap scan_map_;
  std::vector<std::uint8_t> edt_in_;
  std::vector<float> edt_out_;  // distance to the template outline, cells, over edt_box_
  EdtScratch edt_scratch_;
  Roi edt_box_{0, 0, 0, 0};
  std::vector<Eigen::Vector2d> outline_;  // scan points in the outline cells of its closed x-y mask, scan frame
  std::size_t outline_count_ = 0;
  std::vector<Candidate> candidates_;     // the pm_candidates most probable classes of a decision
  std::vector<std::int32_t> blob_cells_;  // cells of the blob being weighed
  // The lost bands mark_lost_data() found in this check (cells: axis, half width, extent along the axis), for
  // follow_lost_bands(). Fixed capacity: a scan has a few glare bands, not dozens.
  struct LostBand {
    // A raster position's coordinate along the band's axis (the normal turned a quarter) and across it, from the
    // centre, in cells.
    [[nodiscard]] Eigen::Vector2d axis() const { return {-normal.y(), normal.x()}; }
    [[nodiscard]] double along(const Eigen::Vector2d& p) const { return (p - centre).dot(axis()); }
    [[nodiscard]] double across(const Eigen::Vector2d& p) const { return (p - centre).dot(normal); }
    Eigen::Vector2d centre{0.0, 0.0};
    Eigen::Vector2d normal{0.0, 0.0};
    double half_width = 0.0;
    double along_lo = 0.0;
    double along_hi = 0.0;
  };
  static constexpr int kMaxLostBands = 8;
  std::array<LostBand, kMaxLostBands> lost_bands_{};
  int lost_band_count_ = 0;
  bool outline_valid_ = false;  // outline_ belongs to the current scan
};

}  // namespace cellsight::algo
