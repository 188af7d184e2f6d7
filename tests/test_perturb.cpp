// Seeded scan perturbations against independent truth: a synthetic raw scan (a plate with a hole in front of a
// carrier plane, sampled like the sensor), statistics, brute-force distances and analytic geometry.
#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <cmath>
#include <map>
#include <numbers>
#include <unordered_map>

#include "algo/perturb.hpp"

using namespace cellsight;
using algo::PerturbKind;
using algo::ScanPoint;

namespace {

// The carrier: the plane z = 5 mm tilted a little about x (so "in front" is not just "z > 0").
algo::Plane carrier_plane() {
  const Eigen::Vector3d n = Eigen::Vector3d(0.0, -0.02, 1.0).normalized();
  return {n, n.dot(Eigen::Vector3d(0.0, 0.0, 0.005))};
}

constexpr double kProfile_m = 0.0022;   // sensor: one profile per 2.2 mm of travel
constexpr double kPlateDepth_m = 0.05;  // the plate hangs 50 mm in front of the carrier
constexpr double kBand_m = 0.006;       // carrier band of the spec's default

struct Synthetic {
  double x_lo_m = -0.35, x_hi_m = 0.35;  // scanned: the carrier is wider than the part
  double y_lo_m = 0.0, y_hi_m = 1.0;
  double plate_x_m = 0.2, plate_y_lo_m = 0.15, plate_y_hi_m = 0.85;  // plate |x| <= 0.2, y in [0.15, 0.85]
  double hole_r_m = 0.08;                                            // a round hole at (0, 0.5)
  double dy_m = 0.002;                                               // point spacing along a profile
  bool with_part = true;
};

bool on_plate(const Synthetic& s, double x, double y) {
  return s.with_part && std::abs(x) <= s.plate_x_m && y >= s.plate_y_lo_m && y <= s.plate_y_hi_m &&
         std::hypot(x, y - 0.5) > s.hole_r_m;
}

// One point per (profile, row): on the plate where it is, else on the carrier (hidden behind the plate).
std::vector<ScanPoint> make_scan(const Synthetic& s = {}) {
  const algo::Plane plane = carrier_plane();
  std::vector<ScanPoint> points;
  std::uint16_t frame = 0;
  for (double x = s.x_lo_m; x <= s.x_hi_m + 1e-9; x += kProfile_m, ++frame) {
    std::uint16_t row = 0;
    for (double y = s.y_lo_m; y <= s.y_hi_m + 1e-9; y += s.dy_m, ++row) {
      const double depth = on_plate(s, x, y) ? kPlateDepth_m : 0.0;
      const double z = (plane.offset_m + depth - plane.normal.x() * x - plane.normal.y() * y) / plane.normal.z();
      points.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), frame, row});
    }
  }
  return points;
}

double depth_of(const ScanPoint& p) {
  return carrier_plane().signed_distance(Eigen::Vector3d(p.x, p.y, p.z));
}
bool is_part(const ScanPoint& p) {
  return depth_of(p) >= kBand_m;
}
bool same(const ScanPoint& a, const ScanPoint& b) {
  return a.x == b.x && a.y == b.y && a.z == b.z;
}

// The kinds that only remove points keep the others in order: which of `before` are still there.
std::vector<char> kept_flags(const std::vector<ScanPoint>& before, const std::vector<ScanPoint>& after) {
  std::vector<char> kept(before.size(), 0);
  std::size_t j = 0;
  for (std::size_t i = 0; i < before.size() && j < after.size(); ++i) {
    if (same(before[i], after[j])) {
      kept[i] = 1;
      ++j;
    }
  }
  REQUIRE(j == after.size());  // nothing added or moved
  return kept;
}

algo::PerturbSpec spec_of(std::string_view text) {
  auto spec = algo::parse_perturb(text);
  REQUIRE(spec.ok());
  return *spec;
}

}  // namespace

