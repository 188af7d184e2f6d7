// Tests of algo/cascade: the thesis 6.4.4 decision table on real (small) template maps of catalogue parts, the
// two-way check on parts that differ by one hole or one rib (both directions), threshold learning, and an
// allocation counter around decide(). Scans are sampled from the catalogue's exact facet geometry
// (drivers/sim/scene build_part) at known poses, so the truth is the simulator's pose.
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <memory>
#include <numbers>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "algo/cascade.hpp"
#include "algo/distance_map.hpp"
#include "algo/grid.hpp"
#include "algo/perfect_match.hpp"
#include "app/catalogue.hpp"
#include "drivers/sim/rig.hpp"
#include "drivers/sim/scene.hpp"
#include "drivers/sim/sim_cell.hpp"
#include "tests/support/alloc_counter.hpp"

using namespace cellsight;
using algo::Cascade;
using algo::CascadeParams;
using algo::ClassProbability;
using algo::Decision;
using algo::DecisionSource;
using algo::MatchReport;
using algo::PlanarPose;
using algo::ScanPoint;
using algo::TemplateModel;
using Clock = std::chrono::steady_clock;

namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kHoleRadiusM = 0.020;  // plate_5h's centre hole (config/parts.yaml)
constexpr sim::PartPose kTaughtPose{0.004, -0.006, 0.6 * kDeg, -0.5 * kDeg};
constexpr sim::PartPose kTestPose{-0.019, 0.011, 2.3 * kDeg, 1.3 * kDeg};

// A grid that holds every test pose (+-30 mm, +-4 deg, swing +-2 deg) at the real 2.2 mm, but only the depth slab
// the flat and ribbed parts occupy, so that a map builds in about a second under ASan.
algo::GridSpec test_grid() {
  algo::GridSpec g;
  g.origin_m = {0.03, 0.18, 0.07};
  g.resolution_m = 0.0022;
  g.nx = 275;
  g.ny = 380;
  g.nz = 36;
  return g;
}

const std::vector<sim::PartSpec>& catalogue() {
  static const std::vector<sim::PartSpec> parts = [] {
    auto loaded = app::load_catalogue(CELLSIGHT_SOURCE_DIR "/config/parts.yaml");
    REQUIRE(loaded.ok());
    return *loaded;
  }();
  return parts;
}

const sim::PartSpec& part(const std::string& name) {
  for (const sim::PartSpec& p : catalogue()) {
    if (p.name == name) return p;
  }
  FAIL("no part " << name);
  return catalogue().front();
}

// The simulated cell's placement (SimCell::begin_pass): p_C = n + R_z(theta) R_y(swing) R_x(tilt) p_part + (x, y, z).
Eigen::Vector3d nominal_centre(const sim::PartSpec& spec) {
  const sim::CarrierParams c = sim::default_rig_params().carrier;
  return {0.5 * c.length_m, c.hook_height_m - 0.5e-3 * spec.height_mm, c.part_plane_z_m};
}
Eigen::Isometry3d part_to_carrier(const sim::PartSpec& spec, const sim::PartPose& pose) {
  return Eigen::Translation3d(nominal_centre(spec) + Eigen::Vector3d(pose.x_m, pose.y_m, pose.z_m)) *
         Eigen::AngleAxisd(pose.theta_rad, Eigen::Vector3d::UnitZ()) *
         Eigen::AngleAxisd(pose.swing_rad, Eigen::Vector3d::UnitY()) *
         Eigen::AngleAxisd(pose.tilt_rad, Eigen::Vector3d::UnitX());
}

// A scan of the part's exact surface: every facet sampled on a lattice of about one profile per 2.2 mm along x and
// one row per 1.6 mm along y (the rig's spacing), lattice phase and depth noise from `seed`.
// step_v_m: the row spacing (3.3 mm for a sensor with every second image row, robustness kind "thin").
std::vector<ScanPoint> sample_part(const sim::PartSpec& spec, const sim::PartPose& pose, std::uint64_t seed,
                                   double noise_m = 0.3e-3, double step_v_m = 0.0016) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> phase(0.0, 1.0);
  std::normal_distribution<double> noise(0.0, noise_m);
  const Eigen::Isometry3d to_carrier = part_to_carrier(spec, pose);
  constexpr double kStepU = 0.0022;
  std::vector<ScanPoint> out;
  for (const sim::Facet& f : sim::build_part(spec)) {
    double u0 = 1e9, u1 = -1e9, v0 = 1e9, v1 = -1e9;
    for (const Eigen::Vector2d& q : f.outline) {
      u0 = std::min(u0, q.x());
      u1 = std::max(u1, q.x());
      v0 = std::min(v0, q.y());
      v1 = std::max(v1, q.y());
    }
    const double pu = phase(rng) * kStepU, pv = phase(rng) * step_v_m;
    const int nu = static_cast<int>(std::ceil((u1 - u0 - pu) / kStepU));
    const int nv = static_cast<int>(std::ceil((v1 - v0 - pv) / step_v_m));
    for (int iu = 0; iu < nu; ++iu) {
      const double u = u0 + pu + iu * kStepU;
      for (int iv = 0; iv < nv; ++iv) {
        const double v = v0 + pv + iv * step_v_m;
        if (!f.contains({u, v})) continue;
        const Eigen::Vector3d p = to_carrier * (f.at({u, v}) + noise(rng) * f.normal);
        out.push_back({static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()), 0, 0});
      }
    }
  }
  return out;
}

// A taught template: the scan's occupancy grid, its distance map and surface, its centroid.
struct Template {
  std::string name;
  sim::PartPose pose;
  std::vector<ScanPoint> scan;
  algo::DistanceMap map;
  std::vector<algo::SurfaceCell> surface;
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();
};

std::unique_ptr<Template> teach_from(const std::string& name, const sim::PartPose& pose, std::vector<ScanPoint> scan) {
  auto t = std::make_unique<Template>();
  t->name = name;
  t->pose = pose;
  t->scan = std::move(scan);
  const algo::GridSpec g = test_grid();
  algo::OccupancyGrid occupancy(g, t->scan.size());
  REQUIRE(occupancy.accumulate(t->scan) == 0);
  const algo::GridDims dims{g.nx, g.ny, g.nz, g.resolution_m};
  algo::EdtScratch scratch(dims);
  std::vector<float> work(dims.cell_count());
  REQUIRE(
      algo::build_distance_map(occupancy.data(), dims, g.origin_m, algo::kDefaultBandM, scratch, work.data(), t->map)
          .ok());
  algo::surface_cells_from_map(t->map.view(), t->surface);
  t->centroid_m = algo::centroid_xy_m(t->scan);
  return t;
}

std::unique_ptr<Template> teach(const std::string& name, const sim::PartPose& pose, std::uint64_t seed) {
  return teach_from(name, pose, sample_part(part(name), pose, seed));
}

// A ribbed scan without the foot of each rib's +x wall over `half_length_m` either side of the scan's centre: the
// wall's lower half and the sheet within `strip_mm` of the rib's top, the strip a wall hides from a camera beside it
// in some poses and not in others (the laser's shadow). The sheet's depth is the median; rib tops lie 20 mm above it.
std::vector<ScanPoint> without_wall_foot(std::vector<ScanPoint> scan, float half_length_m, long strip_mm) {
  std::vector<float> depths;
  float cy = 0.0F;
  for (const ScanPoint& p : scan) {
    depths.push_back(p.z);
    cy += p.y;
  }
  cy /= static_cast<float>(scan.size());
  std::nth_element(depths.begin(), depths.begin() + static_cast<std::ptrdiff_t>(depths.size() / 2), depths.end());
  const float sheet = depths[depths.size() / 2];
  std::set<std::pair<long, long>> rib;  // 1 mm x-y map of the rib tops
  for (const ScanPoint& p : scan) {
    if (std::abs(p.z - sheet) > 0.010F) rib.emplace(std::lround(p.x * 1e3F), std::lround(p.y * 1e3F));
  }
  std::erase_if(scan, [&](const ScanPoint& p) {
    if (std::abs(p.y - cy) > half_length_m || std::abs(p.z - sheet) > 0.012F) return false;
    const long x = std::lround(p.x * 1e3F), y = std::lround(p.y * 1e3F);
    for (long d = 1; d <= strip_mm; ++d) {
      for (long dy = -1; dy <= 1; ++dy) {  // rows of points are 1.6 mm apart
        if (rib.count({x - d, y + dy}) != 0) return true;
      }
    }
    return false;
  });
  return scan;
}

// Templates are taught once per process (each ctest run is one process; Catch re-enters a scenario per leaf).
const Template& taught(const std::string& name) {
  static std::map<std::string, std::unique_ptr<Template>> cache;
  auto it = cache.find(name);
  if (it == cache.end()) {
    std::uint64_t seed = 1000;
    for (const char ch : name) seed = seed * 31 + static_cast<unsigned char>(ch);
    it = cache.emplace(name, teach(name, kTaughtPose, seed)).first;
  }
  return *it->second;
}

Eigen::Vector3d mean_point(const std::vector<ScanPoint>& points) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const ScanPoint& p : points) sum += Eigen::Vector3d(p.x, p.y, p.z);
  return sum / static_cast<double>(points.size());
}

TemplateModel model_of(const Template& t, int class_index, int part_id) {
  TemplateModel m;
  m.class_index = class_index;
  m.part_id = part_id;
  m.map = t.map.view();
  m.centroid_m = t.centroid_m;
  m.centroid_z_m = mean_point(t.scan).z();  // c's depth: every accepted decision also refines the full pose
  m.surface_cells = t.surface;
  return m;
}

// DESIGN.md's pose of a scan taken at `scan` relative to a template taught at `taught` (swing left out: the planar
// pose does not model it): p_scan = c + R(dtheta)(p_template - c) + t.
// `spec`: the taught part's (a part outside the catalogue; the other overload looks it up by the template's name).
PlanarPose true_relative_pose(const sim::PartSpec& spec, const Template& taught, const sim::PartPose& scan) {
  const Eigen::Vector2d n = nominal_centre(spec).head<2>();
  const Eigen::Vector2d t0(taught.pose.x_m, taught.pose.y_m), t1(scan.x_m, scan.y_m);
  const double dtheta = scan.theta_rad - taught.pose.theta_rad;
  const Eigen::Vector2d c = taught.centroid_m;
  const Eigen::Vector2d t = Eigen::Rotation2Dd(dtheta) * (c - n - t0) + n + t1 - c;
  return {t.x(), t.y(), dtheta};
}
PlanarPose true_relative_pose(const Template& taught, const sim::PartPose& scan) {
  return true_relative_pose(part(taught.name), taught, scan);
}

// Poses of "other passes" of the same part (thesis pose range is +-50 mm / +-5 deg; here +-30 mm / +-4 deg so the
// small test grid holds them).
const std::vector<sim::PartPose>& other_poses() {
  static const std::vector<sim::PartPose> poses = {
      {0.021, -0.013, 3.1 * kDeg, 1.6 * kDeg},  {-0.027, 0.018, -3.7 * kDeg, -1.9 * kDeg},
      {0.008, 0.026, 1.2 * kDeg, 0.7 * kDeg},   {-0.015, -0.024, -1.8 * kDeg, 1.1 * kDeg},
      {0.029, 0.004, -2.6 * kDeg, -0.4 * kDeg},
  };
  return poses;
}

algo::PerfectMatchParams pm_params() {
  return algo::PerfectMatchParams{};
}

// Learns a template's thresholds the way training does: its own class's scans at the other poses.
algo::TemplateThresholds learn(Cascade& cascade, const TemplateModel& model, const std::string& name,
                               std::uint64_t seed_base) {
  std::vector<MatchReport> reports;
  for (std::size_t i = 0; i < other_poses().size(); ++i) {
    const auto scan = sample_part(part(name), other_poses()[i], seed_base + i);
    reports.push_back(cascade.evaluate(model, scan));
  }
  return algo::learn_thresholds(reports, cascade.params());
}

// A report that passes every gate but the size's and the edges': its bottom and top edges beyond the template's by
// these, its height their sum, its width and side edges the template's.
MatchReport bottom_top_report(double bottom_m, double top_m) {
  MatchReport r;
  r.pm.error = 0.0;
  r.coverage = 1.0;
  r.scan_outliers = 0.0;
  r.edge_m = {0.0, 0.0, bottom_m, top_m};
  r.size_dx_m = 0.0;
  r.size_dy_m = bottom_m + top_m;
  return r;
}

}  // namespace

// ---------------------------------------------------------------------------------------------------------------------

TEST_CASE("surface_cells_from_map returns exactly the occupied cells", "[cascade]") {
  // Given a small random occupancy grid and its map
  const algo::GridDims dims{23, 17, 11, 0.003};
  const Eigen::Vector3d origin(0.1, -0.2, 0.05);
  std::vector<std::uint8_t> occupied(dims.cell_count(), 0);
  std::mt19937 rng(7);
  std::set<std::tuple<int, int, int>> truth;
  for (int i = 0; i < 60; ++i) {
    const int x = static_cast<int>(rng() % 23), y = static_cast<int>(rng() % 17), z = static_cast<int>(rng() % 11);
    occupied[dims.index(x, y, z)] = 1;
    truth.insert({x, y, z});
  }
  algo::EdtScratch scratch(dims);
  std::vector<float> work(dims.cell_count());
  algo::DistanceMap map;
  REQUIRE(algo::build_distance_map(occupied.data(), dims, origin, 0.006, scratch, work.data(), map).ok());
  // When its surface cells are recovered
  std::vector<algo::SurfaceCell> surface;
  algo::surface_cells_from_map(map.view(), surface);
  // Then they are the occupied cells, each once
  std::set<std::tuple<int, int, int>> found;
  for (const algo::SurfaceCell& c : surface) found.insert({c.x, c.y, c.z});
  CHECK(surface.size() == truth.size());
  CHECK(found == truth);
}

TEST_CASE("learn_thresholds takes the own-class maxima times the factor plus the floor", "[cascade]") {
  CascadeParams p;
  p.error_factor = 2.0;
  p.error_floor = 1e-4;
  p.area_factor = 1.5;
  p.area_floor_m2 = 100e-6;
  p.share_factor = 2.0;
  p.share_floor = 0.002;
  std::vector<MatchReport> reports(3);
  reports[0].pm.error = 3e-4;
  reports[0].missing_area_m2 = 20e-6;
  reports[0].extra_area_m2 = 5e-6;
  reports[1].pm.error = 5e-4;
  reports[1].missing_area_m2 = 10e-6;
  reports[1].extra_area_m2 = 40e-6;
  reports[2].pm.error = 1e-4;
  reports[2].missing_area_m2 = 30e-6;
  reports[2].extra_area_m2 = 0.0;
  for (std::size_t i = 0; i < reports.size(); ++i) {
    reports[i].coverage = 1.0 - 1e-4 * static_cast<double>(i);  // uncovered 0, 1e-4, 2e-4
    reports[i].scan_outliers = 3e-4 / static_cast<double>(i + 1);
  }
  const algo::TemplateThresholds t = algo::learn_thresholds(reports, p);
  CHECK(t.max_error == Approx(5e-4 * 2.0 + 1e-4));
  CHECK(t.max_missing_area_m2 == Approx(30e-6 * 1.5 + 100e-6));
  CHECK(t.max_extra_area_m2 == Approx(40e-6 * 1.5 + 100e-6));
  CHECK(t.max_uncovered == Approx(2e-4 * 2.0 + 0.002));
  CHECK(t.max_outliers == Approx(3e-4 * 2.0 + 0.002));
  // A report meets them at the limits and fails just beyond any one of them.
  MatchReport at;
  at.pm.error = t.max_error;
  at.missing_area_m2 = t.max_missing_area_m2;
  at.extra_area_m2 = t.max_extra_area_m2;
  at.coverage = 1.0 - t.max_uncovered * 0.999;
  at.scan_outliers = t.max_outliers;
  CHECK(at.passes(t));
  MatchReport spread = at;
  spread.coverage = 1.0 - t.max_uncovered * 1.01;  // many small blobs, none large
  CHECK_FALSE(spread.passes(t));
  MatchReport outlying = at;
  outlying.scan_outliers = t.max_outliers * 1.01;
  CHECK_FALSE(outlying.passes(t));
  MatchReport unchecked = at;
  unchecked.coverage = std::numeric_limits<double>::quiet_NaN();
  CHECK_FALSE(unchecked.passes(t));
  const algo::TemplateThresholds empty = algo::learn_thresholds({}, p);
  CHECK(empty.max_error == Approx(1e-4));
  CHECK(empty.max_missing_area_m2 == Approx(100e-6));
  CHECK(empty.max_uncovered == Approx(0.002));
}

TEST_CASE("learn_thresholds learns the width's and the height's limits apart", "[cascade][size]") {
  // Catalogue 11002's rnd05 (measured): a 58 mm flange along its right edge projects up to 6 mm more width as the
  // part swings on its hook, its height stays within 1 mm; its twin rnd09 is 5 mm taller.
  CascadeParams p;
  p.size_factor = 1.0;
  p.size_floor_m = 0.0015;
  std::vector<MatchReport> own(12);
  for (std::size_t i = 0; i < own.size(); ++i) {
    own[i].size_dx_m = 0.0007 * static_cast<double>(i);               // 0 .. 7.7 mm wider
    own[i].size_dy_m = 0.0001 * static_cast<double>(i % 5) - 0.0002;  // -0.2 .. +0.2 mm
  }
  const algo::TemplateThresholds t = algo::learn_thresholds(own, p);
  // Centres are the medians (4.2 mm, 0 mm); the limits the own maximum deviation from them plus the floor, or for
  // the width's wide scatter three robust sigmas (1.4826 x the median deviation, 2.1 mm: 9.3 mm).
  CHECK(t.size_centre_x_m == Approx(0.0042));
  CHECK(t.size_centre_y_m == Approx(0.0).margin(1e-9));
  CHECK(t.max_size_dev_x_m == Approx(3.0 * 1.4826 * 0.0021));
  CHECK(t.max_size_dev_y_m == Approx(0.0002 + 0.0015));
  CHECK(t.max_size_dev_m == t.max_size_dev_x_m);
  MatchReport twin = own[3];
  twin.size_dy_m = 0.005;  // the twin: 5 mm taller, its width within the own scatter
  twin.pm.error = 0.0;
  for (MatchReport* r : {&twin, &own[3]}) {
    r->coverage = 1.0;
    r->scan_outliers = 0.0;
  }
  THEN("the twin fails on its height, though its deviation is within the width's limit; the own scan passes") {
    CHECK(t.size_deviation(twin) < t.max_size_dev_x_m);
    CHECK_FALSE(twin.check_passes(t));
    double value = 0.0, limit = 0.0;
    CHECK(algo::first_failed_gate(twin, t, value, limit) == algo::RejectReason::kSize);
    CHECK(value == Approx(0.005));
    CHECK(limit == Approx(t.max_size_dev_y_m));
    CHECK(own[3].check_passes(t));
  }
}

TEST_CASE("learn_thresholds gives the width a profile step of floor, which a few passes turned a little do not show",
          "[cascade][size]") {
  // Fresh catalogue 11350 taught with 5 passes (measured): rnd00's taught widths within 0.44 mm of each other, each
  // pass turned a little so its lines lose different fractions of a profile step; a fresh pass square to the profiles
  // (turned 0.01 deg) came out 2.1 mm narrower, a whole step on every line, against a limit of 1.8 mm.
  const CascadeParams p;  // the defaults: size_floor_m 1.5 mm, size_floor_x_m 2.2 mm
  constexpr std::array<double, 5> kWidthMm = {0.110, -0.285, -0.386, 0.143, -0.057};
  std::vector<MatchReport> own(kWidthMm.size());
  for (std::size_t i = 0; i < own.size(); ++i) {
    own[i] = bottom_top_report(0.0, 0.0);
    own[i].size_dx_m = 0.001 * kWidthMm[i];
  }
  const algo::TemplateThresholds t = algo::learn_thresholds(own, p);
  MatchReport square = own[4];
  square.size_dx_m = -0.002145;
  MatchReport wider = own[4];
  wider.size_dx_m = 0.005 - 0.0022;  // a twin 5 mm wider, as narrow as the sampling makes it
  CHECK(t.max_size_dev_x_m == Approx(0.001 * (0.386 - 0.057) + p.size_floor_x_m));  // about the median, -0.057
  CHECK(square.check_passes(t));
  double value = 0.0, limit = 0.0;
  CHECK(algo::first_failed_gate(wider, t, value, limit) == algo::RejectReason::kSize);
  CHECK(t.max_size_dev_y_m == Approx(p.size_floor_m));
}

TEST_CASE("learn_thresholds learns each edge's limit apart, so a clean edge tells a twin a flange's end hides",
          "[cascade][size]") {
  // Catalogue 11301's rnd00 / rnd08 at Perfect Match's pose (measured): rnd08 is 5 mm taller, both have a bent
  // flange along the bottom whose visible end scatters by 5 mm between passes; the clean top edge of rnd00's own
  // passes lay +0.45..+1.64 mm beyond its template, rnd08's passes +2.75..+4.31 mm.
  CascadeParams p;
  p.size_factor = 1.0;
  p.size_floor_m = 0.0015;
  p.edge_floor_m = 0.001;
  const auto top = static_cast<std::size_t>(algo::Edge::kTop);
  const auto bottom = static_cast<std::size_t>(algo::Edge::kBottom);
  std::vector<MatchReport> own(12);
  for (std::size_t i = 0; i < own.size(); ++i) {
    own[i] = bottom_top_report(-0.0012 + 0.00045 * static_cast<double>(i), 0.00045 + 0.0001 * static_cast<double>(i));
  }
  const algo::TemplateThresholds t = algo::learn_thresholds(own, p);
  // Centres are the medians, limits the own maximum deviation plus the floor, per edge; the flange's wide scatter
  // three robust sigmas (median deviation 1.35 mm: 6.0 mm).
  CHECK(t.edge_centre_m[top] == Approx(0.00045 + 0.0006));
  CHECK(t.max_edge_dev_m[top] == Approx(0.0006 + 0.001));
  CHECK(t.max_edge_dev_m[bottom] == Approx(3.0 * 1.4826 * 0.00135));
  MatchReport twin = own[4];
  twin.edge_m[top] = 0.0028;  // the twin's clean edge: 1.75 mm beyond the centre
  twin.size_dy_m = twin.edge_m[bottom] + twin.edge_m[top];
  THEN("the twin's height is within the flange's scatter, its top edge is not; the own scans pass") {
    CHECK_FALSE(t.size_beyond(twin));
    CHECK_FALSE(twin.check_passes(t));
    double value = 0.0, limit = 0.0;
    CHECK(algo::first_failed_gate(twin, t, value, limit) == algo::RejectReason::kEdge);
    CHECK(value == Approx(0.0028 - 0.00105));
    CHECK(limit == Approx(t.max_edge_dev_m[top]));
    for (const MatchReport& r : own) CHECK(r.check_passes(t));
  }
  THEN("an edge its own scans never measured does not fail a scan that measures it") {
    std::vector<MatchReport> unmeasured = own;
    for (MatchReport& r : unmeasured) r.edge_m[top] = std::numeric_limits<double>::quiet_NaN();
    const algo::TemplateThresholds u = algo::learn_thresholds(unmeasured, p);
    CHECK(u.max_edge_dev_m[top] >= 1.0);
    CHECK(twin.check_passes(u));
  }
}

