// The part's own frame (algo/canonical) against a synthetic part moved by a known transform, the synthetic variants
// (algo/augment) and the group-aware split and folds of algo/training.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <map>
#include <numbers>
#include <set>
#include <vector>

#include "algo/augment.hpp"
#include "algo/canonical.hpp"
#include "algo/features.hpp"
#include "algo/grid.hpp"
#include "algo/training.hpp"
#include "tests/support/alloc_counter.hpp"

using namespace cellsight;

namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kPitch = 0.001;  // sample spacing of the synthetic surface (finer than a 2.2 mm cell)
constexpr double kRibHeight = 0.012;

algo::GridSpec shipped_grid() {
  return algo::GridSpec{};
}  // 296 x 500 x 182 at 2.2 mm, origin 0

// A 400 x 600 mm plate without symmetry: a rectangular, a square and a round hole and a raised rib, sheet at z = 0,
// centred on the origin (part frame). Each point knows whether it lies on the sheet.
struct PartPoint {
  double x, y, z;
  bool sheet;
};
std::vector<PartPoint> synthetic_part() {
  std::vector<PartPoint> pts;
  for (double y = -0.3; y <= 0.3; y += kPitch) {
    for (double x = -0.2; x <= 0.2; x += kPitch) {
      if (x > -0.15 && x < -0.05 && y > 0.15 && y < 0.22) continue;
      if (x > 0.05 && x < 0.12 && y > 0.0 && y < 0.07) continue;
      if (std::hypot(x - 0.1, y + 0.15) < 0.04) continue;
      const bool rib = x > -0.18 && x < 0.18 && y > -0.25 && y < -0.23;
      pts.push_back({x, y, rib ? kRibHeight : 0.0, !rib});
    }
  }
  return pts;
}

// DESIGN.md pose: p = c + R_y(swing) R_z(theta) p_part + (dx, dy, 0), c the hanging centre in the carrier frame.
struct Pose {
  double dx_m = 0.0, dy_m = 0.0, theta_rad = 0.0, swing_rad = 0.0;
};
constexpr double kCentreX = 0.33, kCentreY = 0.56, kCentreZ = 0.12;

std::vector<algo::ScanPoint> place(const std::vector<PartPoint>& part, const Pose& pose) {
  std::vector<algo::ScanPoint> out;
  out.reserve(part.size());
  const double ct = std::cos(pose.theta_rad), st = std::sin(pose.theta_rad);
  const double cs = std::cos(pose.swing_rad), ss = std::sin(pose.swing_rad);
  for (const PartPoint& p : part) {
    const double x1 = ct * p.x - st * p.y, y1 = st * p.x + ct * p.y, z1 = p.z;
    const double x2 = cs * x1 + ss * z1, z2 = -ss * x1 + cs * z1;
    out.push_back({static_cast<float>(kCentreX + x2 + pose.dx_m), static_cast<float>(kCentreY + y1 + pose.dy_m),
                   static_cast<float>(kCentreZ + z2), 0, 0});
  }
  return out;
}

struct Mapped {
  std::vector<algo::ScanPoint> points;
  algo::CanonicalPose pose;
  cv::Mat depth;
};
Mapped map_and_image(const std::vector<algo::ScanPoint>& in) {
  const algo::GridSpec spec = shipped_grid();
  algo::CanonicalScratch scratch(spec);
  Mapped m;
  m.points.resize(in.size());
  REQUIRE(algo::canonicalise(in, spec, {}, scratch, m.points, m.pose) == algo::CanonicalStatus::kOk);
  algo::OccupancyGrid grid(spec, in.size());
  (void)grid.accumulate(m.points);
  grid.depth_image(m.depth);
  return m;
}

// Share of the occupied pixels of `a` with an occupied pixel of `b` within one cell whose depth is within
// `levels` grey levels.
double matched_share(const cv::Mat& a, const cv::Mat& b, int levels) {
  int occupied = 0, matched = 0;
  for (int r = 1; r + 1 < a.rows; ++r) {
    for (int c = 1; c + 1 < a.cols; ++c) {
      const int va = a.at<std::uint8_t>(r, c);
      if (va == 0) continue;
      ++occupied;
      bool hit = false;
      for (int dr = -1; dr <= 1 && !hit; ++dr)
        for (int dc = -1; dc <= 1 && !hit; ++dc) {
          const int vb = b.at<std::uint8_t>(r + dr, c + dc);
          hit = vb != 0 && std::abs(vb - va) <= levels;
        }
      matched += hit ? 1 : 0;
    }
  }
  return occupied > 0 ? static_cast<double>(matched) / occupied : 0.0;
}

algo::FeatureVector features_of(const cv::Mat& depth) {
  const algo::GridSpec spec = shipped_grid();
  algo::FeatureExtractor extractor(spec.ny, spec.nx, algo::feature_params_for(spec));
  algo::FeatureVector f{};
  REQUIRE(extractor.compute(depth, f) == algo::FeatureStatus::kOk);
  return f;
}