TEST_CASE("Given the same seed, a perturbation gives the same points and given another seed other points") {
  const algo::PerturbSpec spec = spec_of("swing,stray_edge,stray_points,glare,dropout,noise");
  auto a = make_scan(), b = make_scan(), c = make_scan();
  (void)algo::perturb_scan(a, spec, carrier_plane(), 42);
  (void)algo::perturb_scan(b, spec, carrier_plane(), 42);
  (void)algo::perturb_scan(c, spec, carrier_plane(), 43);
  REQUIRE(a.size() == b.size());
  CHECK(std::equal(a.begin(), a.end(), b.begin(), same));
  CHECK((a.size() != c.size() || !std::equal(a.begin(), a.end(), c.begin(), same)));
}

TEST_CASE("Given a plane, when noise is added, then the depth error has the requested sigma and y a little") {
  Synthetic s;
  s.with_part = false;
  const auto before = make_scan(s);
  for (const double strength : {1.0, 2.0}) {
    auto after = before;
    const auto r = algo::perturb_scan(after, spec_of("noise:" + std::to_string(strength)), carrier_plane(), 7);
    REQUIRE(after.size() == before.size());
    double sum2_z = 0, sum2_y = 0, sum_z = 0;
    for (std::size_t i = 0; i < before.size(); ++i) {
      CHECK(after[i].x == before[i].x);
      sum_z += after[i].z - before[i].z;
      sum2_z += std::pow(after[i].z - before[i].z, 2);
      sum2_y += std::pow(after[i].y - before[i].y, 2);
    }
    const double n = static_cast<double>(before.size());
    const double sigma_z = std::sqrt(sum2_z / n), sigma_y = std::sqrt(sum2_y / n);
    CHECK(r.noise_sigma_z_m == Approx(0.35e-3 * strength));
    CHECK(sigma_z == Approx(0.35e-3 * strength).epsilon(0.10));
    CHECK(std::abs(sum_z / n) < 0.1 * sigma_z);
    CHECK(sigma_y > 0.0);
    CHECK(sigma_y < 0.5 * sigma_z);
  }
}

TEST_CASE("Given a scan, when dropout runs, then 3 +- 0.5 % of the points are lost, both single and in runs") {
  const auto before = make_scan();
  for (const std::uint64_t seed : {1U, 2U, 3U}) {
    auto after = before;
    (void)algo::perturb_scan(after, spec_of("dropout"), carrier_plane(), seed);
    const double lost = 1.0 - static_cast<double>(after.size()) / static_cast<double>(before.size());
    CHECK(lost == Approx(0.03).margin(0.005));
    // The synthetic points are stored profile by profile, y rising: a neighbour in the vector is one along y.
    const auto kept = kept_flags(before, after);
    int single = 0, in_run = 0;
    for (std::size_t i = 1; i + 1 < before.size(); ++i) {
      if (kept[i] != 0) continue;
      if (kept[i - 1] != 0 && kept[i + 1] != 0)
        ++single;
      else
        ++in_run;
    }
    CHECK(single > 0);
    CHECK(in_run > 0);
  }
}

TEST_CASE(
    "Given a part, when glare hits it, then >= 90 % of its points in the band are lost, none outside, and "
    "the carrier is untouched") {
  const auto before = make_scan();
  std::map<int, int> orientations;  // 0 vertical, 1 horizontal, 2 oblique
  for (std::uint64_t seed = 1; seed <= 12; ++seed) {
    auto after = before;
    const auto r = algo::perturb_scan(after, spec_of("glare"), carrier_plane(), seed);
    REQUIRE(r.applied[static_cast<std::size_t>(PerturbKind::kGlare)]);
    CHECK(r.glare_width_m >= 0.015);
    CHECK(r.glare_width_m <= 0.035);
    const double nx = std::abs(r.glare_normal_xy.x());
    ++orientations[nx > 0.999 ? 0 : nx < 0.001 ? 1 : 2];
    const auto kept = kept_flags(before, after);
    std::size_t inside = 0, inside_lost = 0, outside_lost = 0, carrier_lost = 0;
    for (std::size_t i = 0; i < before.size(); ++i) {
      const ScanPoint& p = before[i];
      if (!is_part(p)) {
        carrier_lost += kept[i] == 0 ? 1 : 0;
        continue;
      }
      const double across = r.glare_normal_xy.dot(Eigen::Vector2d(p.x, p.y) - r.glare_centre_xy);
      if (std::abs(across) <= 0.5 * r.glare_width_m) {
        ++inside;
        inside_lost += kept[i] == 0 ? 1 : 0;
      } else {
        outside_lost += kept[i] == 0 ? 1 : 0;
      }
    }
    REQUIRE(inside > 100);
    CHECK(static_cast<double>(inside_lost) >= 0.9 * static_cast<double>(inside));
    CHECK(outside_lost == 0);
    CHECK(carrier_lost == 0);
  }
  CHECK(orientations.size() == 3);
}