TEST_CASE("learn_thresholds takes a flange end's scatter to its tail, and keeps a clean edge's limit tight",
          "[cascade][size]") {
  // Fresh catalogue 11345's rnd03 under `mixed` (measured at Perfect Match's pose, nine of its taught passes): a
  // bottom flange bent 110 deg, its visible end 2.7 mm either side of the centre; a fresh pass (s1130009) had its
  // bottom edge 4.05 mm short and its height 5.0 mm off its centre, against limits of 3.5 and 4.2 mm from the taught
  // passes' maxima. Its clean top edge lay within 0.4 mm of its centre.
  const CascadeParams p;  // the defaults: size_factor 1, size_floor_m 1.5 mm, edge_floor_m 0.8 mm
  const auto top = static_cast<std::size_t>(algo::Edge::kTop);
  const auto bottom = static_cast<std::size_t>(algo::Edge::kBottom);
  constexpr std::array<double, 9> kBottomMm = {0.003, 1.974, 2.411, -0.825, 1.652, 2.989, -2.080, -1.092, -1.549};
  constexpr std::array<double, 9> kTopMm = {1.011, 0.885, 1.133, 0.759, 1.452, 1.105, 1.107, 1.101, 1.290};
  std::vector<MatchReport> own(kBottomMm.size());
  for (std::size_t i = 0; i < own.size(); ++i) own[i] = bottom_top_report(0.001 * kBottomMm[i], 0.001 * kTopMm[i]);
  const algo::TemplateThresholds t = algo::learn_thresholds(own, p);
  MatchReport fresh = own[0];
  fresh.edge_m[bottom] = -0.004054;
  fresh.edge_m[top] = 0.000482;
  fresh.size_dy_m = fresh.edge_m[bottom] + fresh.edge_m[top];
  MatchReport twin = own[4];  // 5 mm taller: 2.5 mm beyond at either end
  twin.edge_m[bottom] += 0.0025;
  twin.edge_m[top] += 0.0025;
  twin.size_dy_m += 0.005;
  THEN("the fresh pass meets the flange's limits, which lie beyond the taught passes' maxima plus the floor") {
    double largest = 0.0;
    for (const MatchReport& r : own) largest = std::max(largest, std::abs(r.edge_m[bottom] - t.edge_centre_m[bottom]));
    CHECK(t.max_edge_dev_m[bottom] > largest + p.edge_floor_m);
    CHECK(fresh.check_passes(t));
    for (const MatchReport& r : own) CHECK(r.check_passes(t));
  }
  THEN("the clean top edge's limit is its own maximum plus the floor (widened for 9 scans), and the twin fails on it") {
    // (A one-sided normal tolerance bound's factor for 9 scans against 12's: 4.143 / 3.747.)
    CHECK(t.max_edge_dev_m[top] == Approx(std::abs(0.001452 - t.edge_centre_m[top]) + p.edge_floor_m * 4.143 / 3.747));
    double value = 0.0, limit = 0.0;
    CHECK(algo::first_failed_gate(twin, t, value, limit) == algo::RejectReason::kEdge);
    CHECK(limit == Approx(t.max_edge_dev_m[top]));
  }
}

TEST_CASE("learn_thresholds widens an edge's floor for few taught passes, and a twin with its holes moved still fails",
          "[cascade][size]") {
  // Fresh catalogue 11379, 5 passes taught: rnd02's five passes had their clean edges within 0.4 mm of the centre, and
  // a fresh pass turned 6.6 deg was unknown by its bottom edge 1.13 mm off against a limit of 0.91 mm (0.11 mm + the
  // 0.8 mm floor); its other fresh passes scattered to 0.85 mm. Five values like the taught ones (illustrative):
  const CascadeParams p;  // the defaults: edge_floor_m 0.8 mm, size_floor_m 1.5 mm
  const auto bottom = static_cast<std::size_t>(algo::Edge::kBottom);
  const auto top = static_cast<std::size_t>(algo::Edge::kTop);
  constexpr std::array<double, 5> kBottomMm = {0.0, 0.05, -0.06, 0.11, -0.03};
  auto taught = [&](std::size_t count) {
    std::vector<MatchReport> own;
    for (std::size_t i = 0; i < count; ++i) own.push_back(bottom_top_report(0.001 * kBottomMm[i % 5], 0.0));
    return own;
  };
  MatchReport fresh = bottom_top_report(0.00113, 0.0);
  MatchReport moved = bottom_top_report(0.0025, -0.0025);  // a twin with its holes 2.5 mm lower: same size
  WHEN("five passes are taught") {
    const algo::TemplateThresholds t = algo::learn_thresholds(taught(5), p);
    THEN("the bottom edge's limit is the largest deviation plus the floor x k(5) / k(12) = 5.741 / 3.747") {
      CHECK(t.max_edge_dev_m[bottom] == Approx(0.00011 + p.edge_floor_m * 5.741 / 3.747).margin(1e-6));
      CHECK(fresh.check_passes(t));
      double value = 0.0, limit = 0.0;
      CHECK(algo::first_failed_gate(moved, t, value, limit) == algo::RejectReason::kEdge);
      CHECK(value == Approx(0.0025).margin(0.0001));
    }
    THEN("the size's floor is not widened: the height's limit is the largest deviation plus its floor") {
      CHECK(t.max_size_dev_y_m == Approx(0.00011 + p.size_floor_m).margin(1e-6));
    }
  }
  WHEN("twelve passes are taught (the same values) or more") {
    for (std::size_t count : {12U, 20U}) {
      const algo::TemplateThresholds t = algo::learn_thresholds(taught(count), p);
      CHECK(t.max_edge_dev_m[bottom] == Approx(0.00011 + p.edge_floor_m).margin(1e-6));
      CHECK(t.max_edge_dev_m[top] == Approx(p.edge_floor_m).margin(1e-6));
    }
  }
}

TEST_CASE("learn_thresholds follows an edge that moves with the swing, so its limit stays tight for a twin",
          "[cascade][size]") {
  // Catalogue 11315's rnd03 (measured, 56 mm flanges left and right): the right edge, where the right flange's laser
  // shadow ends, came out 1.0 mm - 80 mm x the depth slope along x (the swing against the template's) within
  // 0.5 mm; its left edge did not follow the slope. A twin 2.5 mm wider on the right hides in a +-5 mm scatter about
  // one centre, not about the line.
  CascadeParams p;
  p.edge_floor_x_m = 0.0015;
  const auto left = static_cast<std::size_t>(algo::Edge::kLeft);
  const auto right = static_cast<std::size_t>(algo::Edge::kRight);
  p.area_factor = 1.0;
  constexpr double kGain = -0.08;
  constexpr std::size_t kGlare = 5;  // a scan whose right edge glare cut 4 mm short
  std::vector<MatchReport> own(12);
  for (std::size_t i = 0; i < own.size(); ++i) {
    MatchReport& r = own[i];
    r.pm.error = 0.0;
    r.coverage = 1.0;
    r.scan_outliers = 0.0;
    r.depth_slope_x = -0.06 + 0.011 * static_cast<double>(i);                  // -0.06 .. +0.061 (+-3.5 deg)
    const double wobble = 0.0002 * static_cast<double>((i * 7) % 5) - 0.0004;  // -0.4 .. +0.4 mm, not in the slope
    r.edge_m = {wobble, 0.001 + kGain * r.depth_slope_x - 0.5 * wobble, 0.0, 0.0};
    r.missing_area_m2 = 40e-6 + 5e-6 * static_cast<double>(i % 3);
    if (i == kGlare) {  // (its missing area flags it: an edge alone never does, see learn_thresholds)
      r.edge_m[right] -= 0.004;
      r.missing_area_m2 = 2000e-6;
    }
    r.size_dx_m = r.edge_m[left] + r.edge_m[right];
    r.size_dy_m = 0.0;
  }
  const algo::ThresholdLearning learnt = algo::learn_thresholds(own, {}, p);
  const algo::TemplateThresholds& t = learnt.thresholds;
  MatchReport twin = own[6];  // swung as own[6], 2.5 mm wider on the right
  twin.edge_m[right] += 0.0025;
  twin.size_dx_m += 0.0025;
  THEN("the right edge's centre follows the slope, the left edge's does not; the glare scan is flagged") {
    CHECK(t.edge_gain_m[right] == Approx(kGain).margin(0.005));
    CHECK(t.edge_gain_m[left] == 0.0);
    CHECK(t.max_edge_dev_median_m[right] == 0.0);  // the line explains it: no band about the median beside it
    CHECK(t.max_edge_dev_m[right] < 0.0005 + p.edge_floor_x_m);
    CHECK(learnt.flagged == std::vector<int>{static_cast<int>(kGlare)});
    for (std::size_t i = 0; i < own.size(); ++i) {
      if (i != kGlare) CHECK(own[i].check_passes(t));
    }
  }
  THEN("the twin fails on its width and its right edge; learnt without the slopes, both pass") {
    double value = 0.0, limit = 0.0;
    CHECK(algo::first_failed_gate(twin, t, value, limit) == algo::RejectReason::kSize);  // (the first gate of the two)
    CHECK(value == Approx(0.0025).margin(0.0005));
    CHECK(t.edge_beyond(twin));
    std::vector<MatchReport> level = own;
    for (MatchReport& r : level) r.depth_slope_x = 0.0;
    const algo::TemplateThresholds centred = algo::learn_thresholds(level, p);
    CHECK(centred.edge_gain_m[right] == 0.0);
    MatchReport level_twin = twin;
    level_twin.depth_slope_x = 0.0;
    CHECK(level_twin.check_passes(centred));
  }
}

TEST_CASE("learn_thresholds keeps the band about the median beside a line that explains an edge only in part",
          "[cascade][size]") {
  // The shipped channel_u (measured, 12 taught passes of the glare set on eval seeds 1140001..): its left edge, where
  // the left flange's laser shadow ends, follows the swing as a step (-2.3..-0.5 mm at slopes 0-0.006, +0.9..+2.1 mm
  // at 0.046-0.088); its right edge follows it as a line. A fresh pass at a slope of 0.0947 measured its left edge
  // at -0.7 mm, where the line through the taught passes says +2.6 mm: 3.3 mm off against a 3.0 mm limit.
  CascadeParams p;
  const auto left = static_cast<std::size_t>(algo::Edge::kLeft);
  const auto right = static_cast<std::size_t>(algo::Edge::kRight);
  constexpr std::array<double, 12> kSlope = {0.0654, 0.0878, 0.0464, 0.0061, 0.0574, 0.0668,
                                             0.0482, 0.0,    0.0861, 0.0754, 0.0491, 0.0029};
  constexpr std::array<double, 12> kLeftMm = {0.936, 0.976,  0.898, -0.454, 1.455, 2.051,
                                              1.223, -2.266, 2.009, 1.494,  1.049, -1.660};
  constexpr std::array<double, 12> kRightMm = {-2.824, -5.191, -2.100, 0.400,  -2.024, -3.894,
                                               -1.969, 2.220,  -6.030, -4.165, -1.611, 1.766};
  auto pass = [](double slope, double left_mm, double right_mm) {
    MatchReport r = bottom_top_report(0.0, 0.0);
    r.depth_slope_x = slope;
    r.edge_m[static_cast<std::size_t>(algo::Edge::kLeft)] = 0.001 * left_mm;
    r.edge_m[static_cast<std::size_t>(algo::Edge::kRight)] = 0.001 * right_mm;
    r.size_dx_m = 0.001 * (left_mm + right_mm);
    return r;
  };
  std::vector<MatchReport> own;
  for (std::size_t i = 0; i < kSlope.size(); ++i) own.push_back(pass(kSlope[i], kLeftMm[i], kRightMm[i]));
  const algo::TemplateThresholds t = algo::learn_thresholds(own, p);
  REQUIRE(t.edge_gain_m[left] > 0.02);  // both edges keep their lines
  REQUIRE(t.edge_gain_m[right] < -0.05);
  const MatchReport fresh = pass(0.0947, -0.703, -4.136);
  THEN("the fresh pass is off the left edge's line but within the taught passes' scatter, and passes") {
    CHECK(std::abs(fresh.edge_m[left] - t.edge_centre_at(left, fresh)) > t.max_edge_dev_m[left]);
    CHECK(t.max_edge_dev_median_m[left] > 0.0);
    CHECK(fresh.check_passes(t));
    for (const MatchReport& r : own) CHECK(r.check_passes(t));
  }
  THEN("the right edge, which its line explains, has no band; an edge beyond both the line and the band fails") {
    CHECK(t.max_edge_dev_median_m[right] == 0.0);
    // Swung as the most swung taught passes, 0.5 mm short of the band's end (and 6 mm short of the line's centre).
    // As wide as the taught passes at that swing: the left edge is the first gate it fails.
    MatchReport beyond = pass(0.088, 1000.0 * (t.edge_median_m[left] - t.max_edge_dev_median_m[left]) - 0.5, -5.0);
    beyond.size_dx_m = t.size_centre_x_at(beyond);
    double value = 0.0, limit = 0.0;
    CHECK(algo::first_failed_gate(beyond, t, value, limit) == algo::RejectReason::kEdge);
    CHECK(limit == Approx(t.max_edge_dev_m[left]));
    CHECK(value - limit == Approx(0.0005).margin(1e-6));  // by as much as it exceeds the nearer of the two
  }
}

SCENARIO("A slot along a rib is a hole of its own, not the rib's laser shadow", "[cascade][two-way][shadow]") {
  // Catalogue 11102's rnd01 / rnd05 (measured: every rnd01 pass ambiguous against rnd05): rnd05 is rnd01 plus a
  // 126 x 30 mm slot 1.5 mm from a 13 mm rib. Here a vertical rib and the slot on its +x side, where the rib's
  // laser shadow falls in the template's own scan.
  sim::PartSpec with_slot;
  with_slot.name = "rib_slot";
  with_slot.width_mm = 400;
  with_slot.height_mm = 600;
  sim::FeatureSpec rib;
  rib.kind = sim::FeatureKind::kRib;
  rib.x_mm = -50;
  rib.width_mm = 35;  // x -67.5 .. -32.5
  rib.length_mm = 500;
  rib.rise_mm = 13;
  rib.vertical = true;
  sim::FeatureSpec slot;
  slot.kind = sim::FeatureKind::kSlot;
  slot.x_mm = -16;  // x -31 .. -1: 1.5 mm from the rib
  slot.width_mm = 30;
  slot.height_mm = 126;
  slot.vertical = true;
  with_slot.features = {rib, slot};
  sim::PartSpec without_slot = with_slot;
  without_slot.name = "rib_no_slot";
  without_slot.features = {rib};
  REQUIRE(sim::validate_part(with_slot).empty());
  // The template of the slotted part from a scan without the foot of its rib's +x wall (the shadow).
  const auto taught_scan = without_wall_foot(sample_part(with_slot, kTaughtPose, 71), 0.28F, 8);
  const std::unique_ptr<Template> t = teach_from("rib_slot", kTaughtPose, taught_scan);
  const PlanarPose at = true_relative_pose(with_slot, *t, kTestPose);
  Cascade cascade(CascadeParams{}, pm_params(), test_grid());
  const double slot_m2 = 0.030 * 0.126;
  WHEN("the twin without the slot is checked against the slotted template, and the slotted part's own scan") {
    const MatchReport twin = cascade.two_way_check(model_of(*t, 0, 1), sample_part(without_slot, kTestPose, 72), at);
    const MatchReport own = cascade.two_way_check(model_of(*t, 0, 1), sample_part(with_slot, kTestPose, 73), at);
    THEN("the twin's material where the slot is counts as extra in full; the own scan shows none") {
      INFO("twin: extra " << twin.extra_area_m2 * 1e6 << " missing " << twin.missing_area_m2 * 1e6
                          << " mm^2; own: extra " << own.extra_area_m2 * 1e6 << " mm^2; slot " << slot_m2 * 1e6
                          << " mm^2");
      CHECK(twin.extra_area_m2 > 0.6 * slot_m2);
      CHECK(own.extra_area_m2 < 0.05 * slot_m2);
    }
  }
}

SCENARIO("The two-way check sees one hole more or less in both directions and the same part at other poses passes",
         "[cascade][two-way]") {
  GIVEN("templates of plate_4h and plate_5h (= plate_4h + one 40 mm centre hole), taught at one pose") {
    const Template* t4 = &taught("plate_4h");
    const Template* t5 = &taught("plate_5h");
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    // What a hole leaves: the template cells whose window (a square of half-side h = (r + 1/2) cells around the
    // cell) lies wholly inside the hole, i.e. the disc eroded by that square: between the discs of radius
    // R - sqrt(2) h and R - h, one cell of rasterisation either way.
    const double cell = test_grid().resolution_m;
    const double h = (cascade.window_cells() + 0.5) * cell;
    const double hole_min_m2 = std::numbers::pi * std::pow(kHoleRadiusM - std::numbers::sqrt2 * h - cell, 2);
    const double hole_max_m2 = std::numbers::pi * std::pow(kHoleRadiusM - h + cell, 2);

    WHEN("a plate_5h scan is checked against the plate_4h template at the true pose (the scan LACKS material)") {
      const auto scan = sample_part(part("plate_5h"), kTestPose, 21);
      const MatchReport r = cascade.two_way_check(model_of(*t4, 0, 1), scan, true_relative_pose(*t4, kTestPose));
      THEN("the template area it misses is the hole's disc shrunk by the window, and nothing is extra") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm^2, extra " << r.extra_area_m2 * 1e6 << " mm^2, expected "
                        << hole_min_m2 * 1e6 << ".." << hole_max_m2 * 1e6);
        CHECK(r.missing_area_m2 >= hole_min_m2);
        CHECK(r.missing_area_m2 <= hole_max_m2);
        CHECK(r.extra_area_m2 < 20e-6);
        CHECK(r.coverage < 1.0);
        CHECK(r.coverage > 0.98);
      }
    }
    WHEN("a plate_4h scan is checked against the plate_5h template at the true pose (the scan has EXTRA material)") {
      const auto scan = sample_part(part("plate_4h"), kTestPose, 22);
      const MatchReport r = cascade.two_way_check(model_of(*t5, 0, 1), scan, true_relative_pose(*t5, kTestPose));
      THEN("the extra area is the whole hole the scan covers (its disc to a cell), and nothing is missing") {
        const double disc_min_m2 = std::numbers::pi * std::pow(kHoleRadiusM - cell, 2);
        const double disc_max_m2 = std::numbers::pi * std::pow(kHoleRadiusM + cell, 2);
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm^2, extra " << r.extra_area_m2 * 1e6 << " mm^2, expected "
                        << disc_min_m2 * 1e6 << ".." << disc_max_m2 * 1e6);
        CHECK(r.extra_area_m2 >= disc_min_m2);
        CHECK(r.extra_area_m2 <= disc_max_m2);
        CHECK(r.missing_area_m2 < 20e-6);
        CHECK(r.scan_outliers > 0.0);
      }
    }
    WHEN("plate_4h and plate_5h scans at five other poses are checked against their own templates") {
      double worst = 0.0;
      for (std::size_t i = 0; i < other_poses().size(); ++i) {
        for (const Template* t : {t4, t5}) {
          const auto scan = sample_part(part(t->name), other_poses()[i], 100 + i);
          const MatchReport r =
              cascade.two_way_check(model_of(*t, 0, 1), scan, true_relative_pose(*t, other_poses()[i]));
          INFO(t->name << " pose " << i << ": missing " << r.missing_area_m2 * 1e6 << " mm^2, extra "
                       << r.extra_area_m2 * 1e6 << " mm^2, depth slope " << r.depth_slope_x);
          worst = std::max({worst, r.missing_area_m2, r.extra_area_m2});
          CHECK(r.coverage > 0.99);
          CHECK(r.scan_outliers < 0.01);
          // The swing difference (up to 2.4 deg) is a depth slope the levelling finds: -tan(dswing).
          CHECK(r.depth_slope_x == Approx(-std::tan(other_poses()[i].swing_rad - kTaughtPose.swing_rad)).margin(0.004));
        }
      }
      THEN("every blob stays a small fraction of the one-hole difference") {
        INFO("worst own-class blob " << worst * 1e6 << " mm^2, one hole >= " << hole_min_m2 * 1e6 << " mm^2");
        CHECK(worst < 0.1 * hole_min_m2);
      }
    }
  }
}