const std::vector<Pose>& moved_poses() {
  static const std::vector<Pose> poses = {
      {0.045, -0.030, 4.0 * kDeg, 1.5 * kDeg}, {-0.050, 0.040, -5.0 * kDeg, -2.0 * kDeg}, {0.0, 0.0, 2.0 * kDeg, 0.0}};
  return poses;
}

}  // namespace

TEST_CASE(
    "Given a part shifted, turned and swung by a known transform, when it is mapped into its own frame, then "
    "the turn and swing are recovered and its depth image matches the unmoved part's within a cell") {
  const std::vector<PartPoint> part = synthetic_part();
  const Mapped reference = map_and_image(place(part, {}));
  CHECK(std::abs(reference.pose.turn_rad) < 0.1 * kDeg);
  for (const Pose& pose : moved_poses()) {
    const Mapped moved = map_and_image(place(part, pose));
    INFO("pose dx " << pose.dx_m << " dy " << pose.dy_m << " theta " << pose.theta_rad / kDeg << " swing "
                    << pose.swing_rad / kDeg);
    // The turn is the known theta (the outline's edges, mod 90 deg); the centroid moved by the known shift
    // (the part turns about its own centre here, which is its silhouette's centroid up to the holes' asymmetry).
    CHECK(std::abs(moved.pose.turn_rad - pose.theta_rad) < 0.15 * kDeg);
    // The sheet plane's slope along x is the swing's: z = -tan(swing) x' to first order.
    CHECK(std::abs(moved.pose.slope_x + std::tan(pose.swing_rad)) < 0.002);
    // Every occupied pixel has a counterpart within one cell and two grey levels (1 level = 1.57 mm; the grid's
    // depth step of 2.2 mm spans 1.4 levels) in both directions.
    CHECK(matched_share(moved.depth, reference.depth, 2) > 0.995);
    CHECK(matched_share(reference.depth, moved.depth, 2) > 0.995);
  }
}

TEST_CASE("Given a swung part, when it is levelled, then its sheet lies at one depth and its rib keeps its height") {
  const std::vector<PartPoint> part = synthetic_part();
  const Mapped moved = map_and_image(place(part, {0.02, 0.01, 3.0 * kDeg, 2.0 * kDeg}));
  const double sheet_z = algo::canonical_sheet_depth_m(shipped_grid(), {});
  double worst_sheet = 0.0, worst_rib = 0.0;
  for (std::size_t i = 0; i < part.size(); ++i) {
    const double dz = moved.points[i].z - sheet_z;
    if (part[i].sheet)
      worst_sheet = std::max(worst_sheet, std::abs(dz));
    else
      worst_rib = std::max(worst_rib, std::abs(dz - kRibHeight * std::cos(2.0 * kDeg)));
  }
  CHECK(worst_sheet < 2e-4);  // float coordinates and the 2 deg swing's cosine: well below a 2.2 mm cell
  CHECK(worst_rib < 3e-4);
}

TEST_CASE(
    "Given a moved part, when its features are computed in its own frame, then they match the unmoved part's "
    "within the tolerance of one cell of outline") {
  const std::vector<PartPoint> part = synthetic_part();
  const algo::FeatureVector ref = features_of(map_and_image(place(part, {})).depth);
  for (const Pose& pose : moved_poses()) {
    const algo::FeatureVector f = features_of(map_and_image(place(part, pose)).depth);
    INFO("theta " << pose.theta_rad / kDeg << " swing " << pose.swing_rad / kDeg);
    // Width and height are means of per-line extents: each end may move by one cell.
    CHECK(std::abs(f[algo::kWidthIndex] - ref[algo::kWidthIndex]) <= 2 * 0.0022);
    CHECK(std::abs(f[algo::kHeightIndex] - ref[algo::kHeightIndex]) <= 2 * 0.0022);
    // Area: the outline and hole edges (~1300 cells of ~48000) may each gain or lose a cell: 3 %.
    CHECK(std::abs(f[algo::kAreaIndex] - ref[algo::kAreaIndex]) <= 0.03 * ref[algo::kAreaIndex]);
    // Levelled depth: the sheet falls into the same one or two depth levels, so the histogram barely changes.
    CHECK(std::abs(f[algo::kHistEntropyIndex] - ref[algo::kHistEntropyIndex]) < 0.15);
    CHECK(std::abs(f[algo::kHistEnergyIndex] - ref[algo::kHistEnergyIndex]) < 0.1);
    CHECK(std::abs(f[algo::kEccentricityIndex] - ref[algo::kEccentricityIndex]) < 0.01);
    CHECK(std::abs(f[algo::kHuIndex] - ref[algo::kHuIndex]) < 0.02 * std::abs(ref[algo::kHuIndex]));
  }
}

TEST_CASE("Given the scratch sized at start-up, when a part is mapped, then nothing is allocated") {
  const std::vector<algo::ScanPoint> in = place(synthetic_part(), {0.01, 0.0, 1.0 * kDeg, 0.5 * kDeg});
  const algo::GridSpec spec = shipped_grid();
  algo::CanonicalScratch scratch(spec);
  std::vector<algo::ScanPoint> out(in.size());
  algo::CanonicalPose pose;
  long allocations = 0;
  algo::CanonicalStatus status{};
  {
    const test::AllocationWindow window;
    status = algo::canonicalise(in, spec, {}, scratch, out, pose);
    allocations = window.count();
  }
  CHECK(status == algo::CanonicalStatus::kOk);
  CHECK(allocations == 0);
}