TEST_CASE(
    "Given a part, when a stray edge enters, then its points are in front of the carrier, >= 15 mm from "
    "every part point, sampled like the scan and touching an end of the scanned x range") {
  const auto before = make_scan();
  // Part points hashed on a 15 mm grid: the 3 x 3 neighbouring cells hold every point nearer than 15 mm.
  constexpr double kCell_m = 0.015;
  const auto key = [](double x, double y) {
    return (static_cast<std::int64_t>(std::floor(x / kCell_m)) << 32) ^
           static_cast<std::int64_t>(static_cast<std::uint32_t>(std::floor(y / kCell_m)));
  };
  std::unordered_map<std::int64_t, std::vector<Eigen::Vector2d>> part;
  for (const ScanPoint& p : before) {
    if (is_part(p)) part[key(p.x, p.y)].emplace_back(p.x, p.y);
  }
  const auto [lo, hi] = std::minmax_element(before.begin(), before.end(),
                                            [](const ScanPoint& a, const ScanPoint& b) { return a.x < b.x; });
  std::map<bool, int> sides;
  for (std::uint64_t seed = 1; seed <= 8; ++seed) {
    auto after = before;
    const auto r = algo::perturb_scan(after, spec_of("stray_edge"), carrier_plane(), seed);
    REQUIRE(r.applied[static_cast<std::size_t>(PerturbKind::kStrayEdge)]);
    ++sides[r.stray_edge_from_left];
    const double height = r.stray_edge.y_max_m - r.stray_edge.y_min_m;
    CHECK(height >= 0.3);
    CHECK(height <= 0.7);
    REQUIRE(r.stray_edge.points > 0);
    // The strip is appended after the points that are kept.
    const std::vector<ScanPoint> strip(after.end() - static_cast<std::ptrdiff_t>(r.stray_edge.points), after.end());
    double x_min = 1e9, x_max = -1e9, nearest = 1e9;
    std::map<float, std::vector<float>> rows;  // y of the strip's points per profile x
    for (const ScanPoint& p : strip) {
      CHECK(depth_of(p) == Approx(kPlateDepth_m).margin(1e-4));
      x_min = std::min<double>(x_min, p.x);
      x_max = std::max<double>(x_max, p.x);
      rows[p.x].push_back(p.y);
      const auto cx = static_cast<std::int64_t>(std::floor(p.x / kCell_m));
      const auto cy = static_cast<std::int64_t>(std::floor(p.y / kCell_m));
      for (std::int64_t i = -1; i <= 1; ++i) {
        for (std::int64_t j = -1; j <= 1; ++j) {
          const auto it = part.find(key((cx + i + 0.5) * kCell_m, (cy + j + 0.5) * kCell_m));
          if (it == part.end()) continue;
          for (const Eigen::Vector2d& q : it->second)
            nearest = std::min(nearest, (q - Eigen::Vector2d(p.x, p.y)).norm());
        }
      }
    }
    CHECK(nearest >= 0.015 - 1e-6);
    const double end_gap = r.stray_edge_from_left ? x_min - lo->x : hi->x - x_max;
    CHECK(std::abs(end_gap) < 1e-4);
    CHECK(x_max - x_min <= 0.080 + 1e-6);
    // On the scan's own profiles, with its spacing along y.
    for (const auto& [x, ys] : rows) {
      const double k = (x - (-0.35)) / kProfile_m;
      CHECK(std::abs(k - std::round(k)) < 1e-3);
      REQUIRE(ys.size() > 1);
      CHECK(ys[1] - ys[0] == Approx(0.002).margin(1e-5));
    }
  }
  CHECK(sides.size() == 2);
}