SCENARIO("The two-way check sees one pressed rib more or less, which a flat x-y mask cannot", "[cascade][two-way]") {
  GIVEN("templates of ribbed_v4 and ribbed_v3 (= ribbed_v4 without its right-most rib)") {
    const Template* t4 = &taught("ribbed_v4");
    const Template* t3 = &taught("ribbed_v3");
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    // The rib's top (20 mm wide, 560 mm long, 20 mm proud) is certainly off by more than the depth tolerance.
    const double rib_top_m2 = (0.020 - 2 * cascade.window_cells() * test_grid().resolution_m) * 0.560;
    WHEN("each scan is checked against the other template at the true pose") {
      const auto scan3 = sample_part(part("ribbed_v3"), kTestPose, 41);
      const auto scan4 = sample_part(part("ribbed_v4"), kTestPose, 42);
      const MatchReport v3_on_v4 =
          cascade.two_way_check(model_of(*t4, 0, 1), scan3, true_relative_pose(*t4, kTestPose));
      const MatchReport v4_on_v3 =
          cascade.two_way_check(model_of(*t3, 0, 1), scan4, true_relative_pose(*t3, kTestPose));
      THEN("both directions show a rib-sized blob of missing and of extra surface") {
        INFO("v3 scan on v4: missing " << v3_on_v4.missing_area_m2 * 1e6 << " extra " << v3_on_v4.extra_area_m2 * 1e6
                                       << "; v4 scan on v3: missing " << v4_on_v3.missing_area_m2 * 1e6 << " extra "
                                       << v4_on_v3.extra_area_m2 * 1e6 << " mm^2; rib top " << rib_top_m2 * 1e6);
        CHECK(v3_on_v4.missing_area_m2 > rib_top_m2);
        CHECK(v3_on_v4.extra_area_m2 > rib_top_m2);
        CHECK(v4_on_v3.missing_area_m2 > rib_top_m2);
        CHECK(v4_on_v3.extra_area_m2 > rib_top_m2);
      }
    }
    WHEN("the ribbed_v4 scan has a glare band across all ribs that leaves 3 % of the points, checked against v3") {
      float cy = 0.0F;
      auto scan4 = sample_part(part("ribbed_v4"), kTestPose, 43);
      for (const ScanPoint& p : scan4) cy += p.y;
      cy /= static_cast<float>(scan4.size());
      std::mt19937_64 rng(44);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      std::erase_if(scan4, [&](const ScanPoint& p) { return std::abs(p.y - cy) < 0.012 && u(rng) >= 0.03; });
      const MatchReport r = cascade.two_way_check(model_of(*t3, 0, 1), scan4, true_relative_pose(*t3, kTestPose));
      THEN("the rib it lacks still counts fully: depths that disagree are contradiction, never lost data") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " extra " << r.extra_area_m2 * 1e6 << " mm^2; rib top "
                        << rib_top_m2 * 1e6);
        CHECK(r.missing_area_m2 + r.extra_area_m2 > rib_top_m2);
      }
    }
    WHEN("the ribbed_v4 scan lacks the foot of each rib's +x wall over 100 mm (a laser shadow), or has a hole there") {
      const auto clean = sample_part(part("ribbed_v4"), kTestPose, 45);
      const auto shadow = without_wall_foot(clean, 0.05F, 12);
      const Eigen::Vector2f c = algo::centroid_xy_m(clean).cast<float>();
      const float cx = c.x(), cy = c.y();
      // A 24 mm hole in the sheet between the ribs at +45 mm and +135 mm (sheet from +65 to +115 mm), its rim 3 mm
      // from the first rib's foot.
      auto holed = clean;
      std::erase_if(holed, [&](const ScanPoint& p) { return std::hypot(p.x - cx - 0.080F, p.y - cy) < 0.012F; });
      const PlanarPose at = true_relative_pose(*t4, kTestPose);
      const MatchReport own = cascade.two_way_check(model_of(*t4, 0, 1), shadow, at);
      const MatchReport twin = cascade.two_way_check(model_of(*t3, 0, 1), shadow, true_relative_pose(*t3, kTestPose));
      const MatchReport hole = cascade.two_way_check(model_of(*t4, 0, 1), holed, at);
      const double hole_m2 = std::numbers::pi * 0.012 * 0.012;
      THEN(
          "the shadow weighs nothing and is not lost data that could hide a twin (it would bring every candidate to "
          "verification), the hole beside the wall is missing all the same, the twin's rib counts in full") {
        INFO("shadow: removed " << clean.size() - shadow.size() << " points; own: missing " << own.missing_area_m2 * 1e6
                                << " lost " << own.lost_area_m2 * 1e6 << " mm^2; v3: missing "
                                << twin.missing_area_m2 * 1e6 << " extra " << twin.extra_area_m2 * 1e6
                                << " mm^2; hole: missing " << hole.missing_area_m2 * 1e6 << " lost "
                                << hole.lost_area_m2 * 1e6 << " of " << hole_m2 * 1e6 << " mm^2");
        CHECK(clean.size() - shadow.size() > 1000);
        CHECK(own.lost_area_m2 < 20e-6);
        CHECK(own.missing_area_m2 < 20e-6);
        CHECK(twin.missing_area_m2 + twin.extra_area_m2 > rib_top_m2);
        // (The check's window takes two cells off every rim: what is left of a 24 mm hole is about a quarter.)
        CHECK(hole.missing_area_m2 > 0.2 * hole_m2);
        CHECK(hole.lost_area_m2 < 20e-6);
      }
    }
    WHEN("the template was taught in a pose that hid the foot of each rib's +x wall, and the scan sees it") {
      static const auto shadowed = teach_from(
          "ribbed_v4", kTaughtPose, without_wall_foot(sample_part(part("ribbed_v4"), kTaughtPose, 47), 0.28F, 16));
      // The control: a template with a 24 mm hole beside the +45 mm rib's foot that the scan does not have (the
      // one-hole-more twin), which a rim stepping into the rib must not excuse.
      static const auto holed = [] {
        auto scan = sample_part(part("ribbed_v4"), kTaughtPose, 48);
        const Eigen::Vector2f c = algo::centroid_xy_m(scan).cast<float>();
        const float cx = c.x(), cy = c.y();
        std::erase_if(scan, [&](const ScanPoint& p) { return std::hypot(p.x - cx - 0.078F, p.y - cy) < 0.012F; });
        return teach_from("ribbed_v4", kTaughtPose, std::move(scan));
      }();
      const auto scan = sample_part(part("ribbed_v4"), kTestPose, 49);
      const MatchReport seen =
          cascade.two_way_check(model_of(*shadowed, 0, 1), scan, true_relative_pose(*shadowed, kTestPose));
      const MatchReport covered =
          cascade.two_way_check(model_of(*holed, 0, 1), scan, true_relative_pose(*holed, kTestPose));
      THEN("the wall and its foot in the template's shadow weigh nothing; the covered hole beside the rib counts") {
        INFO("shadowed template: extra " << seen.extra_area_m2 * 1e6 << " missing " << seen.missing_area_m2 * 1e6
                                         << " mm^2, outliers " << seen.scan_outliers << "; holed template: extra "
                                         << covered.extra_area_m2 * 1e6 << " mm^2");
        CHECK(seen.extra_area_m2 < 50e-6);
        CHECK(covered.extra_area_m2 > 0.5 * std::numbers::pi * 0.012 * 0.012);
      }
    }
    WHEN("the same is done with an unbounded depth tolerance (a flat x-y mask)") {
      CascadeParams flat;
      flat.depth_tolerance_m = 1.0;
      flat.per_cell_depth = false;
      Cascade flat_cascade(flat, pm_params(), test_grid());
      const auto scan3 = sample_part(part("ribbed_v3"), kTestPose, 41);
      const MatchReport r = flat_cascade.two_way_check(model_of(*t4, 0, 1), scan3, true_relative_pose(*t4, kTestPose));
      THEN("the difference is invisible: the masks of a ribbed and a flat sheet coincide") {
        CHECK(r.missing_area_m2 < 20e-6);
        CHECK(r.extra_area_m2 < 20e-6);
      }
    }
    WHEN("ribbed scans at other poses are checked against their own templates") {
      for (std::size_t i = 0; i < other_poses().size(); ++i) {
        for (const Template* t : {t4, t3}) {
          const auto scan = sample_part(part(t->name), other_poses()[i], 200 + i);
          const MatchReport r =
              cascade.two_way_check(model_of(*t, 0, 1), scan, true_relative_pose(*t, other_poses()[i]));
          INFO(t->name << " pose " << i << ": missing " << r.missing_area_m2 * 1e6 << " extra "
                       << r.extra_area_m2 * 1e6);
          CHECK(r.missing_area_m2 < 0.1 * rib_top_m2);
          CHECK(r.extra_area_m2 < 0.1 * rib_top_m2);
        }
      }
    }
    WHEN("a plate's rib stands 1.2 mm sideways of where its template has it, and a plate without the rib") {
      // The swing turns a rib's top against its foot (21 mm x sin 2.9 deg: 1.1 mm), and the pose that aligns the
      // sheet leaves that. A flank drops 24 mm over 9 mm, 5.9 mm per cell, one depth per cell as the rig's profiles
      // meet it: 1.2 mm sideways is 3.2 mm in depth, and the next cell is 2.7 mm off the other way, so neither
      // surface has a cell within the fine tolerance of the other's, though both cross that depth (catalogue 11318's
      // rnd01, 21 mm ribs swung 2.9 deg: 348 mm2 missing along their flanks, over its 230 mm2 limit).
      auto ridge_plate = [](double rib_shift_m, bool with_rib) {
        constexpr double kRibX = 0.30, kHalfTop = 0.009, kFlank = 0.009, kRise = 0.024, kSheet = 0.10;
        std::vector<ScanPoint> out;
        for (int k = 55; k < 191; ++k) {  // profiles at the test grid's cell centres, x 0.151 .. 0.449 m
          const double x = test_grid().origin_m.x() + (k + 0.5) * test_grid().resolution_m;
          const double d = std::abs(x - kRibX - rib_shift_m);
          const double rise = !with_rib || d >= kHalfTop + kFlank ? 0.0
                              : d <= kHalfTop                     ? kRise
                                                                  : kRise * (kHalfTop + kFlank - d) / kFlank;
          for (double y = 0.35; y <= 0.75; y += 0.0016) {
            out.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(kSheet + rise), 0, 0});
          }
        }
        return out;
      };
      const auto plate = teach_from("ridge_plate", {}, ridge_plate(0.0, true));
      const MatchReport own = cascade.two_way_check(model_of(*plate, 0, 1), ridge_plate(0.0012, true), {});
      const MatchReport twin = cascade.two_way_check(model_of(*plate, 0, 1), ridge_plate(0.0, false), {});
      THEN("the flanks count as seen; the plate without the rib still misses the rib's top") {
        INFO("own: missing " << own.missing_area_m2 * 1e6 << " extra " << own.extra_area_m2 * 1e6
                             << " mm^2; no rib: missing " << twin.missing_area_m2 * 1e6 << " mm^2");
        CHECK(own.missing_area_m2 < 0.25 * CascadeParams{}.area_floor_m2);
        CHECK(own.extra_area_m2 < 0.25 * CascadeParams{}.area_floor_m2);
        CHECK(twin.missing_area_m2 > (0.018 - 2 * 0.0022) * 0.4);  // the rib's top less a cell either side
      }
    }
  }
}

SCENARIO("The two-way check tells louvres from ribs of the same footprint, which the window's depth range cannot",
         "[cascade][two-way]") {
  GIVEN("a louvred_panel template and its twin with a 15 mm rib wherever the panel has a louvre") {
    // The twin of catalogue 8503's rnd01 / rnd07 pair: the same outline and holes; each louvre (a 30 mm flap opened
    // 35 deg, 17 mm proud at its free edge) replaced by a trapezoidal rib of its footprint. Their depths differ by
    // 2-8 mm over the whole footprint, while within the window's 4.4 mm the flap spans 0-17 mm, so a depth hull admits
    // the rib's everywhere.
    const Template* panel = &taught("louvred_panel");
    sim::PartSpec ribbed = part("louvred_panel");
    for (sim::FeatureSpec& f : ribbed.features) {
      if (f.kind != sim::FeatureKind::kLouvre) continue;
      f.kind = sim::FeatureKind::kRib;
      f.rise_mm = 15.0;
      f.angle_deg = 0.0;
    }
    const double louvre_m2 = 0.030 * 0.150;
    const PlanarPose at = true_relative_pose(*panel, kTestPose);
    WHEN("the ribbed twin's scan is checked against the louvred template at the true pose") {
      const auto scan = sample_part(ribbed, kTestPose, 51);
      Cascade cascade(CascadeParams{}, pm_params(), test_grid());
      const MatchReport r = cascade.two_way_check(model_of(*panel, 0, 1), scan, at);
      CascadeParams hull_only;
      hull_only.per_cell_depth = false;
      Cascade hull_cascade(hull_only, pm_params(), test_grid());
      const MatchReport hull = hull_cascade.two_way_check(model_of(*panel, 0, 1), scan, at);
      THEN("a louvre-sized blob is missing and extra, far over the area floor; the hull alone sees almost nothing") {
        INFO("per cell: missing " << r.missing_area_m2 * 1e6 << " extra " << r.extra_area_m2 * 1e6
                                  << " mm^2; hull only: missing " << hull.missing_area_m2 * 1e6 << " extra "
                                  << hull.extra_area_m2 * 1e6 << " mm^2; louvre " << louvre_m2 * 1e6);
        CHECK(r.missing_area_m2 + r.extra_area_m2 > 0.2 * louvre_m2);
        CHECK(std::max(r.missing_area_m2, r.extra_area_m2) > CascadeParams{}.area_floor_m2);
        CHECK(hull.missing_area_m2 + hull.extra_area_m2 < 0.5 * CascadeParams{}.area_floor_m2);
      }
    }
    WHEN("louvred_panel's own scans at other poses are checked against its template") {
      Cascade cascade(CascadeParams{}, pm_params(), test_grid());
      for (std::size_t i = 0; i < other_poses().size(); ++i) {
        const auto scan = sample_part(part("louvred_panel"), other_poses()[i], 300 + i);
        const MatchReport r =
            cascade.two_way_check(model_of(*panel, 0, 1), scan, true_relative_pose(*panel, other_poses()[i]));
        // (The per-cell depths agree: no blob near the area floor.)
        INFO("pose " << i << ": missing " << r.missing_area_m2 * 1e6 << " extra " << r.extra_area_m2 * 1e6);
        CHECK(r.missing_area_m2 < 0.2 * CascadeParams{}.area_floor_m2);
        CHECK(r.extra_area_m2 < 0.2 * CascadeParams{}.area_floor_m2);
      }
    }
  }
}

TEST_CASE("The outer size resolves a fraction of the profile spacing on a turned part", "[cascade][size]") {
  // Plates 300.9 mm wide plus 0 .. 1.6 mm, turned 2.3 deg, profiles 2.2 mm apart: along the left and right edges the
  // first profile inside lies 0-2.2 mm in, the two gaps moving together, so each row's width takes one of two values
  // a cell apart, in shares set by the width. Their mean follows the width; the value most rows take does not,
  // until the shares tip, and then it jumps by a whole cell.
  constexpr double kWidth = 0.3009, kHeight = 0.400, kSheet = 0.10, kTheta = 2.3 * kDeg;
  const Eigen::Vector2d centre(0.30, 0.55);
  // Profiles every 2.2 mm along x from `phase_m`, rows every 1.6 mm; the plate turned by theta about its centre.
  auto plate = [&](double width, double phase_m, double theta) {
    std::vector<ScanPoint> out;
    const Eigen::Rotation2Dd back(-theta);
    for (double x = 0.10 + phase_m; x < 0.50; x += 0.0022) {
      for (double y = 0.30; y < 0.80; y += 0.0016) {
        const Eigen::Vector2d q = back * (Eigen::Vector2d(x, y) - centre);
        if (std::abs(q.x()) > 0.5 * width || std::abs(q.y()) > 0.5 * kHeight) continue;
        out.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(kSheet), 0, 0});
      }
    }
    return out;
  };
  const auto t = teach_from("turned_plate", {}, plate(kWidth, 0.0011, 0.0));
  Cascade cascade(CascadeParams{}, pm_params(), test_grid());
  // The pose maps the template onto the scan: about the template's centroid, shifted so that the plate's centre
  // stays put.
  const Eigen::Vector2d shift = centre - t->centroid_m - Eigen::Rotation2Dd(kTheta) * (centre - t->centroid_m);
  const PlanarPose at{shift.x(), shift.y(), kTheta};
  auto width_off = [&](double wider) {
    return cascade.two_way_check(model_of(*t, 0, 1), plate(kWidth + wider, 0.0007, kTheta), at).size_dx_m;
  };
  const double base = width_off(0.0);
  REQUIRE(std::isfinite(base));
  for (double wider : {0.0004, 0.0008, 0.0012, 0.0016}) {
    const double seen = width_off(wider) - base;
    INFO(wider * 1e3 << " mm wider: measured " << seen * 1e3 << " mm wider");
    CHECK(seen == Approx(wider).margin(0.0003));
  }
}

SCENARIO("The outer size of a part taught and scanned by a sensor with rows 3.3 mm apart is its own",
         "[cascade][two-way][size]") {
  GIVEN("plate_4h and ribbed_v4 taught from scans with every second row, turned by 0.6 deg") {
    for (const char* name : {"plate_4h", "ribbed_v4"}) {
      const auto t = teach_from(name, kTaughtPose, sample_part(part(name), kTaughtPose, 41, 0.3e-3, 0.0033));
      Cascade cascade(CascadeParams{}, pm_params(), test_grid());
      WHEN(std::string("a scan of ") + name + " as sparse, turned by 2.3 deg, is checked at the true pose") {
        const auto scan = sample_part(part(name), kTestPose, 42, 0.3e-3, 0.0033);
        const MatchReport r = cascade.two_way_check(model_of(*t, 0, 1), scan, true_relative_pose(*t, kTestPose));
        THEN("its width and height differ from the template's by a sampling step at most") {
          // Each line's template extent, not only the scan's, is taken over the line and its two neighbours: a
          // sparse row crosses the template's lines at a slant, and a line alone holds only part of a row (the
          // width came out 13-19 mm short for ribbed_h5 under "thin").
          INFO("size dx " << r.size_dx_m * 1e3 << " dy " << r.size_dy_m * 1e3 << " mm");
          CHECK(std::abs(r.size_dx_m) < 0.0022);
          CHECK(std::abs(r.size_dy_m) < 0.0033);
        }
      }
    }
  }
}

namespace {

// A 300 x 400 mm plate with three holes, `taller_mm` taller, its holes where they were about its centre: the
// random catalogue's "5 mm taller" twin (11301's rnd08 and rnd10 without their flange), each end 2.5 mm further
// out. With `window`, one 100 x 240 mm window instead of the holes (fresh catalogue 11357's rnd09 / rnd11: a window
// of 102 x 240 mm, 5 000 cells, and no hole).
sim::PartSpec twin_plate(double taller_mm, bool window = false) {
  sim::PartSpec p;
  p.name = taller_mm > 0 ? "taller" : "plate";
  p.width_mm = 300;
  p.height_mm = 400 + taller_mm;
  p.features = {sim::FeatureSpec{.kind = sim::FeatureKind::kHole, .x_mm = -80, .y_mm = 100, .diameter_mm = 30},
                sim::FeatureSpec{.kind = sim::FeatureKind::kHole, .x_mm = 90, .y_mm = -60, .diameter_mm = 24},
                sim::FeatureSpec{.kind = sim::FeatureKind::kHole, .x_mm = -40, .y_mm = -120, .diameter_mm = 40}};
  if (window) {
    p.features = {sim::FeatureSpec{
        .kind = sim::FeatureKind::kWindow, .x_mm = -40, .y_mm = -20, .width_mm = 100, .height_mm = 240}};
  }
  REQUIRE(sim::validate_part(p).empty());
  return p;
}

// A scan of `spec` at `pose` whose bottom end is seen `short_mm` short: a flange bent away there leaves an edge
// that moves between passes (11301's rnd00: 0-8 mm, by the pose). With `right_half`, only the half right of the
// part's centre.
std::vector<ScanPoint> with_bottom_seen_short(const sim::PartSpec& spec, const sim::PartPose& pose, std::uint64_t seed,
                                              double short_mm, bool right_half = false) {
  std::vector<ScanPoint> scan = sample_part(spec, pose, seed);
  const Eigen::Isometry3d to_part = part_to_carrier(spec, pose).inverse();
  const double cut_m = 1e-3 * (-0.5 * spec.height_mm + short_mm);
  std::erase_if(scan, [&](const ScanPoint& p) {
    const Eigen::Vector3d q = to_part * Eigen::Vector3d(p.x, p.y, p.z);
    return q.y() < cut_m && (!right_half || q.x() > 0.0);
  });
  return scan;
}

}  // namespace

SCENARIO("A twin 5 mm taller whose other end is seen short by a varying length fails by its clean edge",
         "[cascade][two-way][size]") {
  const std::array<double, 5> short_mm = {0.0, 6.0, 2.0, 8.0, 4.0};  // per other pose
  const sim::PartPose test_pose{0.012, -0.021, -1.4 * kDeg, 0.9 * kDeg};
  const bool window = GENERATE(false, true);
  GIVEN(std::string("a plate and its twin 5 mm taller, with ") + (window ? "one window" : "three holes") +
        ", each taught and learnt from its own scans at five other poses") {
    const sim::PartSpec plate = twin_plate(0.0, window), taller = twin_plate(5.0, window);
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    std::vector<std::unique_ptr<Template>> templates;
    std::vector<TemplateModel> models;
    for (const sim::PartSpec* spec : {&plate, &taller}) {
      templates.push_back(teach_from(spec->name, kTaughtPose, with_bottom_seen_short(*spec, kTaughtPose, 51, 3.0)));
      TemplateModel m = model_of(*templates.back(), static_cast<int>(models.size()), 1);
      std::vector<MatchReport> own;
      for (std::size_t i = 0; i < other_poses().size(); ++i) {
        own.push_back(cascade.evaluate(m, with_bottom_seen_short(*spec, other_poses()[i], 520 + i, short_mm[i])));
      }
      m.thresholds = algo::learn_thresholds(own, cascade.params());
      models.push_back(m);
    }
    // (Seen about 3.5 mm short, the height of either lies within the other's scatter; farther off, the size tells.)
    // A window holds the scan's place as holes do (edges_against_holes takes pieces up to a window 240 mm square).
    // In this scene its centre, like the holes', scatters by ~1.6 mm between poses, so the clean top edge does not
    // always tell the twin there (2.40 against 2.44 mm at theta -1.4 deg): then both pass, and the decision is
    // unknown, never the twin.
    WHEN("a scan of each at two new poses, its bottom seen 3.5 mm short, is checked against both templates") {
      const char* then = window
                             ? "its edges are measured, it passes its own template, and the decision is never its twin"
                             : "it passes its own template and fails its twin's by an edge, its height within the "
                               "twin's scatter";
      THEN(then) {
        for (const sim::PartPose& pose : {test_pose, kTestPose}) {
          for (std::size_t s = 0; s < 2; ++s) {
            const sim::PartSpec& spec = s == 0 ? plate : taller;
            const auto scan = with_bottom_seen_short(spec, pose, 530, 3.5);
            const MatchReport own = cascade.evaluate(models[s], scan);
            const MatchReport other = cascade.evaluate(models[1 - s], scan);
            const algo::TemplateThresholds& ot = models[1 - s].thresholds;
            const auto top = static_cast<std::size_t>(algo::Edge::kTop);
            CHECK(own.passes(models[s].thresholds));
            if (window) {
              CHECK(std::isfinite(own.edge_m[top]));
              CHECK(std::isfinite(other.edge_m[top]));
              // The SVM ranking the twin first.
              const ClassProbability svm[] = {{static_cast<int>(1 - s), 0.6}, {static_cast<int>(s), 0.4}};
              const Decision d = cascade.decide(svm, models, scan, Clock::now() + std::chrono::seconds(60));
              INFO("decided " << d.class_index << " (" << algo::to_string(d.source) << ") for " << s);
              CHECK(d.class_index != static_cast<int>(1 - s));
              continue;
            }
            double value = 0.0, limit = 0.0;
            const algo::RejectReason reason = algo::first_failed_gate(other, ot, value, limit);
            INFO(spec.name << " at theta " << pose.theta_rad / kDeg << " deg: the other template's height deviation "
                           << std::abs(other.size_dy_m - ot.size_centre_y_m) * 1e3 << " mm (limit "
                           << ot.max_size_dev_y_m * 1e3 << "), its top edge " << other.edge_m[top] * 1e3
                           << " mm (centre " << ot.edge_centre_m[top] * 1e3 << ", limit "
                           << ot.max_edge_dev_m[top] * 1e3 << "); reason " << algo::to_string(reason));
            CHECK_FALSE(ot.size_beyond(other));
            CHECK(reason == algo::RejectReason::kEdge);
          }
        }
      }
    }
  }
}