TEST_CASE("Given a turn beyond the limit, when a part is mapped, then only the limit is undone (no 90 deg flip)") {
  const std::vector<PartPoint> part = synthetic_part();
  const Mapped moved = map_and_image(place(part, {0.0, 0.0, 30.0 * kDeg, 0.0}));
  CHECK(std::abs(moved.pose.measured_turn_rad - 30.0 * kDeg) < 0.3 * kDeg);
  CHECK(moved.pose.turn_rad == Approx(algo::CanonicalParams{}.max_turn_rad));
}

TEST_CASE(
    "Given a scan, when synthetic variants are made, then they are reproducible, differ from each other and "
    "stay within the pose range") {
  const std::vector<algo::ScanPoint> in = place(synthetic_part(), {});
  std::vector<algo::ScanPoint> a, b, c;
  algo::augment_scan(in, {}, 7, a);
  algo::augment_scan(in, {}, 7, b);
  algo::augment_scan(in, {}, 8, c);
  REQUIRE(!a.empty());
  CHECK(a.size() == b.size());
  CHECK(std::equal(a.begin(), a.end(), b.begin(),
                   [](const auto& p, const auto& q) { return p.x == q.x && p.y == q.y && p.z == q.z; }));
  CHECK(a.size() != c.size());
  CHECK(a.size() >= static_cast<std::size_t>(0.5 * static_cast<double>(in.size())));
  double mx = 0.0, my = 0.0;
  for (const auto& p : a) {
    mx += p.x;
    my += p.y;
  }
  mx /= static_cast<double>(a.size());
  my /= static_cast<double>(a.size());
  // The centroid moves by at most the shift (50 mm per axis) plus what thinning and dropouts take away.
  CHECK(std::abs(mx - kCentreX) < 0.06);
  CHECK(std::abs(my - kCentreY) < 0.06);
}

namespace {

// 3 classes x 6 taught scans x (1 + 4 variants), group = taught scan.
algo::Dataset grouped_dataset() {
  algo::Dataset d;
  d.classes = {{"a", 1}, {"b", 2}, {"c", 3}};
  int group = 0;
  for (int c = 0; c < 3; ++c) {
    for (int s = 0; s < 6; ++s, ++group) {
      for (int v = 0; v <= 4; ++v) {
        algo::FeatureVector f{};
        f[0] = static_cast<float>(c);
        f[1] = static_cast<float>(group);
        f[2] = static_cast<float>(v);
        d.push(f, c, group, v);
      }
    }
  }
  return d;
}

}  // namespace

TEST_CASE(
    "Given taught scans with synthetic variants, when the folds are assigned, then every group stays in one "
    "fold and every class is in every fold") {
  const algo::Dataset d = grouped_dataset();
  auto folds = algo::stratified_folds(d, 5, 11);
  REQUIRE(folds);
  std::map<int, std::set<int>> folds_of_group;
  std::map<int, std::set<int>> classes_in_fold;
  for (std::size_t i = 0; i < d.size(); ++i) {
    folds_of_group[d.group_of(i)].insert((*folds)[i]);
    classes_in_fold[(*folds)[i]].insert(d.labels[i]);
  }
  for (const auto& [group, f] : folds_of_group) CHECK(f.size() == 1);
  REQUIRE(classes_in_fold.size() == 5);
  for (const auto& [fold, classes] : classes_in_fold) CHECK(classes.size() == 3);
}

TEST_CASE(
    "Given taught scans with synthetic variants, when they are split, then a training scan takes its variants "
    "along and a held-back scan goes alone") {
  const algo::Dataset d = grouped_dataset();
  auto split = algo::split_per_class(d, 4, 3);
  REQUIRE(split);
  CHECK(split->test.size() == 3 * 2);
  std::set<int> train_groups, test_groups;
  for (std::size_t i = 0; i < split->test.size(); ++i) {
    CHECK(split->test.variant_of(i) == 0);
    CHECK(split->test.features[i][2] == 0.0F);
    test_groups.insert(split->test.group_of(i));
  }
  for (std::size_t i = 0; i < split->train.size(); ++i) {
    train_groups.insert(split->train.group_of(i));
    CHECK(static_cast<int>(split->train.features[i][1]) == split->train.group_of(i));
  }
  CHECK(split->train.size() == 3 * 4 * 5);
  for (int g : test_groups) CHECK(train_groups.count(g) == 0);
}

TEST_CASE("Given a group that mixes two classes, when the dataset is validated, then it is refused") {
  algo::Dataset d = grouped_dataset();
  d.labels[1] = 1;  // variant 1 of group 0 (class 0) claims class 1
  CHECK_FALSE(algo::validate_dataset(d));
}