TEST_CASE(
    "Given a part, when chain and stray points are added, then a narrow strip rises from the part's top "
    "edge and 0.2 % outliers lie in front of the carrier") {
  const auto before = make_scan();
  auto after = before;
  const auto r = algo::perturb_scan(after, spec_of("stray_points"), carrier_plane(), 5);
  REQUIRE(r.applied[static_cast<std::size_t>(PerturbKind::kStrayPoints)]);
  const double width = r.chain.x_max_m - r.chain.x_min_m;
  CHECK(width >= 0.006 - 1e-6);
  CHECK(width <= 0.010 + 1e-6);
  CHECK(r.chain.y_min_m == Approx(0.85).margin(0.0021));  // the plate's top edge
  CHECK(r.chain.y_max_m == Approx(1.0).margin(0.0021));   // up to the top of the scan
  CHECK(r.chain.depth_m == Approx(kPlateDepth_m).margin(1e-4));
  CHECK(r.outliers == static_cast<std::size_t>(std::lround(0.002 * static_cast<double>(before.size()))));
  const std::size_t added = r.chain.points + r.outliers;
  for (auto it = after.end() - static_cast<std::ptrdiff_t>(r.outliers); it != after.end(); ++it) {
    CHECK(depth_of(*it) >= kBand_m);
    CHECK(depth_of(*it) <= kPlateDepth_m + 1e-4);
  }
  // The chain hides the carrier behind it and nothing else.
  const std::vector<ScanPoint> kept_part(after.begin(), after.end() - static_cast<std::ptrdiff_t>(added));
  const auto kept = kept_flags(before, kept_part);
  std::size_t hidden = 0;
  for (std::size_t i = 0; i < before.size(); ++i) {
    if (kept[i] != 0) continue;
    ++hidden;
    CHECK_FALSE(is_part(before[i]));
    CHECK(before[i].x >= r.chain.x_min_m);
    CHECK(before[i].x <= r.chain.x_max_m);
    CHECK(before[i].y >= r.chain.y_min_m);
  }
  CHECK(hidden > 0);
}

TEST_CASE("Given a scan, when thinned, then the points of every other image row remain (half the sensor's rows)") {
  // Every third profile lost its first point (a dropout above): the rows below it are still the sensor's rows.
  auto before = make_scan();
  {
    std::vector<char> drop(before.size(), 0);
    const auto profiles = algo::profiles_by_x(before, 0.001);
    for (std::size_t k = 0; k < profiles.size(); k += 3) drop[profiles[k].front()] = 1;
    std::size_t i = 0;
    std::erase_if(before, [&](const ScanPoint&) { return drop[i++] != 0; });
  }
  auto after = before;
  const auto r = algo::perturb_scan(after, spec_of("thin"), carrier_plane(), 1);
  std::size_t even = 0;
  for (const ScanPoint& p : before) even += p.row % 2 == 0 ? 1 : 0;
  REQUIRE(even > 0);
  REQUIRE(even < before.size());
  CHECK(after.size() == even);
  CHECK(r.thinned == before.size() - even);
  for (const ScanPoint& p : after) CHECK(p.row % 2 == 0);
  // The same rows in every profile: a row that survives in one profile survives in all that reach it.
  const auto p_after = algo::profiles_by_x(after, 0.001);
  REQUIRE(p_after.size() == 319);
}

TEST_CASE("Given a scan with no image rows recorded, when thinned, then every profile keeps half of its points") {
  auto before = make_scan();
  for (ScanPoint& p : before) p.row = 0;  // a PLY from elsewhere
  auto after = before;
  (void)algo::perturb_scan(after, spec_of("thin"), carrier_plane(), 1);
  const auto p_before = algo::profiles_by_x(before, 0.001), p_after = algo::profiles_by_x(after, 0.001);
  REQUIRE(p_before.size() == 319);
  REQUIRE(p_after.size() == p_before.size());
  for (std::size_t k = 0; k < p_before.size(); ++k) CHECK(p_after[k].size() == (p_before[k].size() + 1) / 2);
}