SCENARIO("A strip missing along part of an edge is missing material, even where the holes measure the edge",
         "[cascade][two-way][evidence]") {
  // A twin without a tab, or with a step in one edge, differs from its sibling only there. The edge's measure is a
  // robust mean over the whole edge and barely moves (0.2 mm here), so the strip itself must count: weighing thin
  // strips along measured edges weakly (tried for a flange's end a rare pose sees short) let such a twin pass.
  GIVEN("the plate with three holes, and the same plate without holes, each taught") {
    sim::PartSpec plain = twin_plate(0.0);
    plain.name = "plain";
    plain.features.clear();
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    // The right half of the bottom end `short_mm` short.
    auto scan_of = [](const sim::PartSpec& spec, double short_mm) {
      return with_bottom_seen_short(spec, kTestPose, 540, short_mm, true);
    };
    for (const bool holes : {true, false}) {
      const sim::PartSpec spec = holes ? twin_plate(0.0) : plain;
      const auto t = teach_from(spec.name, kTaughtPose, sample_part(spec, kTaughtPose, 51));
      const TemplateModel m = model_of(*t, 0, 1);
      const PlanarPose at = true_relative_pose(spec, *t, kTestPose);
      WHEN(spec.name + ": a scan lacks a 7 mm strip along the right half of its bottom end") {
        const MatchReport r = cascade.two_way_check(m, scan_of(spec, 7.0), at);
        const MatchReport clean = cascade.two_way_check(m, scan_of(spec, 0.0), at);
        const auto bottom = static_cast<std::size_t>(algo::Edge::kBottom);
        THEN("the strip beyond the check's window counts as missing, whatever the edge's measure says") {
          INFO("missing " << r.missing_area_m2 * 1e6 << " mm^2 (clean " << clean.missing_area_m2 * 1e6
                          << "), bottom edge " << r.edge_m[bottom] * 1e3 << " mm (clean " << clean.edge_m[bottom] * 1e3
                          << ")");
          CHECK(std::isfinite(r.edge_m[bottom]) == holes);
          CHECK(clean.missing_area_m2 < 30e-6);
          CHECK(r.missing_area_m2 > 200e-6);
        }
      }
    }
  }
}

SCENARIO("The holes place the edges by the profiles' chords through them, which a dropout run at a rim moves little",
         "[cascade][two-way][size]") {
  GIVEN("a plate with three holes, taught at one pose, and scans of it at other poses") {
    const sim::PartSpec plate = twin_plate(0.0);
    const auto t = teach_from(plate.name, kTaughtPose, sample_part(plate, kTaughtPose, 61));
    const TemplateModel m = model_of(*t, 0, 1);
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    // Runs of points lost along two neighbouring profiles right above each hole's rim, on the hole's left half (the
    // robustness kind "dropout" loses runs of 2-6 points along a profile; louvred_panel's s1070008 under "mixed" had
    // such a tail, 3 rows by 2-3 columns, on a 20 mm hole): the piece of empty cells grows a tail at its top.
    auto with_runs_above_rims = [&](std::vector<ScanPoint> scan, const sim::PartPose& pose) {
      const Eigen::Isometry3d to_part = part_to_carrier(plate, pose).inverse();
      std::erase_if(scan, [&](const ScanPoint& p) {
        const Eigen::Vector3d q = to_part * Eigen::Vector3d(p.x, p.y, p.z);
        for (const sim::FeatureSpec& f : plate.features) {
          const double r = 0.5e-3 * f.diameter_mm, dx = q.x() - 1e-3 * f.x_mm, dy = q.y() - 1e-3 * f.y_mm;
          const bool column = dx > -0.5 * r - 0.0022 && dx < -0.5 * r + 0.0022;
          if (column && dy > 0.0 && dy * dy + dx * dx >= r * r && dy < std::sqrt(r * r - dx * dx) + 0.006) return true;
        }
        return false;
      });
      return scan;
    };
    WHEN("each scan is checked at the true pose with and without such runs") {
      THEN("the bottom and top edges move by a tenth of a cell at most") {
        const auto bottom = static_cast<std::size_t>(algo::Edge::kBottom),
                   top = static_cast<std::size_t>(algo::Edge::kTop);
        // (Placed by the pieces' centroids, they moved 0.38-0.46 mm; by the chords, 0.03-0.15 mm.)
        for (std::size_t i = 0; i < other_poses().size(); ++i) {
          const sim::PartPose& pose = other_poses()[i];
          const auto scan = sample_part(plate, pose, 620 + i);
          const PlanarPose at = true_relative_pose(plate, *t, pose);
          const MatchReport clean = cascade.two_way_check(m, scan, at);
          const MatchReport runs = cascade.two_way_check(m, with_runs_above_rims(scan, pose), at);
          REQUIRE(std::isfinite(clean.edge_m[bottom]));
          REQUIRE(std::isfinite(runs.edge_m[bottom]));
          INFO("pose " << i << ": bottom " << clean.edge_m[bottom] * 1e3 << " -> " << runs.edge_m[bottom] * 1e3
                       << " mm, top " << clean.edge_m[top] * 1e3 << " -> " << runs.edge_m[top] * 1e3 << " mm");
          CHECK(std::abs(runs.edge_m[bottom] - clean.edge_m[bottom]) <= 0.1 * 0.0022);
          CHECK(std::abs(runs.edge_m[top] - clean.edge_m[top]) <= 0.1 * 0.0022);
        }
      }
    }
  }
}

SCENARIO("The check aligns the outlines when the pose it is given is millimetres off", "[cascade][two-way]") {
  GIVEN("plate_4h, ribbed_v4 and plate_5h templates and scans of the same parts at another pose") {
    CascadeParams no_refine;
    no_refine.refine_iterations = 0;
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    Cascade cascade_fixed(no_refine, pm_params(), test_grid());
    for (const std::string name : {"plate_4h", "ribbed_v4", "plate_5h"}) {
      const Template& t = taught(name);
      const auto scan = sample_part(part(name), kTestPose, 51);
      const PlanarPose truth = true_relative_pose(t, kTestPose);
      WHEN(name + ": the check is given a pose 4 mm, -3 mm and 0.5 deg off the true one") {
        const PlanarPose start{truth.x_m + 0.004, truth.y_m - 0.003, truth.theta_rad + 0.5 * kDeg};
        const MatchReport r = cascade.two_way_check(model_of(t, 0, 1), scan, start);
        const MatchReport fixed = cascade_fixed.two_way_check(model_of(t, 0, 1), scan, start);
        THEN("it runs at the outline pose, close to the truth, and finds no blob where the fixed pose finds some") {
          INFO("check pose " << r.check_pose.x_m << ", " << r.check_pose.y_m << ", " << r.check_pose.theta_rad / kDeg
                             << " deg; truth " << truth.x_m << ", " << truth.y_m << ", " << truth.theta_rad / kDeg
                             << "; outline rms " << r.outline_rms_m * 1e3 << " mm; at the given pose: missing "
                             << fixed.missing_area_m2 * 1e6 << ", extra " << fixed.extra_area_m2 * 1e6 << " mm^2");
          // Along x the outline is known to one profile spacing (2.2 mm) at either edge, along y to a row (1.6 mm).
          CHECK(std::abs(r.check_pose.x_m - truth.x_m) < 0.0025);
          CHECK(std::abs(r.check_pose.y_m - truth.y_m) < 0.0015);
          CHECK(std::abs(r.check_pose.theta_rad - truth.theta_rad) < 0.08 * kDeg);
          CHECK(r.missing_area_m2 < 30e-6);
          CHECK(r.extra_area_m2 < 30e-6);
          CHECK(fixed.missing_area_m2 + fixed.extra_area_m2 > 100e-6);
        }
      }
    }
  }
}

// ---- The decision table
// ----------------------------------------------------------------------------------------------

namespace {

// Four classes: plate_4h (0), ribbed_v4 (1), plate_5h (2), ribbed_v3 (3); thresholds learnt from own-class scans.
// The policy's decisions, not this machine's speed, are under test here (sanitizer builds are slow): a budget no
// verification reaches. The budget itself has its own case.
CascadeParams generous_budget() {
  CascadeParams p;
  p.verify_budget_ms = 60000.0;
  p.search_budget_ms = 60000.0;
  return p;
}

class Catalogue4 {
 public:
  Catalogue4() : cascade_(generous_budget(), pm_params(), test_grid()) {
    const std::vector<std::string> names = {"plate_4h", "ribbed_v4", "plate_5h", "ribbed_v3"};
    for (std::size_t i = 0; i < names.size(); ++i) {
      templates_.push_back(&::taught(names[i]));
      models_.push_back(model_of(*templates_.back(), static_cast<int>(i), 101 + static_cast<int>(i)));
    }
    for (std::size_t i = 0; i < names.size(); ++i) {
      models_[i].thresholds = learn(cascade_, models_[i], names[i], 400 + 10 * i);
    }
  }
  Cascade& cascade() { return cascade_; }
  [[nodiscard]] std::span<const TemplateModel> models() const { return models_; }
  [[nodiscard]] const Template& taught(int i) const { return *templates_[static_cast<std::size_t>(i)]; }

 private:
  Cascade cascade_;
  std::vector<const Template*> templates_;
  std::vector<TemplateModel> models_;
};

// Built once per process (see taught()).
Catalogue4& catalogue4() {
  static Catalogue4 cat;
  return cat;
}

Clock::time_point far_deadline() {
  return Clock::now() + std::chrono::seconds(60);
}

void check_pose(const Decision& d, const PlanarPose& truth) {
  INFO("pose " << d.pose.x_m << ", " << d.pose.y_m << ", " << d.pose.theta_rad / kDeg << " deg; truth " << truth.x_m
               << ", " << truth.y_m << ", " << truth.theta_rad / kDeg);
  REQUIRE(d.pose_valid);
  // Perfect Match's pose (thesis table 6.13 with real parts: 8 mm, 2.7 mm, 0.95 deg at most).
  CHECK(std::abs(d.pose.x_m - truth.x_m) < 0.008);
  CHECK(std::abs(d.pose.y_m - truth.y_m) < 0.008);
  CHECK(std::abs(d.pose.theta_rad - truth.theta_rad) < 0.95 * kDeg);
}

}  // namespace

SCENARIO("The cascade decides by the thesis 6.4.4 table and verifies every accepted class", "[cascade][policy]") {
  GIVEN("four taught classes with learnt thresholds, and a plate_4h scan at another pose") {
    Catalogue4& cat = catalogue4();
    const auto scan = sample_part(part("plate_4h"), kTestPose, 501);
    const PlanarPose truth = true_relative_pose(cat.taught(0), kTestPose);

    WHEN("the SVM is sure of the right class (p1 0.90 >= 0.70, p2 0.05 <= 0.06)") {
      const ClassProbability svm[] = {{0, 0.90}, {2, 0.05}, {1, 0.03}, {3, 0.02}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("the SVM's class is taken, Perfect Match gives the pose, the decision is filled") {
        CHECK(d.source == DecisionSource::kSvm);
        CHECK(d.class_index == 0);
        CHECK(d.part_id == 101);
        CHECK(d.probability == 0.90);
        CHECK(d.second_class_index == 2);
        CHECK(d.pm_error <= cat.models()[0].thresholds.max_error);
        CHECK(d.template_coverage > 0.98);
        CHECK(d.scan_outliers < 0.02);
        CHECK(d.pm_ms > 0.0);
        CHECK(d.total_ms >= d.pm_ms);
        check_pose(d, truth);
      }
    }
    WHEN("the SVM is unsure (p1 0.55 < 0.70) between ribbed_v4 and plate_4h") {
      const ClassProbability svm[] = {{1, 0.55}, {0, 0.40}, {2, 0.03}, {3, 0.02}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      // Independent of decide(): each candidate's error on its own.
      const MatchReport r0 = cat.cascade().evaluate(cat.models()[0], scan);
      const MatchReport r1 = cat.cascade().evaluate(cat.models()[1], scan);
      THEN("Perfect Match picks the candidate with the lower error, the right one") {
        INFO("plate_4h error " << r0.pm.error << ", ribbed_v4 error " << r1.pm.error);
        CHECK(r0.pm.error < r1.pm.error);
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 0);
        CHECK(d.part_id == 101);
        CHECK(d.probability == 0.40);
        CHECK(d.second_class_index == 1);
        CHECK(d.pm_error == Approx(r0.pm.error));
        check_pose(d, truth);
      }
    }
    WHEN("p1 is high but p2 too (0.72 / 0.10 > 0.06)") {
      const ClassProbability svm[] = {{0, 0.72}, {1, 0.10}, {2, 0.10}, {3, 0.08}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("Perfect Match decides") {
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 0);
      }
    }
    WHEN("the SVM is sure of the one-hole-different plate_5h") {
      const ClassProbability svm[] = {{2, 0.92}, {0, 0.05}, {1, 0.02}, {3, 0.01}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("plate_5h fails verification (extra material where its hole is) and the k-candidate match finds plate_4h") {
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 0);
        CHECK(d.part_id == 101);
        check_pose(d, truth);
      }
    }
    WHEN("the SVM ranks the true class last (issue 10: the thesis's top-2 limit would never look at it)") {
      const ClassProbability svm[] = {{1, 0.50}, {3, 0.45}, {2, 0.03}, {0, 0.02}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("every candidate is verified in rank order and the true class is found") {
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 0);
        CHECK(d.part_id == 101);
        CHECK(d.probability == 0.02);
        REQUIRE(d.candidate_count == 4);
        CHECK(d.verified_count == 4);
        for (int i = 0; i < 4; ++i) CHECK(d.candidates[static_cast<std::size_t>(i)].class_index == svm[i].class_index);
        CHECK(d.candidates[3].passed);
        CHECK(d.candidates[3].rejected_by == algo::RejectReason::kNone);
        CHECK_FALSE(d.candidates[0].passed);
        CHECK(d.candidates[0].rejected_by != algo::RejectReason::kNone);
        CHECK(d.candidates[0].value > d.candidates[0].limit);  // the failed figure and its threshold are reported
        check_pose(d, truth);
      }
    }
    WHEN("a scan of an untaught bracket_l comes (an L-shaped bracket: no taught sheet lies where its points do)") {
      const auto bracket = sample_part(part("bracket_l"), kTestPose, 502);
      const ClassProbability ranked[] = {{0, 0.50}, {2, 0.45}, {3, 0.03}, {1, 0.02}};
      const Decision d = cat.cascade().decide(ranked, cat.models(), bracket, far_deadline());
      THEN(
          "every candidate is verified, each match gives up early on an error far above its limit, and the scan "
          "is unknown") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.verified_count == 4);
        REQUIRE(d.candidate_count == 4);
        for (int i = 0; i < d.candidate_count; ++i) {
          const algo::CandidateOutcome& c = d.candidates[static_cast<std::size_t>(i)];
          INFO("candidate " << i << " class " << c.class_index << " pm_error " << c.pm_error << " limit " << c.limit);
          CHECK(c.pm_stopped_early);
          CHECK(c.rejected_by == algo::RejectReason::kPmError);
          CHECK(c.value > 2.0 * c.limit);  // the cascade's give-up limit: twice the template's own
        }
      }
    }
    WHEN("the verification budget allows one candidate only and the SVM ranks the true class second") {
      CascadeParams p = cat.cascade().params();
      p.verify_budget_ms = 1e-6;
      Cascade tight(p, pm_params(), test_grid());
      const ClassProbability svm[] = {{1, 0.50}, {0, 0.45}, {2, 0.03}, {3, 0.02}};
      const Decision d = tight.decide(svm, cat.models(), scan, far_deadline());
      THEN("the first candidate is still verified, the rest is reported not verified, and the scan is unknown") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.class_index == -1);
        CHECK(d.verified_count == 1);
        CHECK(d.candidates[1].rejected_by == algo::RejectReason::kNotVerified);
        CHECK(d.probability == 0.50);
      }
    }
    WHEN("the search budget is spent and no candidate has passed, the true class ranked third") {
      CascadeParams p = cat.cascade().params();
      p.search_budget_ms = 1e-6;
      Cascade tight(p, pm_params(), test_grid());
      const ClassProbability svm[] = {{1, 0.50}, {2, 0.45}, {0, 0.03}, {3, 0.02}};
      const Decision d = tight.decide(svm, cat.models(), scan, far_deadline());
      THEN("the SVM's two most probable are verified all the same, not the third, and the scan is unknown") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.class_index == -1);
        CHECK(d.verified_count == 2);
        CHECK_FALSE(d.candidates[0].passed);
        CHECK_FALSE(d.candidates[1].passed);
        CHECK(d.candidates[2].rejected_by == algo::RejectReason::kNotVerified);
      }
    }
    WHEN("the search budget is spent but the true class passes second, with a look-alike after it") {
      CascadeParams p = cat.cascade().params();
      p.search_budget_ms = 1e-6;
      Cascade tight(p, pm_params(), test_grid());
      // plate_5h (2) as plate_4h's (0) look-alike, as training would record it: one hole more.
      std::vector<TemplateModel> models(cat.models().begin(), cat.models().end());
      const int look_alike[] = {2};
      models[0].confusable = look_alike;
      const ClassProbability svm[] = {{1, 0.50}, {0, 0.45}, {3, 0.03}, {2, 0.02}};
      const Decision d = tight.decide(svm, models, scan, far_deadline());
      THEN("the look-alike is verified within the whole budget, fails, and the part is found") {
        CHECK(d.class_index == 0);
        CHECK(d.candidates[1].passed);
        CHECK(d.candidates[3].verified);
        CHECK_FALSE(d.candidates[3].passed);
        CHECK(d.candidates[2].rejected_by == algo::RejectReason::kNotVerified);
      }
    }
    WHEN("the true class passes first but the budget runs out before an almost as probable candidate") {
      CascadeParams p = cat.cascade().params();
      p.verify_budget_ms = 1e-6;
      Cascade tight(p, pm_params(), test_grid());
      const ClassProbability svm[] = {{0, 0.50}, {1, 0.45}, {2, 0.03}, {3, 0.02}};
      const Decision d = tight.decide(svm, cat.models(), scan, far_deadline());
      THEN("the scan is unknown for want of verification, and the passing candidate is not called ambiguous") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.unknown_reason == algo::RejectReason::kNotVerified);
        CHECK(d.verified_count == 1);
        CHECK(d.candidates[0].passed);
        CHECK(d.candidates[0].rejected_by == algo::RejectReason::kNone);
        CHECK(d.candidates[1].rejected_by == algo::RejectReason::kNotVerified);
      }
    }
    WHEN("the budget is generous but was spent before decide() (it counts from when the decision began)") {
      const ClassProbability svm[] = {{1, 0.50}, {0, 0.45}, {2, 0.03}, {3, 0.02}};
      const Clock::time_point began =
          Clock::now() - std::chrono::milliseconds(static_cast<long>(cat.cascade().params().verify_budget_ms) + 1);
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline(), began);
      const Decision fresh = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("only the first candidate is verified and the scan is unknown; begun now, the same call finds the part") {
        CHECK(d.verified_count == 1);
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.candidates[1].rejected_by == algo::RejectReason::kNotVerified);
        CHECK(fresh.class_index == 0);
      }
    }
    WHEN("the deadline has already passed") {
      const ClassProbability svm[] = {{0, 0.90}, {2, 0.05}, {1, 0.03}, {3, 0.02}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, Clock::now() - std::chrono::milliseconds(1));
      THEN("the decision is a timeout, never a guess") {
        CHECK(d.source == DecisionSource::kTimeout);
        CHECK(d.class_index == -1);
        CHECK(d.part_id == 0);
        CHECK_FALSE(d.pose_valid);
      }
    }
  }
}

SCENARIO("A scan lacking one hole's material is told from its one-hole sibling, whatever the SVM says",
         "[cascade][policy]") {
  GIVEN("four taught classes with learnt thresholds, and a plate_5h scan at another pose") {
    Catalogue4& cat = catalogue4();
    const auto scan = sample_part(part("plate_5h"), kTestPose, 601);
    WHEN("the SVM is sure of plate_4h (which the scan is plate_4h plus a hole)") {
      const ClassProbability svm[] = {{0, 0.93}, {2, 0.04}, {1, 0.02}, {3, 0.01}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      const MatchReport wrong = cat.cascade().evaluate(cat.models()[0], scan);
      THEN("plate_4h fails on the missing hole material although its error passes, and plate_5h is chosen") {
        INFO("plate_4h on the plate_5h scan: error "
             << wrong.pm.error << " (max " << cat.models()[0].thresholds.max_error << "), missing "
             << wrong.missing_area_m2 * 1e6 << " mm^2 (max " << cat.models()[0].thresholds.max_missing_area_m2 * 1e6
             << ")");
        CHECK(wrong.pm.error <= cat.models()[0].thresholds.max_error);  // one-way matching is blind here
        CHECK(wrong.missing_area_m2 > cat.models()[0].thresholds.max_missing_area_m2);
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 2);
        CHECK(d.part_id == 103);
        check_pose(d, true_relative_pose(cat.taught(2), kTestPose));
      }
    }
    WHEN("the SVM offers only plate_4h and a ribbed panel") {
      const ClassProbability svm[] = {{0, 0.60}, {1, 0.30}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("nothing passes: unknown rather than the wrong plate, and the reason names plate_4h's missing area") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.class_index == -1);
        CHECK(d.part_id == 0);
        CHECK(d.unknown_reason == algo::RejectReason::kMissingArea);
        CHECK(d.candidates[0].rejected_by == algo::RejectReason::kMissingArea);
      }
    }
  }
  GIVEN("the same four classes and scans of ribbed_v3 and of a part that was never taught") {
    Catalogue4& cat = catalogue4();
    WHEN("the SVM is sure of ribbed_v4 for a ribbed_v3 scan") {
      const auto scan = sample_part(part("ribbed_v3"), kTestPose, 602);
      const ClassProbability svm[] = {{1, 0.90}, {3, 0.05}, {0, 0.03}, {2, 0.02}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("ribbed_v3 is chosen") {
        CHECK(d.source == DecisionSource::kPm);
        CHECK(d.class_index == 3);
      }
    }
    WHEN("the SVM is sure of plate_4h for a frame_window scan") {
      const auto scan = sample_part(part("frame_window"), kTestPose, 603);
      const ClassProbability svm[] = {{0, 0.95}, {2, 0.03}, {1, 0.01}, {3, 0.01}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("the decision is unknown") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.class_index == -1);
      }
    }
  }
}

namespace {

// Scan artefacts a plant's scans have (independent of algo/cascade: plain point filters on the sampled truth).
std::vector<ScanPoint> without_band(std::vector<ScanPoint> scan, double x0_m, double x1_m) {
  std::erase_if(scan, [&](const ScanPoint& p) { return p.x >= x0_m && p.x <= x1_m; });
  return scan;
}
// Glare that leaves a few points: in x0..x1 only `keep` of the points survive (seeded).
std::vector<ScanPoint> with_glare_residue(std::vector<ScanPoint> scan, double x0_m, double x1_m, double keep,
                                          std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::erase_if(scan, [&](const ScanPoint& p) { return p.x >= x0_m && p.x <= x1_m && u(rng) >= keep; });
  return scan;
}
// Own-class checks of scans with artefacts: how many pass, and the largest missing area and hole pattern among them.
struct ArtefactTally {
  int passed = 0, scans = 0;
  double worst_missing_m2 = 0.0, worst_hole_pattern_m2 = 0.0;
  void add(const MatchReport& r, const algo::TemplateThresholds& t) {
    passed += r.passes(t) ? 1 : 0;
    ++scans;
    worst_missing_m2 = std::max(worst_missing_m2, r.missing_area_m2);
    worst_hole_pattern_m2 = std::max(worst_hole_pattern_m2, r.hole_pattern_m2);
  }
};
// A tab of material `length_m` long and `width_m` wide on the sheet's plane sticking out of the part's right edge at
// its mid-height.
std::vector<ScanPoint> with_tab_on_right(std::vector<ScanPoint> scan, double width_m, double length_m) {
  float zsum = 0.0F, ysum = 0.0F, right = -1e9F;
  for (const ScanPoint& p : scan) {
    zsum += p.z;
    ysum += p.y;
  }
  const float n = static_cast<float>(scan.size());
  const float cy = ysum / n;
  for (const ScanPoint& p : scan) {
    if (std::abs(p.y - cy) < 0.5 * width_m) right = std::max(right, p.x);
  }
  for (double x = 0.0022; x < length_m; x += 0.0022) {
    for (double y = -0.5 * width_m; y <= 0.5 * width_m; y += 0.0016) {
      scan.push_back({right + static_cast<float>(x), cy + static_cast<float>(y), zsum / n, 0, 0});
    }
  }
  return scan;
}
// A pressed rib the part did not have, x0..x1 by y0..y1: its points come `proud_m` nearer the camera, and the
// laser's shadow of its long walls takes `shadow_m` on either side.
std::vector<ScanPoint> with_rib(std::vector<ScanPoint> scan, const Eigen::AlignedBox2d& rib, double proud_m,
                                double shadow_m) {
  std::erase_if(scan, [&](const ScanPoint& p) {
    const bool beside = (p.x >= rib.min().x() - shadow_m && p.x < rib.min().x()) ||
                        (p.x > rib.max().x() && p.x <= rib.max().x() + shadow_m);
    return beside && p.y >= rib.min().y() && p.y <= rib.max().y();
  });
  for (ScanPoint& p : scan) {
    if (rib.contains(Eigen::Vector2d(p.x, p.y))) p.z += static_cast<float>(proud_m);
  }
  return scan;
}
std::vector<ScanPoint> with_dropouts(std::vector<ScanPoint> scan, double share, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::erase_if(scan, [&](const ScanPoint&) { return u(rng) < share; });
  return scan;
}
// A chain from the part's top edge up: a strip `width_m` wide, `length_m` long, on the sheet's plane.
std::vector<ScanPoint> with_chain(std::vector<ScanPoint> scan, double width_m, double length_m) {
  float zsum = 0.0F, xsum = 0.0F;
  for (const ScanPoint& p : scan) {
    zsum += p.z;
    xsum += p.x;
  }
  const float n = static_cast<float>(scan.size());
  const float cx = xsum / n;
  float top = -1e9F;  // the part's top edge where the chain hangs (the part is turned: not its highest point)
  for (const ScanPoint& p : scan) {
    if (std::abs(p.x - cx) < 0.5 * width_m) top = std::max(top, p.y);
  }
  for (double y = 0.0; y < length_m; y += 0.0016) {
    for (double x = -0.5 * width_m; x <= 0.5 * width_m; x += 0.0022) {
      scan.push_back({cx + static_cast<float>(x), top + static_cast<float>(y), zsum / n, 0, 0});
    }
  }
  return scan;
}

}  // namespace

SCENARIO("A part that passes only with lost data brings every candidate to verification", "[cascade][policy]") {
  GIVEN("the four classes (no look-alikes recorded) and a ribbed_v3 scan whose glare hides where ribbed_v4 has a rib") {
    Catalogue4& cat = catalogue4();
    auto scan = sample_part(part("ribbed_v3"), kTestPose, 811);
    float cx = 0.0F;
    for (const ScanPoint& p : scan) cx += p.x;
    cx /= static_cast<float>(scan.size());
    // ribbed_v4's fourth rib (x = +135 mm, 40 mm wide; the part turned by a few degrees): 3 % of the points survive.
    std::mt19937_64 rng(812);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    std::erase_if(scan, [&](const ScanPoint& p) { return p.x > cx + 0.09F && p.x < cx + 0.18F && u(rng) >= 0.03; });
    WHEN("the SVM is sure of ribbed_v4 and ranks ribbed_v3 last") {
      const ClassProbability svm[] = {{1, 0.94}, {0, 0.03}, {2, 0.02}, {3, 0.01}};
      const Decision d = cat.cascade().decide(svm, cat.models(), scan, far_deadline());
      THEN("ribbed_v3 is verified too, and the decision is never ribbed_v4") {
        INFO("decision " << d.class_index << ", reason " << algo::to_string(d.unknown_reason) << ", verified "
                         << d.verified_count);
        CHECK(d.verified_count == 4);
        CHECK(d.class_index != 1);
      }
    }
  }
}

SCENARIO("The search beyond the SVM's two most probable has a budget of its own, except on a scan with lost data",
         "[cascade][policy]") {
  GIVEN("the four classes, a search budget spent at once, and the SVM ranking plate_4h last, plate_5h first") {
    Catalogue4& cat = catalogue4();
    CascadeParams p = cat.cascade().params();
    p.search_budget_ms = 1e-6;
    Cascade tight(p, pm_params(), test_grid());
    const ClassProbability svm[] = {{2, 0.50}, {1, 0.45}, {3, 0.03}, {0, 0.02}};
    const auto clean = sample_part(part("plate_4h"), kTestPose, 821);
    float cx = 0.0F;
    for (const ScanPoint& q : clean) cx += q.x;
    cx /= static_cast<float>(clean.size());
    WHEN("a clean plate_4h scan comes") {
      const Decision d = tight.decide(svm, cat.models(), clean, far_deadline());
      THEN("plate_5h and ribbed_v4 are verified and fail, the search stops there, and the scan is unknown") {
        CHECK(d.verified_count == 2);
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.candidates[3].rejected_by == algo::RejectReason::kNotVerified);
      }
    }
    WHEN("the plate_4h scan has a 20 mm glare band that leaves 3 % of its points, where all four are flat sheet") {
      // (Between ribbed_v4's first two ribs, x -115..-65 mm: over a rib the band's cells join the rib's missing ones.)
      const auto glare = with_glare_residue(clean, cx - 0.105, cx - 0.085, 0.03, 822);
      const Decision d = tight.decide(svm, cat.models(), glare, far_deadline());
      THEN("the lost data both checks found keeps the search going, and plate_4h is found") {
        INFO("decision " << d.class_index << ", reason " << algo::to_string(d.unknown_reason) << ", verified "
                         << d.verified_count);
        CHECK(d.verified_count == 4);
        CHECK(d.class_index == 0);
      }
    }
  }
}

SCENARIO("Near twins tied under a glare band are told apart by what the scan shows where they differ",
         "[cascade][policy][twin]") {
  GIVEN("the four classes, the SVM ranking plate_4h first, and a 25 mm glare band through plate_5h's fifth hole") {
    Catalogue4& cat = catalogue4();
    const ClassProbability svm[] = {{0, 0.60}, {2, 0.35}, {1, 0.03}, {3, 0.02}};
    // The outcome of class c among the reported candidates.
    auto outcome = [](const Decision& d, int c) {
      for (int i = 0; i < d.candidate_count; ++i) {
        if (d.candidates[static_cast<std::size_t>(i)].class_index == c)
          return d.candidates[static_cast<std::size_t>(i)];
      }
      FAIL("class " << c << " not reported");
      return algo::CandidateOutcome{};
    };
    // A band `width` wide along y through the part's centre (the fifth hole's), `keep` of its points left.
    auto banded = [](const std::vector<ScanPoint>& clean, double width, double keep, std::uint64_t seed) {
      double cx = 0.0;
      for (const ScanPoint& q : clean) cx += q.x;
      cx /= static_cast<double>(clean.size());
      return with_glare_residue(clean, cx - 0.5 * width, cx + 0.5 * width, keep, seed);
    };
    const auto five = sample_part(part("plate_5h"), kTestPose, 831);
    const auto four = sample_part(part("plate_4h"), kTestPose, 832);
    auto describe = [](const Decision& d) {
      std::ostringstream o;
      o << "decision " << d.class_index << ", reason " << algo::to_string(d.unknown_reason);
      for (int i = 0; i < d.candidate_count; ++i) {
        const algo::CandidateOutcome& c = d.candidates[static_cast<std::size_t>(i)];
        o << "; class " << c.class_index << " passed " << c.passed << " " << algo::to_string(c.rejected_by) << " "
          << c.value << " / " << c.limit;
      }
      return o.str();
    };
    WHEN("the band leaves 5 % of the points of a plate_5h scan") {
      const Decision d = cat.cascade().decide(svm, cat.models(), banded(five, 0.025, 0.05, 833), far_deadline());
      THEN("both plates pass their gates, and plate_5h is chosen: where plate_4h has material the band shows none") {
        INFO(describe(d));
        const algo::CandidateOutcome o4 = outcome(d, 0);
        CHECK(o4.passed);
        CHECK(o4.rejected_by == algo::RejectReason::kTwinFeature);
        CHECK(o4.value == 0.0);  // cells seen in plate_5h's hole
        CHECK(o4.limit >= 8.0);  // where plate_4h's material would have shown this many
        CHECK(d.class_index == 2);
      }
    }
    // (A band of 25 mm over a plate_4h scan leaves plate_5h's hole covered beside it: plate_5h fails by its extra
    // area. One of 36 mm that leaves 1 % hides nearly all of it, and both may pass.)
    for (const double width : {0.025, 0.036}) {
      WHEN("a " << width * 1e3 << " mm band crosses a plate_4h scan there") {
        const Decision d = cat.cascade().decide(svm, cat.models(), banded(four, width, width > 0.03 ? 0.01 : 0.05, 834),
                                                far_deadline());
        THEN("plate_4h is chosen, or unknown, never plate_5h") {
          INFO(describe(d));
          CHECK(d.class_index != 2);
          if (width < 0.03) CHECK(d.class_index == 0);
        }
      }
    }
    WHEN("the band leaves no point of the plate_5h scan") {
      const Decision d = cat.cascade().decide(svm, cat.models(), banded(five, 0.025, 0.0, 835), far_deadline());
      THEN("the hole's emptiness cannot be told from the glare's: unknown, never plate_4h") {
        INFO(describe(d));
        CHECK(d.class_index != 0);
        CHECK(d.source == DecisionSource::kUnknown);
      }
    }
  }
}

namespace {

// A 450 x 650 mm plate with a 34 mm hole and a 6 x 8 field of 11 mm holes (pitch 21 x 33 mm) centred at x_mm: the
// random catalogue's rnd062, whose mirrored twin rnd268 has the field at -x_mm, two pitches over (issue 11).
sim::PartSpec perforated_plate(double field_x_mm) {
  sim::PartSpec p;
  p.name = "field";
  p.width_mm = 450;
  p.height_mm = 650;
  const sim::FeatureSpec field{.kind = sim::FeatureKind::kHoleArray,
                               .x_mm = field_x_mm,
                               .y_mm = 120,
                               .diameter_mm = 11,
                               .count_x = 6,
                               .count_y = 8,
                               .pitch_x_mm = 21,
                               .pitch_y_mm = 33};
  const sim::FeatureSpec hole{.kind = sim::FeatureKind::kHole, .y_mm = -150, .diameter_mm = 34};
  p.features = {field, hole};
  REQUIRE(sim::validate_part(p).empty());
  return p;
}

// `part`'s template model with thresholds learnt from its scans at the five other poses (their reports into `own`).
TemplateModel learnt_at_other_poses(Cascade& cascade, const Template& t, const sim::PartSpec& part,
                                    std::vector<MatchReport>& own) {
  TemplateModel m = model_of(t, 0, 1);
  for (std::size_t i = 0; i < other_poses().size(); ++i) {
    own.push_back(cascade.evaluate(m, sample_part(part, other_poses()[i], 620 + i)));
  }
  m.thresholds = algo::learn_thresholds(own, cascade.params());
  return m;
}

// A plain 300 x 420 mm sheet: no hole, no relief; taught once per process, its limits learnt at other_poses().
sim::PartSpec plain_sheet() {
  sim::PartSpec sheet;
  sheet.name = "sheet";
  sheet.width_mm = 300;
  sheet.height_mm = 420;
  return sheet;
}
const Template& taught_sheet() {
  static const std::unique_ptr<Template> t =
      teach_from("sheet", kTaughtPose, sample_part(plain_sheet(), kTaughtPose, 841));
  return *t;
}
// The SVM's answer for a cascade of the sheet alone.
constexpr ClassProbability kOnlySheet[] = {{0, 1.0}};
TemplateModel learnt_sheet(Cascade& cascade) {
  std::vector<MatchReport> own;
  return learnt_at_other_poses(cascade, taught_sheet(), plain_sheet(), own);
}
// A cascade of the sheet alone and its learnt model.
struct SheetCell {
  Cascade cascade{generous_budget(), pm_params(), test_grid()};
  TemplateModel m = learnt_sheet(cascade);
  [[nodiscard]] Decision decide(const std::vector<ScanPoint>& scan) {
    return cascade.decide(kOnlySheet, std::span<const TemplateModel>(&m, 1), scan, far_deadline());
  }
};

}  // namespace

SCENARIO("A glare band that takes one end of a flat sheet leaves it placed where it hangs, not centred on the rest",
         "[cascade][policy]") {
  GIVEN("a plain 300 x 420 mm sheet (no hole: nothing on it pulls Perfect Match along it) learnt at five poses") {
    const sim::PartSpec sheet = plain_sheet();
    SheetCell cell;
    const PlanarPose truth = true_relative_pose(sheet, taught_sheet(), kTestPose);
    // The strip glare took (3 % of its points left): the top 24 or 36 mm, the bottom 30 mm, the left 30 mm.
    struct Strip {
      const char* where;
      double width_m;
      int axis;  // 0: x, 1: y
      int end;   // -1: the low end, +1: the high end
    };
    for (const Strip& strip : {Strip{"top", 0.024, 1, 1}, Strip{"top", 0.036, 1, 1}, Strip{"bottom", 0.030, 1, -1},
                               Strip{"left", 0.030, 0, -1}}) {
      WHEN("glare took its " << strip.where << " " << strip.width_m * 1e3 << " mm") {
        auto scan = sample_part(sheet, kTestPose, 842);
        float lo = 1e9F, hi = -1e9F;
        auto along = [&](const ScanPoint& p) { return strip.axis == 0 ? p.x : p.y; };
        for (const ScanPoint& p : scan) {
          lo = std::min(lo, along(p));
          hi = std::max(hi, along(p));
        }
        std::mt19937_64 rng(843);
        std::uniform_real_distribution<double> u(0.0, 1.0);
        std::erase_if(scan, [&](const ScanPoint& p) {
          const bool in = strip.end > 0 ? along(p) > hi - strip.width_m : along(p) < lo + strip.width_m;
          return in && u(rng) >= 0.03;
        });
        const Decision d = cell.decide(scan);
        THEN("it is accepted at its pose, not half the strip off") {
          INFO("decision " << d.class_index << ", reason " << algo::to_string(d.unknown_reason) << ", missing "
                           << d.candidates[0].missing_area_m2 * 1e6 << " mm2, check pose "
                           << d.candidates[0].check_pose.x_m << ", " << d.candidates[0].check_pose.y_m << "; truth "
                           << truth.x_m << ", " << truth.y_m);
          REQUIRE(d.class_index == 0);
          CHECK(std::abs(d.pose.x_m - truth.x_m) < 0.003);
          CHECK(std::abs(d.pose.y_m - truth.y_m) < 0.003);
        }
      }
    }
    WHEN("the scan is of a variant 24 mm shorter (no glare: nothing of it is lost)") {
      sim::PartSpec shorter = sheet;
      shorter.height_mm = 396;
      const Decision d = cell.decide(sample_part(shorter, kTestPose, 844));
      THEN("placed flush with either end it is still short (an extent does not move with the pose): unknown") {
        INFO("decision " << d.class_index << ", reason " << algo::to_string(d.unknown_reason) << ", size "
                         << d.candidates[0].size_dev_m * 1e3 << " mm");
        CHECK(d.class_index == -1);
        CHECK(d.candidates[0].size_dev_m > 0.02);
      }
      THEN("its signed figures (classify --json) say 24 mm shorter and as wide; no hole places its edges") {
        const algo::CandidateOutcome& c = d.candidates[0];
        INFO("size off " << c.size_off_xy_m[0] * 1e3 << " x " << c.size_off_xy_m[1] * 1e3 << " mm");
        CHECK(c.size_off_xy_m[1] == Approx(-0.024).margin(0.003));
        CHECK(std::abs(c.size_off_xy_m[0]) < 0.0015);
        for (const double e : c.edge_off_m) CHECK(std::isnan(e));
      }
    }
  }
}

SCENARIO("A glare band along a whole edge is lost data by the few lone points it leaves, a narrower part is not",
         "[cascade][evidence]") {
  GIVEN("a plain 300 x 420 mm sheet learnt at five poses, and a glare band 35 mm wide along its whole left edge") {
    const sim::PartSpec sheet = plain_sheet();
    SheetCell cell;
    auto with_edge_band = [&](double keep) {
      auto scan = sample_part(sheet, kTestPose, 845);
      float left = 1e9F;
      for (const ScanPoint& p : scan) left = std::min(left, p.x);
      std::mt19937_64 rng(846);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      std::erase_if(scan, [&](const ScanPoint& p) { return p.x < left + 0.035F && u(rng) >= keep; });
      return scan;
    };
    WHEN("0.3 % of the band's points survive (10 of 3 302), lone cells spread along it") {
      const Decision d = cell.decide(with_edge_band(0.003));
      THEN("the strip is lost data and the sheet is recognised") {
        INFO("decision " << d.class_index << ", missing " << d.candidates[0].missing_area_m2 * 1e6 << " mm2");
        CHECK(d.class_index == 0);
      }
    }
    WHEN("no point survives") {
      const Decision d = cell.decide(with_edge_band(0.0));
      THEN("nothing tells the strip from a narrower part: unknown") {
        CHECK(d.class_index == -1);
      }
    }
    WHEN("the scan is of a variant 20 mm narrower, its edge's fringe beside the strip") {
      sim::PartSpec narrower = sheet;
      narrower.width_mm = 280;
      const Decision d = cell.decide(sample_part(narrower, kTestPose, 847));
      THEN("unknown") {
        INFO("size " << d.candidates[0].size_dev_m * 1e3 << " mm");
        CHECK(d.class_index == -1);
      }
    }
  }
}