TEST_CASE("Given a flat part, when swung, then its depth slope along x is -tan(drawn angle) and the carrier stays") {
  const auto before = make_scan();
  std::size_t carrier_before = 0;
  for (const ScanPoint& p : before) carrier_before += is_part(p) ? 0 : 1;
  for (std::uint64_t seed = 1; seed <= 5; ++seed) {
    auto after = before;
    const auto r = algo::perturb_scan(after, spec_of("swing"), carrier_plane(), seed);
    CHECK(std::abs(r.swing_rad) <= 2.0 * std::numbers::pi / 180.0);
    CHECK(r.swing_rad != 0.0);
    // Least-squares slope dz/dx along rows of the part (one y each: the carrier's tilt about x gives the plate a
    // depth that changes with y only), against the points of the carrier, which must not move.
    std::map<std::uint16_t, std::array<double, 5>> rows;  // n, sum x, sum z, sum xx, sum xz
    std::size_t unmoved = 0;
    for (std::size_t i = 0; i < before.size(); ++i) {
      if (!is_part(before[i])) {
        unmoved += same(before[i], after[i]) ? 1 : 0;
        continue;
      }
      CHECK(after[i].y == before[i].y);
      auto& s = rows[before[i].row];
      const double x = after[i].x, z = after[i].z;
      s[0] += 1;
      s[1] += x;
      s[2] += z;
      s[3] += x * x;
      s[4] += x * z;
    }
    for (const std::uint16_t row : {100, 200, 300}) {
      const auto& s = rows.at(row);
      const double slope = (s[0] * s[4] - s[1] * s[2]) / (s[0] * s[3] - s[1] * s[1]);
      CHECK(slope == Approx(-std::tan(r.swing_rad)).margin(2e-5));
    }
    CHECK(unmoved == carrier_before);
  }
}

TEST_CASE("Given a share, a kind hits about that fraction of the scans, and mixed puts glare and stray edge on 30 %") {
  Synthetic coarse;
  coarse.dy_m = 0.02;
  const auto before = make_scan(coarse);
  int glare = 0, stray = 0, noise = 0;
  constexpr int kScans = 300;
  for (int seed = 1; seed <= kScans; ++seed) {
    auto after = before;
    const auto r = algo::perturb_scan(after, spec_of("mixed"), carrier_plane(), static_cast<std::uint64_t>(seed));
    glare += r.applied[static_cast<std::size_t>(PerturbKind::kGlare)] ? 1 : 0;
    stray += r.applied[static_cast<std::size_t>(PerturbKind::kStrayEdge)] ? 1 : 0;
    noise += r.applied[static_cast<std::size_t>(PerturbKind::kNoise)] ? 1 : 0;
  }
  CHECK(noise == kScans);
  CHECK(glare == Approx(0.3 * kScans).margin(0.07 * kScans));
  CHECK(stray == Approx(0.3 * kScans).margin(0.07 * kScans));
}

TEST_CASE("Given perturbation texts, the parser takes kinds, strengths, shares and mixed, and names what is wrong") {
  const auto spec = spec_of("noise:2,glare@0.25");
  CHECK(spec[PerturbKind::kNoise].on);
  CHECK(spec[PerturbKind::kNoise].strength == 2.0);
  CHECK(spec[PerturbKind::kGlare].share == 0.25);
  CHECK_FALSE(spec[PerturbKind::kDropout].on);
  const auto mixed = spec_of("mixed");
  CHECK(mixed[PerturbKind::kDropout].share == 1.0);
  CHECK(mixed[PerturbKind::kStrayEdge].share == 0.3);
  CHECK(spec_of("none").empty());

  const auto bad = algo::parse_perturb("noise,sparkle:2");
  REQUIRE_FALSE(bad.ok());
  CHECK_THAT(bad.error().message,
             Catch::Contains("'sparkle'") && Catch::Contains("stray_edge") && Catch::Contains("mixed"));
  CHECK_FALSE(algo::parse_perturb("noise:0").ok());
  CHECK_FALSE(algo::parse_perturb("noise:x").ok());
  CHECK_FALSE(algo::parse_perturb("glare@1.5").ok());
  CHECK_FALSE(algo::parse_perturb("noise,mixed").ok());  // noise twice
  CHECK_FALSE(algo::parse_perturb("noise,,thin").ok());
}