SCENARIO("The hole pattern sees a field of small holes two pitches over, which the window cannot",
         "[cascade][two-way]") {
  GIVEN("a perforated plate's template with thresholds learnt from its own scans at five other poses") {
    const sim::PartSpec plate = perforated_plate(21.0);
    const sim::PartSpec mirrored = perforated_plate(-21.0);
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    static const std::unique_ptr<Template> t = teach_from("field", kTaughtPose, sample_part(plate, kTaughtPose, 61));
    std::vector<MatchReport> own;
    const TemplateModel m = learnt_at_other_poses(cascade, *t, plate, own);
    double own_max = 0.0;
    for (const MatchReport& r : own) own_max = std::max(own_max, r.hole_pattern_m2);
    INFO("own-class hole pattern up to " << own_max * 1e6 << " mm2, limit " << m.thresholds.max_hole_pattern_m2 * 1e6);
    // One 11 mm hole covers ~20 cells of 2.2 mm; its empty core, 6-12.
    constexpr double kOneHoleM2 = 6 * 0.0022 * 0.0022;
    CHECK(own_max < kOneHoleM2);
    WHEN("the scan is of the twin whose field lies 42 mm over (16 holes where the template is solid, 16 covered)") {
      const MatchReport r = cascade.evaluate(m, sample_part(mirrored, kTestPose, 63));
      double value = 0.0, limit = 0.0;
      const algo::RejectReason reason = algo::first_failed_gate(r, m.thresholds, value, limit);
      THEN("the hole pattern rejects it, and it is the first gate that does") {
        INFO("hole pattern " << r.hole_pattern_m2 * 1e6 << " mm2; missing " << r.missing_area_m2 * 1e6 << " extra "
                             << r.extra_area_m2 * 1e6 << " mm2, coverage " << r.coverage);
        CHECK(reason == algo::RejectReason::kHolePattern);
        CHECK(r.hole_pattern_m2 > 32 * kOneHoleM2);
        CHECK(r.evidence_m2 >= r.hole_pattern_m2);
      }
    }
    WHEN("the scan is of the part itself at a test pose, with 3 % dropouts, or a glare band over its field") {
      const auto clean = sample_part(plate, kTestPose, 64);
      float cx = 0.0F;
      for (const ScanPoint& p : clean) cx += p.x;
      cx /= static_cast<float>(clean.size());
      const MatchReport r = cascade.evaluate(m, clean);
      const MatchReport dropped = cascade.evaluate(m, with_dropouts(clean, 0.03, 65));
      const MatchReport glare = cascade.evaluate(m, with_glare_residue(clean, cx + 0.005, cx + 0.030, 0.03, 66));
      THEN("it passes, and the hole pattern finds less than a hole in each") {
        INFO("hole pattern: clean " << r.hole_pattern_m2 * 1e6 << ", dropouts " << dropped.hole_pattern_m2 * 1e6
                                    << ", glare " << glare.hole_pattern_m2 * 1e6 << " mm2");
        CHECK(r.passes(m.thresholds));
        CHECK(dropped.passes(m.thresholds));
        CHECK(glare.passes(m.thresholds));
        CHECK(std::max({r.hole_pattern_m2, dropped.hole_pattern_m2, glare.hole_pattern_m2}) < kOneHoleM2);
      }
    }
    WHEN("glare bands 15 mm wide that keep 4-12 % of their points lie over the plain sheet or along its edge") {
      const auto clean = sample_part(plate, kTestPose, 68);
      float left = 1e9F, right = -1e9F;
      for (const ScanPoint& p : clean) {
        left = std::min(left, p.x);
        right = std::max(right, p.x);
      }
      ArtefactTally tally;
      std::uint64_t seed = 69;
      for (const double x0 : {static_cast<double>(left) + 0.060, static_cast<double>(right) - 0.040,
                              static_cast<double>(right) - 0.020}) {
        for (const double keep : {0.04, 0.08, 0.12}) {
          tally.add(cascade.evaluate(m, with_glare_residue(clean, x0, x0 + 0.015, keep, seed++)), m.thresholds);
        }
      }
      THEN("the pockets between the residue's points are no holes: each passes, with less than a hole's pattern") {
        INFO("largest hole pattern " << tally.worst_hole_pattern_m2 * 1e6 << " mm2 (limit "
                                     << m.thresholds.max_hole_pattern_m2 * 1e6 << "); " << tally.passed << " of "
                                     << tally.scans << " pass");
        CHECK(tally.worst_hole_pattern_m2 < kOneHoleM2);
        CHECK(tally.passed == tally.scans);
      }
    }
    WHEN("the check of the part's own scan runs at a pose 1.5 mm and 1 mm off the fitted one, without realignment") {
      CascadeParams fixed_params;
      fixed_params.refine_iterations = 0;
      Cascade fixed(fixed_params, pm_params(), test_grid());
      const auto scan = sample_part(plate, kTestPose, 67);
      const MatchReport fitted = fixed.evaluate(m, scan);
      const PlanarPose off{fitted.pm.pose.x_m + 0.0015, fitted.pm.pose.y_m - 0.001, fitted.pm.pose.theta_rad};
      const MatchReport r = fixed.two_way_check(m, scan, off);
      THEN("the same holes still match: a pose error moves every hole by as much") {
        INFO("hole pattern " << r.hole_pattern_m2 * 1e6 << " mm2 (at the fitted pose " << fitted.hole_pattern_m2 * 1e6
                             << ")");
        CHECK(r.hole_pattern_m2 < kOneHoleM2);
      }
    }
  }
}

SCENARIO("Evidence is judged by its shape: data loss and hangers weigh little, a hole or an edge fully",
         "[cascade][evidence]") {
  GIVEN("the plate_4h template with thresholds learnt from clean own-class scans") {
    Catalogue4& cat = catalogue4();
    const TemplateModel& m = cat.models()[0];
    const auto clean = sample_part(part("plate_4h"), kTestPose, 801);
    float cx = 0.0F;
    for (const ScanPoint& p : clean) cx += p.x;
    cx /= static_cast<float>(clean.size());
    WHEN("a 30 mm glare band crosses the whole part (no point left in it)") {
      const auto scan = without_band(clean, cx - 0.015, cx + 0.015);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is accepted: the band is a thin strip open at both ends, not a hole") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_missing_area_m2 * 1e6
                        << "), coverage " << r.coverage << " (max uncovered " << m.thresholds.max_uncovered << ")");
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("a 32 mm hole it lacks lies more than half under a 16 mm glare band that leaves no point") {
      // (Fresh random catalogue 11344 under `mixed`: an untaught twin's 46 mm hole under a 20 mm band showed 126 mm2
      // of itself beside the band, under its sibling's 165 mm2 limit, and the twin was given the sibling's id.)
      const auto cy = static_cast<float>(mean_point(clean).y());
      auto with_hole = [&](std::vector<ScanPoint> scan) {  // centred 7 mm right of the band's centre line
        std::erase_if(scan, [&](const ScanPoint& p) {
          const float dx = p.x - (cx + 0.007F), dy = p.y - cy;
          return dx * dx + dy * dy < 0.016F * 0.016F;
        });
        return scan;
      };
      const MatchReport alone = cat.cascade().evaluate(m, with_hole(clean));
      const MatchReport banded = cat.cascade().evaluate(m, without_band(with_hole(clean), cx - 0.008, cx + 0.008));
      const MatchReport own = cat.cascade().evaluate(m, without_band(clean, cx - 0.008, cx + 0.008));
      THEN("it fails as it fails without the band: what it shows beside the band counts as much again") {
        // (Counted once, the piece beside the band was 116 mm2 against the 150 mm2 limit, and the scan passed.)
        INFO("missing: alone " << alone.missing_area_m2 * 1e6 << " mm2, beside the band "
                               << banded.missing_area_m2 * 1e6 << " mm2, the plate with the band alone "
                               << own.missing_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_missing_area_m2 * 1e6
                               << ")");
        CHECK_FALSE(alone.passes(m.thresholds));
        CHECK_FALSE(banded.passes(m.thresholds));
        CHECK(own.passes(m.thresholds));
      }
    }
    WHEN("a 20 mm glare band crosses the part and 3 % of its points survive, scattered") {
      const auto scan = with_glare_residue(clean, cx - 0.06, cx - 0.04, 0.03, 806);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is accepted: the pieces between the surviving points are lost data, not holes") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_missing_area_m2 * 1e6
                        << "), coverage " << r.coverage << " (max uncovered " << m.thresholds.max_uncovered << ")");
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("a 20 mm glare band that leaves 3 % of the points runs along its bottom edge") {
      float bottom = 1e9F;
      for (const ScanPoint& p : clean) bottom = std::min(bottom, p.y);
      std::mt19937_64 rng(810);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      auto scan = clean;
      std::erase_if(scan, [&](const ScanPoint& p) { return p.y < bottom + 0.02F && u(rng) >= 0.03; });
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is accepted: the lines that end in lost data do not measure the part's height") {
        INFO("size dx " << r.size_dx_m * 1e3 << " dy " << r.size_dy_m * 1e3 << " mm; missing "
                        << r.missing_area_m2 * 1e6 << " mm2");
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("a 20 mm glare band that leaves 10 % of the points runs along its right edge") {
      float right = -1e9F;
      for (const ScanPoint& p : clean) right = std::max(right, p.x);
      std::mt19937_64 rng(811);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      auto scan = clean;
      std::erase_if(scan, [&](const ScanPoint& p) { return p.x > right - 0.02F && u(rng) >= 0.10; });
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is accepted: a line whose outermost point is the band's residue does not measure the width") {
        INFO("size dx " << r.size_dx_m * 1e3 << " (centre " << m.thresholds.size_centre_x_m * 1e3 << ", limit "
                        << m.thresholds.max_size_dev_m * 1e3 << ") mm; missing " << r.missing_area_m2 * 1e6 << " mm2");
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("20 mm glare bands that leave 1-2 % of the points run along its right edge and off the part, 0.6 deg off") {
      // The right edge, turned with the pose: a line fitted through the outermost point of each 10 mm of height (the
      // middle 80 %, clear of the corners).
      float y_lo = 1e9F, y_hi = -1e9F;
      for (const ScanPoint& p : clean) {
        y_lo = std::min(y_lo, p.y);
        y_hi = std::max(y_hi, p.y);
      }
      constexpr int kBins = 52;
      std::array<float, kBins> outer{};
      outer.fill(-1e9F);
      const float first = y_lo + 0.1F * (y_hi - y_lo), bin = 0.8F * (y_hi - y_lo) / kBins;
      for (const ScanPoint& p : clean) {
        const int k = static_cast<int>(std::floor((p.y - first) / bin));
        if (k >= 0 && k < kBins) outer[static_cast<std::size_t>(k)] = std::max(outer[static_cast<std::size_t>(k)], p.x);
      }
      double sy = 0.0, sx = 0.0, syy = 0.0, sxy = 0.0;
      for (int k = 0; k < kBins; ++k) {
        const double y = first + (k + 0.5) * bin, x = outer[static_cast<std::size_t>(k)];
        sy += y, sx += x, syy += y * y, sxy += x * y;
      }
      const double edge_slope = (kBins * sxy - sx * sy) / (kBins * syy - sy * sy);
      const double edge_at = (sx - edge_slope * sy) / kBins;  // x of the edge at y = 0
      ArtefactTally tally;
      // The band's axis on the edge at one end, turning 0.6 deg outward: along the part it eats a strip of the edge
      // whose width shrinks as the band runs off.
      const double off = std::tan(0.6 * std::numbers::pi / 180.0);
      for (const float y_start : {y_lo, y_hi}) {
        for (const double keep : {0.01, 0.02}) {
          std::mt19937_64 rng(814 + static_cast<std::uint64_t>(tally.scans));
          std::uniform_real_distribution<double> u(0.0, 1.0);
          auto scan = clean;
          std::erase_if(scan, [&](const ScanPoint& p) {
            const double y = p.y;
            const double axis = edge_at + edge_slope * y + off * std::abs(y - static_cast<double>(y_start));
            return std::abs(static_cast<double>(p.x) - axis) <= 0.010 && u(rng) >= keep;
          });
          tally.add(cat.cascade().evaluate(m, scan), m.thresholds);
        }
      }
      THEN("each passes, and the strip a band eats off the edge where it leaves the part is lost data, no evidence") {
        // Stopped where half the band's width had run off the part, the strip beyond weighed 34-53 mm2 here (the
        // shipped catalogue's plate_4h pass 870010 under `glare`: 286 mm2, rejected).
        INFO("largest missing " << tally.worst_missing_m2 * 1e6 << " mm2; " << tally.passed << " of " << tally.scans
                                << " pass");
        CHECK(tally.passed == tally.scans);
        CHECK(tally.worst_missing_m2 < 0.0022 * 0.0022 * 1.5);
      }
    }
    WHEN("a 44 mm glare band that leaves 10 % of the points lies over where plate_5h has its fifth hole") {
      const auto scan = with_glare_residue(clean, cx - 0.022, cx + 0.022, 0.10, 812);
      const TemplateModel& five = cat.models()[2];
      const MatchReport own = cat.cascade().evaluate(m, scan);
      const MatchReport twin = cat.cascade().evaluate(five, scan);
      THEN("plate_4h passes and plate_5h does not: the residue covers its hole, which has no point at all") {
        INFO("plate_4h: extra " << own.extra_area_m2 * 1e6 << " missing " << own.missing_area_m2 * 1e6
                                << " mm2; plate_5h: extra " << twin.extra_area_m2 * 1e6 << " (max "
                                << five.thresholds.max_extra_area_m2 * 1e6 << ") mm2");
        CHECK(own.passes(m.thresholds));
        CHECK(twin.extra_area_m2 > 0.8 * std::numbers::pi * 0.02 * 0.02);
        CHECK_FALSE(twin.passes(five.thresholds));
      }
    }
    WHEN(
        "a 44 mm band leaves 2 % of the points, and 6 over where plate_5h has its fifth hole (under 3 % of its "
        "cells)") {
      // (Shipped catalogue under `glare`, plate_4h s1180006: 5 residue cells in the 219 of plate_5h's fifth hole,
      // 2.3 %; with the 3 % share of before, both plates passed and the pass was unknown.)
      const TemplateModel& five = cat.models()[2];
      const auto cy = static_cast<float>(mean_point(clean).y());
      auto scan = with_glare_residue(clean, cx - 0.022, cx + 0.022, 0.02, 823);
      std::erase_if(scan, [&](const ScanPoint& p) { return std::hypot(p.x - cx, p.y - cy) < 0.02F; });
      for (int k = 0; k < 6; ++k) {
        const double a = k * std::numbers::pi / 3.0;
        const Eigen::Vector2d at(cx + 0.009 * std::cos(a), cy + 0.009 * std::sin(a));
        const auto nearest = std::min_element(clean.begin(), clean.end(), [&](const ScanPoint& p, const ScanPoint& q) {
          return (Eigen::Vector2d(p.x, p.y) - at).squaredNorm() < (Eigen::Vector2d(q.x, q.y) - at).squaredNorm();
        });
        scan.push_back(*nearest);
      }
      const MatchReport own = cat.cascade().evaluate(m, scan);
      const MatchReport twin = cat.cascade().evaluate(five, scan);
      THEN("plate_5h is rejected, plate_4h passes: a hole has no point, and 6 points are no stray outliers") {
        INFO("plate_4h: missing " << own.missing_area_m2 * 1e6 << " mm2; plate_5h: extra " << twin.extra_area_m2 * 1e6
                                  << " (max " << five.thresholds.max_extra_area_m2 * 1e6 << ") mm2");
        CHECK(own.passes(m.thresholds));
        CHECK(twin.extra_area_m2 > 0.8 * std::numbers::pi * 0.02 * 0.02);
        CHECK_FALSE(twin.passes(five.thresholds));
      }
    }
    WHEN("a plate_5h scan under that band holds 3 stray points inside its fifth hole, at the sheet's depth") {
      const TemplateModel& five = cat.models()[2];
      auto scan = without_band(sample_part(part("plate_5h"), kTestPose, 819), cx - 0.022, cx + 0.022);
      const auto cy = static_cast<float>(mean_point(scan).y());
      const ScanPoint sheet = *std::min_element(scan.begin(), scan.end(), [&](const ScanPoint& p, const ScanPoint& q) {
        return std::hypot(p.x - cx, p.y - cy - 0.03F) < std::hypot(q.x - cx, q.y - cy - 0.03F);
      });
      for (int k = 0; k < 3; ++k) {
        ScanPoint p = sheet;
        p.x = cx + 0.008F * static_cast<float>(k - 1);
        p.y = cy + 0.004F * static_cast<float>(k - 1);
        scan.push_back(p);
      }
      const MatchReport r = cat.cascade().evaluate(five, scan);
      THEN("plate_5h still passes: so few points in a hole are outliers, not material") {
        INFO("extra " << r.extra_area_m2 * 1e6 << " (max " << five.thresholds.max_extra_area_m2 * 1e6 << ") mm2");
        CHECK(r.passes(five.thresholds));
      }
    }
    WHEN("glare bands 35 mm wide leave 3, 10 or 15 % of the points, at four places each") {
      int passed = 0, checked = 0;
      std::string failures;
      for (const double share : {0.03, 0.10, 0.15}) {
        for (int k = 0; k < 4; ++k) {
          const double x0 = cx - 0.12 + 0.06 * k;
          const auto scan = with_glare_residue(clean, x0, x0 + 0.035, share, 820 + static_cast<int>(100 * share) + k);
          const MatchReport r = cat.cascade().evaluate(m, scan);
          ++checked;
          if (r.passes(m.thresholds)) {
            ++passed;
          } else {
            double value = 0.0, limit = 0.0;
            const algo::RejectReason reason = algo::first_failed_gate(r, m.thresholds, value, limit);
            failures += " " + std::to_string(share) + "@" + std::to_string(k) + ": " +
                        std::string(algo::to_string(reason)) + " " + std::to_string(value) + " > " +
                        std::to_string(limit);
          }
        }
      }
      THEN("every one is accepted: no gap between the residue's points is taken for a hole") {
        INFO("failed:" << failures);
        CHECK(passed == checked);
      }
    }
    WHEN("the plate_4h template lacks cells in a lattice of specks 11 mm apart (gaps of its taught scan)") {
      // A taught scan with a point-free speck of 2.5 mm every 11 mm around where plate_5h has its fifth hole: the
      // template lacks single cells there, as templates of the simulated cell do (10603 mixed, rnd10 s730003).
      auto speckled = sample_part(part("plate_4h"), kTaughtPose, 101);
      const Eigen::Vector3d c = mean_point(speckled);
      std::erase_if(speckled, [&](const ScanPoint& p) {
        const double u = std::remainder(p.x - c.x(), 0.011), v = std::remainder(p.y - c.y(), 0.011);
        return std::abs(p.x - c.x()) < 0.05 && u * u + v * v < 0.00125 * 0.00125;
      });
      static const std::unique_ptr<Template> t = teach_from("plate_4h", kTaughtPose, std::move(speckled));
      TemplateModel gaps = model_of(*t, 0, 101);
      gaps.thresholds = learn(cat.cascade(), gaps, "plate_4h", 400);
      const auto five =
          with_glare_residue(sample_part(part("plate_5h"), kTestPose, 816), cx - 0.022, cx + 0.022, 0.05, 817);
      const auto own = with_glare_residue(clean, cx - 0.022, cx + 0.022, 0.05, 818);
      const MatchReport r5 = cat.cascade().evaluate(gaps, five);
      const MatchReport r4 = cat.cascade().evaluate(gaps, own);
      double value4 = 0.0, limit4 = 0.0;
      const algo::RejectReason gate4 = algo::first_failed_gate(r4, gaps.thresholds, value4, limit4);
      THEN("a 44 mm band that leaves 5 % of the points over plate_5h's fifth hole still shows the hole") {
        INFO("plate_5h: missing " << r5.missing_area_m2 * 1e6 << " mm2 (max "
                                  << gaps.thresholds.max_missing_area_m2 * 1e6 << "), lost " << r5.lost_area_m2 * 1e6
                                  << " mm2; plate_4h: missing " << r4.missing_area_m2 * 1e6 << " mm2, extra "
                                  << r4.extra_area_m2 * 1e6 << ", hole pattern " << r4.hole_pattern_m2 * 1e6
                                  << ", gate " << algo::to_string(gate4) << " " << value4 << " > " << limit4);
        CHECK_FALSE(r5.passes(gaps.thresholds));
        CHECK(r4.passes(gaps.thresholds));
      }
    }
    WHEN("the scan is of plate_5h and that 44 mm band, leaving 10 % of the points, lies over its fifth hole") {
      const auto scan =
          with_glare_residue(sample_part(part("plate_5h"), kTestPose, 813), cx - 0.022, cx + 0.022, 0.10, 814);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is not taken for plate_4h: a 40 mm empty disc is no gap between the residue's points") {
        // (The residue leaves about one cell in five occupied: a 40 mm disc empty by chance has odds below e^-50.
        // 10403 mixed, pass 680004: a slot half under such a band made an untaught twin pass as its sibling.)
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_missing_area_m2 * 1e6
                        << "), lost " << r.lost_area_m2 * 1e6 << " mm2, coverage " << r.coverage);
        CHECK(r.missing_area_m2 > 0.5 * std::numbers::pi * 0.02 * 0.02);
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("the scan is of plate_5h and a 30 mm band that leaves no point covers the left 3/4 of its fifth hole") {
      const auto scan = without_band(sample_part(part("plate_5h"), kTestPose, 815), cx - 0.035, cx - 0.005);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is not taken for plate_4h: the hole's part beside the band is a hole, not the band's edge") {
        // (10603 mixed, rnd10 s730001: an untaught twin's slot, half under such a band, was weighed with the band.)
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_missing_area_m2 * 1e6
                        << "), lost " << r.lost_area_m2 * 1e6 << " mm2");
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("the scan is of plate_5h and a glare band that leaves 3 % of the points crosses it beside the hole") {
      // (A band over the hole itself would hide it: what no point shows cannot be told; the README says so.)
      const auto scan =
          with_glare_residue(sample_part(part("plate_5h"), kTestPose, 807), cx - 0.1, cx - 0.07, 0.03, 808);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("it is not taken for plate_4h: the empty hole next to lost data is still a hole") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " mm2, coverage " << r.coverage);
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("a 52 mm wide tab sticks 185 mm out of its right edge (another part's shape, not a chain)") {
      const MatchReport r = cat.cascade().evaluate(m, with_tab_on_right(clean, 0.052, 0.185));
      THEN("the block weighs fully and rejects it: a band that wide is material, not an artefact") {
        INFO("extra " << r.extra_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_extra_area_m2 * 1e6 << ")");
        CHECK(r.extra_area_m2 > 0.5 * 0.052 * 0.185);
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("the scan has a 20 mm rib the template lacks, its walls shadowed (a long empty strip either side)") {
      float cy = 0.0F;
      for (const ScanPoint& p : clean) cy += p.y;
      cy /= static_cast<float>(clean.size());
      // From the bottom edge up to 100 mm below the top: open at one end, like a glare band touching the outline.
      const Eigen::AlignedBox2d rib(Eigen::Vector2d(cx + 0.05, cy - 0.5), Eigen::Vector2d(cx + 0.07, cy + 0.25));
      const MatchReport r = cat.cascade().evaluate(m, with_rib(clean, rib, 0.02, 0.006));
      THEN("the rib weighs fully and rejects it: depths that disagree are contradiction, whatever their shape") {
        INFO("missing " << r.missing_area_m2 * 1e6 << " extra " << r.extra_area_m2 * 1e6 << " mm2");
        CHECK(r.missing_area_m2 + r.extra_area_m2 > 0.5 * 0.02 * 0.5);
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("the scan is of a twin 5 mm taller (the same holes, about two grid cells more sheet)") {
      sim::PartSpec taller = part("plate_4h");
      taller.height_mm += 5.0;
      const MatchReport r = cat.cascade().evaluate(m, sample_part(taller, kTestPose, 809));
      double value = 0.0, limit = 0.0;
      const algo::RejectReason reason = algo::first_failed_gate(r, m.thresholds, value, limit);
      THEN("the outer size rejects it, which no area can: the fit splits the 5 mm into 2.5 mm at either edge") {
        INFO("size dx " << r.size_dx_m * 1e3 << " dy " << r.size_dy_m * 1e3 << " mm; centres "
                        << m.thresholds.size_centre_x_m * 1e3 << ", " << m.thresholds.size_centre_y_m * 1e3
                        << "; limit " << m.thresholds.max_size_dev_m * 1e3 << " mm; missing " << r.missing_area_m2 * 1e6
                        << " extra " << r.extra_area_m2 * 1e6 << " mm2; hole pattern " << r.hole_pattern_m2 * 1e6
                        << " > " << m.thresholds.max_hole_pattern_m2 * 1e6 << " mm2");
        CHECK(reason == algo::RejectReason::kSize);
        CHECK(r.size_dy_m - m.thresholds.size_centre_y_m == Approx(0.005).margin(0.0017));
      }
    }
    WHEN("5 % of the points drop out") {
      const MatchReport r = cat.cascade().evaluate(m, with_dropouts(clean, 0.05, 802));
      THEN("it is accepted") {
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("a 9 mm chain hangs 60 mm above it") {
      const MatchReport r = cat.cascade().evaluate(m, with_chain(clean, 0.009, 0.06));
      THEN("it is accepted: a thin band touching the part at one end only") {
        INFO("extra " << r.extra_area_m2 * 1e6 << " mm2 (max " << m.thresholds.max_extra_area_m2 * 1e6 << ")");
        CHECK(r.passes(m.thresholds));
      }
    }
    WHEN("the scan is of plate_5h (a 40 mm hole the template lacks) and has the glare band too") {
      const auto scan = without_band(sample_part(part("plate_5h"), kTestPose, 803), cx - 0.1, cx - 0.07);
      const MatchReport r = cat.cascade().evaluate(m, scan);
      THEN("the enclosed hole still weighs fully and rejects it") {
        CHECK(r.missing_area_m2 > m.thresholds.max_missing_area_m2);
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
    WHEN("the scan lacks a 40 mm strip along its right edge (a narrower part)") {
      float right = -1e9F;
      for (const ScanPoint& p : clean) right = std::max(right, p.x);
      const MatchReport r = cat.cascade().evaluate(m, without_band(clean, right - 0.04, right + 0.01));
      THEN("the strip along the edge weighs fully and rejects it") {
        CHECK_FALSE(r.passes(m.thresholds));
      }
    }
  }
}

TEST_CASE("learn_thresholds leaves out a taught scan that disagrees and keeps a margin to another part's scan",
          "[cascade]") {
  CascadeParams p;
  std::vector<MatchReport> own(8);
  for (std::size_t i = 0; i < own.size(); ++i) {
    own[i].pm.error = 2e-4 + 1e-5 * static_cast<double>(i);
    own[i].missing_area_m2 = (20.0 + 3.0 * static_cast<double>(i)) * 1e-6;
    own[i].extra_area_m2 = (10.0 + 2.0 * static_cast<double>(i)) * 1e-6;
    own[i].coverage = 0.999;
    own[i].scan_outliers = 0.0005;
  }
  // Given one taught scan with a glare band (a huge missing area) among eight that agree
  std::vector<MatchReport> with_glare = own;
  with_glare[3].missing_area_m2 = 3000e-6;
  // When the thresholds are learnt
  const algo::ThresholdLearning clean = algo::learn_thresholds(own, {}, p);
  const algo::ThresholdLearning glare = algo::learn_thresholds(with_glare, {}, p);
  // Then the glare scan is flagged and the thresholds are those of the scans that agree
  CHECK(clean.flagged.empty());
  REQUIRE(glare.flagged.size() == 1);
  CHECK(glare.flagged[0] == 3);
  CHECK(glare.thresholds.max_missing_area_m2 <= clean.thresholds.max_missing_area_m2);
  CHECK(glare.thresholds.max_missing_area_m2 < 500e-6);  // a 40 mm hole (~500 mm^2 after the window) still counts
  // Given another part's scan that would pass (a 5 mm longer twin: only its error is a little higher)
  MatchReport twin = own[0];
  twin.pm.error = 0.5 * (own.back().pm.error + clean.thresholds.max_error);
  REQUIRE(twin.passes(clean.thresholds));
  const algo::ThresholdLearning margin = algo::learn_thresholds(own, std::vector<MatchReport>{twin}, p);
  // Then it no longer passes, every own scan still does, and the other figures are untouched
  CHECK_FALSE(twin.passes(margin.thresholds));
  for (const MatchReport& r : own) CHECK(r.passes(margin.thresholds));
  CHECK(margin.thresholds.max_missing_area_m2 == clean.thresholds.max_missing_area_m2);
  CHECK(margin.other_scans_rejected == 1);
  // A twin no figure tells apart is reported, not hidden
  const algo::ThresholdLearning same = algo::learn_thresholds(own, std::vector<MatchReport>{own[2]}, p);
  CHECK(same.other_scans_inseparable == 1);
}

TEST_CASE("learn_thresholds only ever lowers the own-class limits for other parts' scans", "[cascade]") {
  // train's rival matching relies on this (Cascade::evaluate's gross_limits): the own-class limits bound the
  // learnt ones, so a rival failing them by far fails the learnt ones by far, and decide() skips its retry too.
  CascadeParams p;
  std::mt19937_64 rng(1101);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const auto report = [&](double scale) {
    MatchReport r;
    r.pm.error = scale * (1e-4 + 8e-4 * u(rng));
    r.missing_area_m2 = scale * (10.0 + 300.0 * u(rng)) * 1e-6;
    r.extra_area_m2 = scale * (10.0 + 300.0 * u(rng)) * 1e-6;
    r.coverage = 1.0 - scale * 0.004 * u(rng);
    r.scan_outliers = scale * 0.004 * u(rng);
    r.size_dx_m = scale * 0.002 * (u(rng) - 0.5);
    r.size_dy_m = scale * 0.002 * (u(rng) - 0.5);
    return r;
  };
  int lowered = 0;
  for (int trial = 0; trial < 200; ++trial) {
    std::vector<MatchReport> own(12), others(30);
    for (MatchReport& r : own) r = report(1.0);
    for (MatchReport& r : others) r = report(0.5 + 3.0 * u(rng));  // some pass the own-class limits, most do not
    const algo::TemplateThresholds alone = algo::learn_thresholds(own, p);
    const algo::TemplateThresholds learnt = algo::learn_thresholds(own, others, p).thresholds;
    INFO("trial " << trial);
    CHECK(learnt.max_error <= alone.max_error);
    CHECK(learnt.max_missing_area_m2 <= alone.max_missing_area_m2);
    CHECK(learnt.max_extra_area_m2 <= alone.max_extra_area_m2);
    CHECK(learnt.max_uncovered <= alone.max_uncovered);
    CHECK(learnt.max_outliers <= alone.max_outliers);
    CHECK(learnt.max_size_dev_m <= alone.max_size_dev_m);
    CHECK(learnt.size_centre_x_m == alone.size_centre_x_m);
    CHECK(learnt.size_centre_y_m == alone.size_centre_y_m);
    lowered += learnt.max_error < alone.max_error || learnt.max_missing_area_m2 < alone.max_missing_area_m2 ||
                       learnt.max_extra_area_m2 < alone.max_extra_area_m2 ||
                       learnt.max_uncovered < alone.max_uncovered || learnt.max_outliers < alone.max_outliers ||
                       learnt.max_size_dev_m < alone.max_size_dev_m
                   ? 1
                   : 0;
  }
  CHECK(lowered > 20);  // the margin step did act in many trials (the property is not vacuous)
}

TEST_CASE("learn_thresholds separates a twin by a levelled error far below the coarse error floor", "[cascade]") {
  // Given own-class matches that err by 3-8e-6 (levelled; catalogue 8302's rnd03 against its template) with small
  // blobs, and a twin (louvres where the part has ribs) whose areas and shares are the same but whose error is
  // 1.6e-5 and more: every figure but the error passes, and the error's coarse gate (max * 2 + 6e-4) too
  CascadeParams p;
  std::vector<MatchReport> own(12);
  for (std::size_t i = 0; i < own.size(); ++i) {
    own[i].pm.error = 3e-6 + 4.5e-7 * static_cast<double>(i);
    own[i].missing_area_m2 = 5e-6;
    own[i].extra_area_m2 = (i % 3) * 5e-6;
    own[i].coverage = 0.99998;
    own[i].scan_outliers = 0.0;
  }
  std::vector<MatchReport> twins;
  for (double e : {1.6e-5, 1.9e-5, 2.8e-5, 1.4e-4}) {
    MatchReport t = own[5];
    t.pm.error = e;
    twins.push_back(t);
  }
  REQUIRE(twins[0].passes(algo::learn_thresholds(own, {}, p).thresholds));
  // When the thresholds are learnt with the twin's scans as the runner-up
  const algo::ThresholdLearning learnt = algo::learn_thresholds(own, twins, p);
  // Then every twin scan fails on the error, every own scan still passes, and nothing is reported inseparable
  INFO("max_error " << learnt.thresholds.max_error);
  for (const MatchReport& t : twins) CHECK_FALSE(t.passes(learnt.thresholds));
  for (const MatchReport& r : own) CHECK(r.passes(learnt.thresholds));
  CHECK(learnt.other_scans_inseparable == 0);
  CHECK(learnt.thresholds.max_error > 1.4 * own.back().pm.error);  // a margin above the own class, not its maximum
  // And with the old floor for the margin (a quarter of the error floor), the same twin could not be told apart
  CascadeParams coarse = p;
  coarse.error_margin_floor = 0.25 * p.error_floor;
  CHECK(algo::learn_thresholds(own, twins, coarse).other_scans_inseparable == 4);
}

SCENARIO("A passing class's look-alikes are verified before it is accepted, and two that pass alike are unknown",
         "[cascade][policy]") {
  GIVEN("the four classes plus a fifth whose template is plate_4h's again (a twin no check can tell apart)") {
    Catalogue4& cat = catalogue4();
    std::vector<TemplateModel> models(cat.models().begin(), cat.models().end());
    TemplateModel twin = models[0];
    twin.class_index = 4;
    twin.part_id = 105;
    models.push_back(twin);
    const auto scan = sample_part(part("plate_4h"), kTestPose, 901);
    const ClassProbability svm[] = {{0, 0.95}, {1, 0.02}, {2, 0.015}, {3, 0.01}, {4, 0.005}};
    WHEN("the twin is not known as a look-alike and the SVM is sure of plate_4h") {
      const Decision d = cat.cascade().decide(svm, models, scan, far_deadline());
      THEN("plate_4h is accepted after one verification: nothing asked for the twin") {
        CHECK(d.class_index == 0);
        CHECK(d.verified_count == 1);
      }
    }
    WHEN("training recorded them as look-alikes of each other") {
      const int of_first[] = {4};
      const int of_twin[] = {0};
      models[0].confusable = of_first;
      models[4].confusable = of_twin;
      const Decision d = cat.cascade().decide(svm, models, scan, far_deadline());
      THEN("the twin is verified too, passes as well, and the scan is unknown (ambiguous), never a guess") {
        CHECK(d.source == DecisionSource::kUnknown);
        CHECK(d.class_index == -1);
        CHECK(d.verified_count == 2);
        CHECK(d.unknown_reason == algo::RejectReason::kAmbiguous);
        CHECK(d.candidates[0].passed);
        CHECK(d.candidates[4].passed);
        CHECK(d.candidates[4].rejected_by == algo::RejectReason::kAmbiguous);
      }
    }
    WHEN("the look-alike is the one-hole sibling plate_5h") {
      const int of_first[] = {2};
      const int of_sibling[] = {0};
      models.pop_back();
      models[0].confusable = of_first;
      models[2].confusable = of_sibling;
      const Decision d = cat.cascade().decide(svm, models, scan, far_deadline());
      THEN("it is verified, fails on the hole, and plate_4h is accepted") {
        CHECK(d.class_index == 0);
        CHECK(d.verified_count == 2);
        CHECK(d.candidates[2].verified);
        CHECK_FALSE(d.candidates[2].passed);
      }
    }
  }
}

namespace {
bool same_or_both_nan(double a, double b) {
  return (std::isnan(a) && std::isnan(b)) || a == b;
}
}  // namespace

TEST_CASE("decide() allocates nothing", "[cascade][alloc]") {
  // Given a cascade and its templates, built at start-up
  Catalogue4& cat = catalogue4();
  const auto scan = sample_part(part("plate_5h"), kTestPose, 701);
  const ClassProbability sure_wrong[] = {{0, 0.93}, {2, 0.04}, {1, 0.02}, {3, 0.01}};  // SVM path, fallback, PM
  const ClassProbability unsure[] = {{1, 0.50}, {3, 0.45}, {0, 0.03}, {2, 0.02}};      // PM path, unknown
  const auto untaught = sample_part(part("frame_window"), kTestPose, 702);
  (void)cat.cascade().decide(sure_wrong, cat.models(), scan, far_deadline());  // warm-up
  // When it decides along every path
  long allocations = 0;
  Decision a, b, c;
  {
    const test::AllocationWindow window;  // proves decide() never reaches the heap
    a = cat.cascade().decide(sure_wrong, cat.models(), scan, far_deadline());
    b = cat.cascade().decide(unsure, cat.models(), untaught, far_deadline());
    c = cat.cascade().decide(sure_wrong, cat.models(), scan, Clock::now() - std::chrono::seconds(1));
    allocations = window.count();
  }
  // Then no allocation happened
  CHECK(allocations == 0);
  CHECK(a.source == DecisionSource::kPm);
  CHECK(b.source == DecisionSource::kUnknown);
  CHECK(c.source == DecisionSource::kTimeout);
}

TEST_CASE("One scan prepared once and checked against several templates reports what evaluate() reports", "[cascade]") {
  // Given the four taught classes and a plate_5h scan
  Catalogue4& cat = catalogue4();
  const auto scan = sample_part(part("plate_5h"), kTestPose, 703);
  std::vector<MatchReport> single;
  for (std::size_t c = 0; c < cat.models().size(); ++c) {
    single.push_back(cat.cascade().evaluate(cat.models()[c], scan, &cat.models()[c].thresholds));
  }
  // When another scan was checked last, then this one is set once and every template is checked in turn (the outline
  // kept from the first check that needs it), in reverse order, and the first again
  (void)cat.cascade().evaluate(cat.models()[1], sample_part(part("ribbed_v4"), kTestPose, 704));
  cat.cascade().set_scan(scan);
  std::vector<MatchReport> prepared(cat.models().size());
  for (std::size_t c = cat.models().size(); c-- > 0;) {
    prepared[c] = cat.cascade().evaluate_prepared(cat.models()[c], scan, &cat.models()[c].thresholds);
  }
  const MatchReport again = cat.cascade().evaluate_prepared(cat.models()[0], scan, &cat.models()[0].thresholds);
  // Then every figure is the same as scan-by-scan evaluation's
  for (std::size_t c = 0; c < cat.models().size(); ++c) {
    INFO("template " << c);
    CHECK(prepared[c].pm.error == single[c].pm.error);
    CHECK(prepared[c].pm.pose.x_m == single[c].pm.pose.x_m);
    CHECK(prepared[c].pm.pose.theta_rad == single[c].pm.pose.theta_rad);
    CHECK(same_or_both_nan(prepared[c].missing_area_m2, single[c].missing_area_m2));
    CHECK(same_or_both_nan(prepared[c].extra_area_m2, single[c].extra_area_m2));
    CHECK(same_or_both_nan(prepared[c].coverage, single[c].coverage));
    CHECK(same_or_both_nan(prepared[c].hole_pattern_m2, single[c].hole_pattern_m2));
    CHECK(prepared[c].check_pose.x_m == single[c].check_pose.x_m);
    CHECK(prepared[c].passes(cat.models()[c].thresholds) == single[c].passes(cat.models()[c].thresholds));
  }
  CHECK(again.pm.error == single[0].pm.error);
  CHECK(same_or_both_nan(again.missing_area_m2, single[0].missing_area_m2));
  // And the templates were not all alike for this scan (the comparison covers a pass and a failure)
  CHECK(single[0].pm.error != single[1].pm.error);
}

SCENARIO(
    "Of two candidates that both pass, the one with clearly less evidence against it wins, whichever the SVM "
    "ranks first",
    "[cascade][policy]") {
  GIVEN(
      "a plate_4h scan, and plate_5h's template with gates so wide that it passes too, though the scan has material "
      "where its fifth hole is") {
    Catalogue4& cat = catalogue4();
    std::vector<TemplateModel> models(cat.models().begin(), cat.models().end());
    algo::TemplateThresholds& wide = models[2].thresholds;
    wide.max_error = 1.0;
    wide.max_missing_area_m2 = wide.max_extra_area_m2 = 1.0;
    wide.max_uncovered = wide.max_outliers = 1.0;
    wide.max_size_dev_x_m = wide.max_size_dev_y_m = wide.max_size_dev_m = std::numeric_limits<double>::infinity();
    const auto scan = sample_part(part("plate_4h"), kTestPose, 1201);
    // Independent of decide(): each template's evidence on its own; the hole's material is a clear margin.
    const MatchReport own = cat.cascade().evaluate(models[0], scan);
    const MatchReport sibling = cat.cascade().evaluate(models[2], scan);
    INFO("evidence plate_4h " << own.evidence_m2 * 1e6 << " mm2, plate_5h " << sibling.evidence_m2 * 1e6 << " mm2");
    REQUIRE(own.passes(models[0].thresholds));
    REQUIRE(sibling.passes(wide));
    REQUIRE(own.evidence_m2 <= cat.cascade().params().margin_ratio * sibling.evidence_m2);
    REQUIRE(sibling.evidence_m2 - own.evidence_m2 >= cat.cascade().params().margin_floor_m2);
    for (const bool sibling_first : {true, false}) {
      WHEN((sibling_first ? "the SVM ranks plate_5h first and plate_4h close behind"
                          : "the SVM ranks plate_4h first and plate_5h close behind")) {
        const int first = sibling_first ? 2 : 0, second = sibling_first ? 0 : 2;
        const ClassProbability svm[] = {{first, 0.55}, {second, 0.40}, {1, 0.03}, {3, 0.02}};
        const Decision d = cat.cascade().decide(svm, models, scan, far_deadline());
        THEN("both are verified and pass, and plate_4h, with the least evidence, is the decision") {
          REQUIRE(d.verified_count == 2);
          CHECK(d.candidates[0].passed);
          CHECK(d.candidates[1].passed);
          CHECK(d.source == DecisionSource::kPm);
          CHECK(d.class_index == 0);
          CHECK(d.part_id == 101);
          CHECK(d.second_class_index == 2);
        }
      }
    }
  }
}

SCENARIO(
    "A look-alike that fails only its outer size leaves the winner ambiguous when it fails narrowly, not when it "
    "fails by a size twin's millimetres",
    "[cascade][policy]") {
  GIVEN(
      "a plate_4h scan, and a look-alike of plate_4h whose template is plate_4h's but whose size centre lies D above "
      "the scan's (limit 3.5 mm): it fails the size gate alone, with the same evidence as plate_4h") {
    Catalogue4& cat = catalogue4();
    const auto scan = sample_part(part("plate_4h"), kTestPose, 1301);
    const MatchReport own = cat.cascade().evaluate(cat.models()[0], scan);
    REQUIRE(own.passes(cat.models()[0].thresholds));
    REQUIRE(std::isfinite(own.size_dx_m));
    REQUIRE(std::isfinite(own.size_dy_m));
    const algo::CascadeParams& params = cat.cascade().params();
    const double limit_m = 0.0035;
    // Within near_fail_factor of the limit either way; the slack is (near_fail_factor - 1) * size_floor_m = 0.75 mm.
    const double slack_m = (params.near_fail_factor - 1.0) * params.size_floor_m;
    REQUIRE((limit_m + 2.0 * slack_m) < params.near_fail_factor * limit_m);
    static constexpr int kLookAlike[] = {1};
    for (const double beyond_m : {0.4 * slack_m, 2.0 * slack_m}) {
      WHEN("the look-alike's size deviation is " << (limit_m + beyond_m) * 1e3 << " mm") {
        std::vector<TemplateModel> models(cat.models().begin(), cat.models().end());
        models[0].confusable = kLookAlike;
        models[1] = cat.models()[0];
        models[1].class_index = 1;
        models[1].part_id = 102;
        models[1].confusable = {};
        algo::TemplateThresholds& t = models[1].thresholds;
        t.size_centre_x_m = own.size_dx_m;
        t.size_centre_y_m = own.size_dy_m - (limit_m + beyond_m);
        t.max_size_dev_x_m = t.max_size_dev_y_m = t.max_size_dev_m = limit_m;
        const ClassProbability svm[] = {{0, 0.55}, {1, 0.40}, {2, 0.03}, {3, 0.02}};
        const Decision d = cat.cascade().decide(svm, models, scan, far_deadline());
        REQUIRE(d.verified_count >= 2);
        REQUIRE(d.candidates[1].class_index == 1);
        REQUIRE(d.candidates[1].rejected_by == algo::RejectReason::kSize);
        if (beyond_m < slack_m) {
          THEN("a narrow failure: no clear margin, unknown") {
            CHECK(d.source == DecisionSource::kUnknown);
          }
        } else {
          THEN("a clear size difference: plate_4h") {
            CHECK(d.source == DecisionSource::kPm);
            CHECK(d.class_index == 0);
          }
        }
      }
    }
  }
}

namespace {

// Thresholds nothing fails: the full pose tests are about the pose of an accepted part, not about verification.
algo::TemplateThresholds accept_anything() {
  algo::TemplateThresholds t;
  t.max_error = 1.0;
  t.max_missing_area_m2 = t.max_extra_area_m2 = t.max_hole_pattern_m2 = 1.0;
  t.max_uncovered = t.max_outliers = 1.0;
  return t;
}

// The true full pose of a scan placed at `scan` relative to a template placed at `taught` (both by
// part_to_carrier), about c: p_scan = c + R (p_template - c) + d with R = R_scan R_taught^T, d = the image of c less c.
// Returned as x, y, z [m] and rx, ry, theta [rad] of R = R_z(theta) R_y(ry) R_x(rx).
std::array<double, algo::kPoseAxes> true_full_pose(const sim::PartSpec& spec, const sim::PartPose& taught,
                                                   const sim::PartPose& scan, const Eigen::Vector3d& c) {
  const Eigen::Isometry3d a = part_to_carrier(spec, scan) * part_to_carrier(spec, taught).inverse();
  const Eigen::Matrix3d r = a.linear();
  const Eigen::Vector3d d = a * c - c;
  return {d.x(), d.y(), d.z(), std::atan2(r(2, 1), r(2, 2)), -std::asin(r(2, 0)), std::atan2(r(1, 0), r(0, 0))};
}

}  // namespace

SCENARIO("An accepted part gets its full pose and a 1-sigma per axis, an axis its geometry does not fix is invalid",
         "[cascade][full_pose]") {
  using algo::PoseAxis;
  constexpr sim::PartPose kSwungPose{-0.017, 0.012, 2.1 * kDeg, 2.6 * kDeg, -1.2 * kDeg, 0.003};
  const ClassProbability sure[] = {{0, 0.9}};
  Cascade cascade(CascadeParams{}, pm_params(), test_grid());
  GIVEN("plate_4h taught, then scanned swung by 2.6 deg, tilted by -1.2 deg, 3 mm nearer and shifted") {
    const Template& t = taught("plate_4h");
    TemplateModel model = model_of(t, 0, 101);
    model.thresholds = accept_anything();
    const Eigen::Vector3d c(model.centroid_m.x(), model.centroid_m.y(), model.centroid_z_m);
    const auto truth = true_full_pose(part("plate_4h"), t.pose, kSwungPose, c);
    const auto scan = sample_part(part("plate_4h"), kSwungPose, 811);
    const TemplateModel models[] = {model};
    const Decision d = cascade.decide(sure, models, scan, far_deadline());
    THEN(
        "x within half a profile pitch, y within 0.5 mm, z within 0.3 mm, rx, ry and theta within 0.1 deg; every sigma "
        "set") {
      REQUIRE(d.accepted());
      const std::array<double, algo::kPoseAxes> got = {d.pose.x_m, d.pose.y_m, d.z_m,
                                                       d.rx_rad,   d.ry_rad,   d.pose.theta_rad};
      INFO("error x " << (got[0] - truth[0]) * 1e3 << " y " << (got[1] - truth[1]) * 1e3 << " z "
                      << (got[2] - truth[2]) * 1e3 << " mm, rx " << (got[3] - truth[3]) / kDeg << " ry "
                      << (got[4] - truth[4]) / kDeg << " theta " << (got[5] - truth[5]) / kDeg << " deg");
      // Along x the part is sampled one profile per 2.2 mm: its edges (and so x) are known to about half of that.
      CHECK(std::abs(got[0] - truth[0]) < 0.0011);
      CHECK(std::abs(got[1] - truth[1]) < 0.0005);
      CHECK(std::abs(got[2] - truth[2]) < 0.0003);
      for (std::size_t a = 3; a < algo::kPoseAxes; ++a) CHECK(std::abs(got[a] - truth[a]) < 0.1 * kDeg);
      for (const double s : d.pose_sigma) {
        CHECK(std::isfinite(s));
        CHECK(s > 0.0);
      }
    }
  }
  GIVEN("a flat strip 450 x 12 mm without any relief, taught and scanned like the plate") {
    sim::PartSpec strip;
    strip.name = "strip";
    strip.width_mm = 450.0;
    strip.height_mm = 12.0;
    const auto taught_scan = sample_part(strip, kTaughtPose, 812);
    const auto t = teach_from("strip", kTaughtPose, taught_scan);
    TemplateModel model = model_of(*t, 0, 7);
    model.thresholds = accept_anything();
    const auto scan = sample_part(strip, kSwungPose, 813);
    const TemplateModel models[] = {model};
    const Decision d = cascade.decide(sure, models, scan, far_deadline());
    THEN("its tilt about x (fixed only over 12 mm) is published invalid with no sigma; its swing and depth are not") {
      REQUIRE(d.accepted());
      const auto sigma = [&](PoseAxis a) { return d.pose_sigma[static_cast<std::size_t>(a)]; };
      INFO("rx " << d.rx_rad / kDeg << " deg, sigma ry " << sigma(PoseAxis::kRy) / kDeg << " deg, sigma z "
                 << sigma(PoseAxis::kZ) * 1e3 << " mm");
      CHECK(std::isnan(d.rx_rad));
      CHECK(std::isnan(sigma(PoseAxis::kRx)));
      CHECK(std::isfinite(d.ry_rad));
      CHECK(std::isfinite(d.z_m));
      CHECK(sigma(PoseAxis::kRy) <= cascade.params().max_sigma_rad);
    }
  }
  GIVEN("a template without its centroid's depth (NaN): the planar pose only") {
    TemplateModel model = model_of(taught("plate_4h"), 0, 101);
    model.thresholds = accept_anything();
    model.centroid_z_m = std::numeric_limits<double>::quiet_NaN();
    const auto scan = sample_part(part("plate_4h"), kSwungPose, 814);
    const TemplateModel models[] = {model};
    const Decision d = cascade.decide(sure, models, scan, far_deadline());
    THEN("x, y, theta are published, z, rx, ry and every sigma are not") {
      REQUIRE(d.accepted());
      CHECK(d.pose_valid);
      CHECK(std::isnan(d.z_m));
      CHECK(std::isnan(d.rx_rad));
      CHECK(std::isnan(d.ry_rad));
      for (const double s : d.pose_sigma) CHECK(std::isnan(s));
    }
  }
}

SCENARIO("The full pose is refined from the pose the check verified too, when Perfect Match's lies apart from it",
         "[cascade][full_pose]") {
  // The refinement is local: from a Perfect Match pose in another minimum it stays there, while the check's outline
  // alignment and gates verified the true one (shipped catalogue, none, 1170001..: perforated_fine s1170010 published
  // 10.9 mm off in y, louvred_panel s1170007 1.2 deg off; their check poses within 0.1 mm and 0.02 deg). On this plate
  // the refinement comes back from 25 mm and 2 deg; from 60 mm and 5 deg it ends 34 mm off.
  using algo::PoseAxis;
  Cascade cascade(CascadeParams{}, pm_params(), test_grid());
  const Template& t = taught("plate_4h");
  TemplateModel model = model_of(t, 0, 101);
  const Eigen::Vector3d c(model.centroid_m.x(), model.centroid_m.y(), model.centroid_z_m);
  constexpr sim::PartPose kPose{-0.011, 0.009, 1.9 * kDeg, 0.9 * kDeg};
  const auto truth = true_full_pose(part("plate_4h"), t.pose, kPose, c);
  const auto scan = sample_part(part("plate_4h"), kPose, 817);
  GIVEN("plate_4h's report, its Perfect Match pose then put 60 mm and 5 deg off: another minimum") {
    MatchReport r = cascade.evaluate(model, scan);
    REQUIRE(std::abs(r.check_pose.y_m - truth[1]) < 0.001);
    r.pm.pose.y_m += 0.06;
    r.pm.pose.theta_rad += 5.0 * kDeg;
    WHEN("the full pose is published from it") {
      Decision d;
      cascade.publish_full_pose(model, r, d);
      THEN("it is the one refined from the check's pose: within a profile pitch and 0.1 deg of the truth") {
        INFO("error x " << (d.pose.x_m - truth[0]) * 1e3 << " y " << (d.pose.y_m - truth[1]) * 1e3 << " mm, theta "
                        << (d.pose.theta_rad - truth[5]) / kDeg << " deg");
        CHECK(std::abs(d.pose.x_m - truth[0]) < 0.0022);
        CHECK(std::abs(d.pose.y_m - truth[1]) < 0.0011);
        CHECK(std::abs(d.pose.theta_rad - truth[5]) < 0.1 * kDeg);
        CHECK(std::isfinite(d.pose_sigma[static_cast<std::size_t>(PoseAxis::kY)]));
      }
    }
  }
}

SCENARIO("A glare band beside a window is lost data along all its length", "[cascade][evidence]") {
  GIVEN("a plate with a 110 x 130 mm window, its template and thresholds learnt from five own scans") {
    sim::PartSpec plate;
    plate.name = "windowed";
    plate.width_mm = 450;
    plate.height_mm = 650;
    plate.features = {sim::FeatureSpec{
        .kind = sim::FeatureKind::kWindow, .x_mm = -100, .y_mm = -180, .width_mm = 110, .height_mm = 130}};
    REQUIRE(sim::validate_part(plate).empty());
    Cascade cascade(CascadeParams{}, pm_params(), test_grid());
    static const std::unique_ptr<Template> t = teach_from("windowed", kTaughtPose, sample_part(plate, kTaughtPose, 61));
    std::vector<MatchReport> own;
    const TemplateModel m = learnt_at_other_poses(cascade, *t, plate, own);
    WHEN("glare bands 18 and 25 mm wide that keep 2 or 5 % of the points run the part's height over a window side") {
      const auto clean = sample_part(plate, kTestPose, 64);
      float cx = 0.0F;
      for (const ScanPoint& p : clean) cx += p.x;
      cx /= static_cast<float>(clean.size());
      ArtefactTally tally;
      for (const double at : {-0.165, -0.155, -0.055, -0.045}) {  // the window spans about -0.155 .. -0.045
        for (const double width : {0.018, 0.025}) {
          for (const double keep : {0.02, 0.05}) {
            tally.add(cascade.evaluate(m, with_glare_residue(clean, cx + at, cx + at + width, keep, 78)), m.thresholds);
          }
        }
      }
      THEN("each passes with no missing area: the window the band crosses does not bend its axis off the band") {
        // With the band's axis and width taken from the group's cells and the window's together: 3 of the 16
        // rejected, 5-305 mm2 of the band left as evidence in 9.
        INFO("largest missing " << tally.worst_missing_m2 * 1e6 << " mm2; " << tally.passed << " of " << tally.scans
                                << " pass");
        CHECK(tally.passed == tally.scans);
        CHECK(tally.worst_missing_m2 < 0.0022 * 0.0022);
      }
    }
  }
}

SCENARIO("Sparse glare residue that leaves an empty rectangle by chance is no hole", "[cascade][evidence]") {
  GIVEN("the four classes and bands of 2-5 % residue that a sweep of 672 bands found with such a rectangle") {
    // Found with 35 and 25 mm bands of 2-15 % residue at seven places over the four parts at two poses: 11 x 26
    // cell rectangles empty by chance, 12.9-15.6 points expected, weighed without the number of places they have.
    Catalogue4& cat = catalogue4();
    const std::vector<std::string> names = {"plate_4h", "ribbed_v4", "plate_5h", "ribbed_v3"};
    const sim::PartPose other{0.021, -0.013, -1.7 * kDeg, -0.9 * kDeg};
    struct Band {
      int part;
      bool other_pose;
      double share, width_m;
      int place;
    };
    const std::vector<Band> bands = {
        {0, false, 0.05, 0.035, 3}, {1, true, 0.02, 0.025, 3}, {1, true, 0.05, 0.035, 4}, {2, false, 0.03, 0.035, 6}};
    WHEN("each part's scan with its band is checked against its own template") {
      std::ostringstream failures;
      for (const Band& b : bands) {
        const auto pi = static_cast<std::size_t>(b.part);
        const int pose_i = b.other_pose ? 1 : 0;
        auto scan = sample_part(part(names[pi]), b.other_pose ? other : kTestPose, 900 + b.part * 10 + pose_i);
        float cx = 0.0F;
        for (const ScanPoint& p : scan) cx += p.x;
        cx /= static_cast<float>(scan.size());
        const double x0 = cx - 0.15 + 0.045 * b.place;
        scan = with_glare_residue(std::move(scan), x0, x0 + b.width_m, b.share,
                                  7000 + 1000 * b.part + 100 * pose_i + static_cast<int>(1000 * b.share) + b.place +
                                      static_cast<int>(b.width_m * 1000) * 13);
        const TemplateModel& m = cat.models()[pi];
        const MatchReport r = cat.cascade().evaluate(m, scan);
        if (!r.passes(m.thresholds)) {
          failures << " " << names[pi] << " " << b.share << ": missing " << r.missing_area_m2 * 1e6 << " mm2";
        }
      }
      THEN("every one is accepted") {
        INFO("rejected:" << failures.str());
        CHECK(failures.str().empty());
      }
    }
  }
}

namespace {

// Perfect Match whose reach is cut: at most 0.05 deg per iteration, ~5 deg from where it starts.
algo::PerfectMatchParams short_reach() {
  algo::PerfectMatchParams slow = pm_params();
  slow.step_max_rad = 0.0008;
  slow.step_initial_rad = 0.0008;
  return slow;
}

// A loose error limit, and the evidence gates at an own class's typical learnt values: only the check sees a turn.
algo::TemplateThresholds evidence_limits() {
  algo::TemplateThresholds limits = accept_anything();
  limits.max_missing_area_m2 = limits.max_extra_area_m2 = 150e-6;
  limits.max_uncovered = limits.max_outliers = 0.003;
  limits.max_hole_pattern_m2 = 120e-6;
  return limits;
}

// plate_4h (class 0) and its one-hole-more twin plate_5h (class 1), both with `limits`.
std::vector<TemplateModel> plate_and_twin(const algo::TemplateThresholds& limits) {
  std::vector<TemplateModel> models = {model_of(taught("plate_4h"), 0, 1), model_of(taught("plate_5h"), 1, 2)};
  for (auto& m : models) m.thresholds = limits;
  return models;
}

// The decision on `scan` with plate_4h ranked first (p 0.8) and its twin second.
Decision decide_plate_first(Cascade& cascade, const std::vector<TemplateModel>& models,
                            std::span<const ScanPoint> scan) {
  const ClassProbability svm[] = {{0, 0.8}, {1, 0.2}};
  return cascade.decide(svm, models, scan, far_deadline());
}

}  // namespace

SCENARIO("A first-ranked candidate Perfect Match does not reach from the unturned start is matched from a turned one",
         "[cascade][policy]") {
  // Fresh catalogue 11310 (plain): 5 of 20 passes of a twin pair, turned 5-9 deg and swung 3-4 deg against the taught
  // pass, left Perfect Match 150 times above its own error from the unturned start. Here its reach is cut instead
  // (at most 0.05 deg per iteration, ~5 deg in all) and the pass is turned 6 deg.
  GIVEN("plate_4h's template and a matcher that turns at most ~5 deg from where it starts") {
    Cascade cascade(generous_budget(), short_reach(), test_grid());
    algo::TemplateThresholds limits = accept_anything();
    limits.max_error = 3e-5;  // a few times an own match's error (a flat plate 4 deg off errs 5.5e-5)
    const std::vector<TemplateModel> models = plate_and_twin(limits);
    const TemplateModel& plate = models[0];
    const sim::PartPose turned{0.006, -0.004, kTaughtPose.theta_rad + 6.0 * kDeg, 0.5 * kDeg};
    const auto scan = sample_part(part("plate_4h"), turned, 77);
    WHEN("its pass turned 6 deg is decided with plate_4h ranked first") {
      const MatchReport unturned = cascade.evaluate(plate, scan);
      const Decision d = decide_plate_first(cascade, models, scan);
      THEN("Perfect Match from the unturned start fails its error limit, a turned start finds the pose") {
        INFO("unturned start: error " << unturned.pm.error << ", theta " << unturned.pm.pose.theta_rad / kDeg
                                      << " deg");
        CHECK(unturned.pm.error > plate.thresholds.max_error);
        REQUIRE(d.source != DecisionSource::kUnknown);
        CHECK(d.class_index == 0);
        CHECK(d.pose.theta_rad == Approx(true_relative_pose(taught("plate_4h"), turned).theta_rad).margin(0.1 * kDeg));
      }
    }
    WHEN("the same pass is one of the part's own scans at training or teach (evaluate_own)") {
      const MatchReport own = cascade.evaluate_own(plate, scan);
      THEN("its report is the turned start's, as decide() matches it: nothing to flag as disagreeing") {
        CHECK(own.pm.error <= plate.thresholds.max_error);
        CHECK(own.pm.pose.theta_rad ==
              Approx(true_relative_pose(taught("plate_4h"), turned).theta_rad).margin(0.1 * kDeg));
      }
    }
  }
}

SCENARIO("A first-ranked candidate whose error is within its limit but whose check fails is matched turned too",
         "[cascade][policy]") {
  // Fresh catalogue 11347 (plain), rnd02 s1140002 / s1140010: Perfect Match stopped ~5 deg short of the pass's turn
  // with an error within the loose limit the error floor sets, the check failed on 14 000 mm2 of missing edge, and
  // the turned starts ran only for an error over the limit. Here Perfect Match turns at most ~5 deg from where it
  // starts, the check is taken at its pose (no outline fit, so the outline's rematch has nothing to add), the error
  // limit is loose and the pass is turned 8 deg.
  GIVEN("plate_4h's template, a matcher that turns at most ~5 deg and a check at its pose") {
    CascadeParams at_pm = generous_budget();
    at_pm.refine_iterations = 0;
    Cascade cascade(at_pm, short_reach(), test_grid());
    algo::TemplateThresholds limits = evidence_limits();
    limits.max_error = 6e-4;  // the error floor's limit: an aligned pass errs ~1e-5
    const std::vector<TemplateModel> models = plate_and_twin(limits);
    const TemplateModel& plate = models[0];
    const sim::PartPose turned{-0.003, 0.004, kTaughtPose.theta_rad + 8.0 * kDeg, -0.5 * kDeg};
    const auto scan = sample_part(part("plate_4h"), turned, 79);
    WHEN("its pass turned 8 deg is decided with plate_4h ranked first") {
      const MatchReport first = cascade.evaluate(plate, scan);
      const Decision d = decide_plate_first(cascade, models, scan);
      THEN("from the unturned start the error passes and the check fails; a turned start finds the pose") {
        INFO("from the unturned start: Perfect Match at " << first.pm.pose.theta_rad / kDeg << " deg, error "
                                                          << first.pm.error << ", missing "
                                                          << first.missing_area_m2 * 1e6 << " mm2");
        CHECK(first.pm.error <= plate.thresholds.max_error);
        CHECK_FALSE(first.passes(plate.thresholds));
        REQUIRE(d.source != DecisionSource::kUnknown);
        CHECK(d.class_index == 0);
        CHECK(d.pose.theta_rad == Approx(true_relative_pose(taught("plate_4h"), turned).theta_rad).margin(0.1 * kDeg));
      }
    }
  }
}

SCENARIO(
    "A first-ranked candidate whose check settles on a pose turned away from Perfect Match's is matched from there",
    "[cascade][policy]") {
  // Fresh catalogue 11309 under `mixed`, rnd05: Perfect Match stopped 4-5 deg short of a pass's turn with its error
  // under the limit, the outline fit turned it most of the way (a degree short), and the check failed at both poses
  // by a few times its limits, too little for the wide outline fit. Here both reaches are cut: Perfect Match turns
  // at most ~5 deg from where it starts, the outline fit runs two iterations (a degree of turn each), and the pass is
  // turned 7 deg; the error limit is loose, so only the check sees the turn. Without the second Perfect Match from
  // the check's pose the pass is unknown (missing area 499 mm2 against 150 at 5.5 deg).
  GIVEN("plate_4h's template, a matcher that turns at most ~5 deg and an outline fit of two iterations") {
    CascadeParams short_fit = generous_budget();
    short_fit.refine_iterations = 2;
    Cascade cascade(short_fit, short_reach(), test_grid());
    const std::vector<TemplateModel> models = plate_and_twin(evidence_limits());
    const TemplateModel& plate = models[0];
    const sim::PartPose turned{0.004, -0.003, kTaughtPose.theta_rad + 7.0 * kDeg, 0.5 * kDeg};
    const auto scan = sample_part(part("plate_4h"), turned, 78);
    WHEN("its pass turned 7 deg is decided with plate_4h ranked first") {
      const MatchReport first = cascade.evaluate(plate, scan);
      const Decision d = decide_plate_first(cascade, models, scan);
      THEN("the check fails at both poses from the unturned start, Perfect Match from the check's pose passes") {
        INFO("from the unturned start: Perfect Match at " << first.pm.pose.theta_rad / kDeg << " deg, check at "
                                                          << first.check_pose.theta_rad / kDeg << " deg, missing "
                                                          << first.missing_area_m2 * 1e6 << " mm2");
        CHECK_FALSE(first.passes(plate.thresholds));
        CHECK(first.check_pose.theta_rad - first.pm.pose.theta_rad > 0.6 * kDeg);
        REQUIRE(d.source != DecisionSource::kUnknown);
        CHECK(d.class_index == 0);
        CHECK(d.pose.theta_rad == Approx(true_relative_pose(taught("plate_4h"), turned).theta_rad).margin(0.1 * kDeg));
      }
    }
  }
}
