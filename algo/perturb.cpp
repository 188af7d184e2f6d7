// Seeded perturbations of raw scans: noise, dropout, glare, stray objects, lower resolution, swing.
#include "algo/perturb.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <numbers>

#include "algo/random.hpp"

namespace cellsight::algo {
namespace {

constexpr std::array<std::string_view, kPerturbKinds> kNames = {"swing", "stray_edge", "stray_points", "glare",
                                                                "thin",  "dropout",    "noise"};
constexpr std::string_view kValidKinds = "noise, dropout, glare, stray_edge, stray_points, thin, swing, mixed, none";
constexpr double kMaxStrength = 10.0;

// Defaults at strength 1 (the figures of issue 10).
constexpr double kNoiseSigmaZ_m = 0.35e-3;
constexpr double kNoiseYOverZ = 0.3;  // the stripe's sub-pixel error is mostly along the viewing ray
constexpr double kDropoutFraction = 0.03;
constexpr double kDropoutRunShare = 0.5;  // of the lost points, the share lost in runs along a profile
constexpr int kDropoutRunMin = 2, kDropoutRunMax = 6;
constexpr double kGlareWidthMin_m = 0.015, kGlareWidthMax_m = 0.035;
constexpr double kGlareLossMin = 0.90, kGlareLossMax = 1.0;
constexpr double kStrayWidthMin_m = 0.020, kStrayWidthMax_m = 0.080;
constexpr double kStrayHeightMin_m = 0.300, kStrayHeightMax_m = 0.700;
constexpr double kStrayClearance_m = 0.015;  // from the part's nearest point, in x-y
constexpr double kChainWidthMin_m = 0.006, kChainWidthMax_m = 0.010;
constexpr double kHookReach_m = 0.05;  // the chain rises this close (x) to the part's centroid
constexpr double kOutlierFraction = 0.002;
constexpr double kSwingMax_rad = 2.0 * std::numbers::pi / 180.0;
constexpr double kMixedShare = 0.3;  // mixed: glare and stray_edge each on this share of the scans

// Sampling of the sensor when the scan is too sparse to measure it.
constexpr double kProfileSpacing_m = 0.0022;
constexpr double kProfileGap_m = 0.4 * kProfileSpacing_m;  // sorted x jumps more than this between profiles
constexpr double kPointSpacingY_m = 0.001;

// Salts of the random streams: one per kind, one for the share draw.
constexpr std::uint64_t kShareSalt = 0x5A4E;

Eigen::Vector3d as_vector(const ScanPoint& p) {
  return {p.x, p.y, p.z};
}

// The point at (x, y) whose signed distance from the plane is depth_m (the carrier faces the camera: normal ~ +z).
ScanPoint point_at_depth(const Plane& plane, double x, double y, double depth_m) {
  const Eigen::Vector3d& n = plane.normal;
  const double z = (plane.offset_m + depth_m - n.x() * x - n.y() * y) / n.z();
  return {static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, 0};
}

double median(std::vector<double> v, double fallback) {
  if (v.empty()) return fallback;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// What the kinds need to know about one scan, measured before any of them runs.
struct Layout {
  std::vector<std::vector<std::size_t>> profiles;  // indices by x, each sorted by y
  std::vector<double> profile_x;                   // mean x of each profile
  double profile_spacing_m = kProfileSpacing_m;
  double point_spacing_y_m = kPointSpacingY_m;  // along y between neighbouring part points of a profile
  Eigen::Vector3d lo = Eigen::Vector3d::Zero(), hi = Eigen::Vector3d::Zero();  // the scanned volume
  std::vector<char> is_part;
  std::size_t part_points = 0;
  double part_depth_m = 0.0;  // median signed distance of the part's points
  double part_max_depth_m = 0.0;
};

Layout measure(const std::vector<ScanPoint>& points, const Plane& support, double carrier_band_m) {
  Layout l;
  l.profiles = profiles_by_x(points, kProfileGap_m);
  std::vector<double> gaps, dy, depths;
  l.is_part.assign(points.size(), 0);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const double d = support.signed_distance(as_vector(points[i]));
    if (d >= carrier_band_m) {
      l.is_part[i] = 1;
      depths.push_back(d);
      l.part_max_depth_m = std::max(l.part_max_depth_m, d);
    }
  }
  l.part_points = depths.size();
  l.part_depth_m = median(depths, 0.0);
  for (const auto& profile : l.profiles) {
    double sum = 0;
    for (std::size_t i : profile) sum += points[i].x;
    l.profile_x.push_back(sum / static_cast<double>(profile.size()));
    if (l.profile_x.size() > 1) gaps.push_back(l.profile_x.back() - l.profile_x[l.profile_x.size() - 2]);
    for (std::size_t k = 1; k < profile.size(); ++k) {
      if (l.is_part[profile[k]] != 0 && l.is_part[profile[k - 1]] != 0) {
        dy.push_back(static_cast<double>(points[profile[k]].y) - points[profile[k - 1]].y);
      }
    }
  }
  l.profile_spacing_m = median(gaps, kProfileSpacing_m);
  l.point_spacing_y_m = std::max(1e-5, median(dy, kPointSpacingY_m));
  if (!points.empty()) {
    l.lo = l.hi = as_vector(points.front());
    for (const ScanPoint& p : points) {
      l.lo = l.lo.cwiseMin(as_vector(p));
      l.hi = l.hi.cwiseMax(as_vector(p));
    }
  }
  return l;
}

// Keeps the points whose flag is 0, in order.
void erase_flagged(std::vector<ScanPoint>& points, const std::vector<char>& lost) {
  std::size_t out = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (lost[i] == 0) points[out++] = points[i];
  }
  points.resize(out);
}

void apply_swing(std::vector<ScanPoint>& points, const Layout& l, double strength, Rng& rng, PerturbReport& r) {
  Eigen::Vector2d c = Eigen::Vector2d::Zero();
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (l.is_part[i] != 0) c += Eigen::Vector2d(points[i].x, points[i].z);
  }
  c /= static_cast<double>(l.part_points);
  const double a = rng.uniform(-1.0, 1.0) * kSwingMax_rad * strength;
  const double ca = std::cos(a), sa = std::sin(a);
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (l.is_part[i] == 0) continue;
    const double dx = points[i].x - c.x(), dz = points[i].z - c.y();
    points[i].x = static_cast<float>(c.x() + ca * dx + sa * dz);
    points[i].z = static_cast<float>(c.y() - sa * dx + ca * dz);
  }
  r.swing_rad = a;
  r.swing_axis_xz = c;
}

// Adds a flat strip on the scan's profiles inside [x0, x1] and rows from y0 to y1 at the given depth (random phase
// along y), and hides the carrier points behind it. Returns what was added.
PerturbReport::Strip add_strip(std::vector<ScanPoint>& points, const Layout& l, const Plane& support, double x0,
                               double x1, double y0, double y1, double depth_m, double carrier_band_m, Rng& rng) {
  PerturbReport::Strip s{x0, x1, y0, y1, depth_m, 0};
  std::vector<char> hidden(points.size(), 0);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const ScanPoint& p = points[i];
    hidden[i] =
        p.x >= x0 && p.x <= x1 && p.y >= y0 && p.y <= y1 && support.signed_distance(as_vector(p)) < carrier_band_m ? 1
                                                                                                                   : 0;
  }
  erase_flagged(points, hidden);
  const double phase = rng.uniform() * l.point_spacing_y_m;
  for (const double x : l.profile_x) {
    if (x < x0 || x > x1) continue;
    // An integer count of points, each placed from the start: a float loop counter would gather rounding error.
    const double first_y = y0 + phase;
    const auto count = first_y <= y1 ? static_cast<long>(std::floor((y1 - first_y) / l.point_spacing_y_m)) + 1 : 0L;
    for (long k = 0; k < count; ++k) {
      points.push_back(point_at_depth(support, x, first_y + static_cast<double>(k) * l.point_spacing_y_m, depth_m));
      ++s.points;
    }
  }
  return s;
}

// The strip's x extent from the drawn end (the other end when the part leaves no room there), narrowed to keep
// kStrayClearance_m (x-y) from every part point.
bool apply_stray_edge(std::vector<ScanPoint>& points, const Layout& l, const Plane& support, double carrier_band_m,
                      double strength, Rng& rng, PerturbReport& r) {
  const bool drawn_left = rng.uniform() < 0.5;
  const double width = rng.uniform(kStrayWidthMin_m, kStrayWidthMax_m) * strength;
  const double height = std::min(rng.uniform(kStrayHeightMin_m, kStrayHeightMax_m), l.hi.y() - l.lo.y());
  const double y0 = l.lo.y() + rng.uniform() * (l.hi.y() - l.lo.y() - height);
  const double y1 = y0 + height;
  // How far in from an end the inner edge may reach: no nearer than the clearance to a part point beside the strip
  // (nearer in y than the clearance); points above or below it count by their x-y distance to the strip's corner.
  const auto reach_from = [&](bool from_left) {
    const double end = from_left ? l.lo.x() : l.hi.x();
    const double dir = from_left ? 1.0 : -1.0;
    double reach = width;
    for (std::size_t i = 0; i < points.size(); ++i) {
      if (l.is_part[i] == 0) continue;
      const double along = dir * (points[i].x - end);
      const double dy = std::max({y0 - points[i].y, static_cast<double>(points[i].y) - y1, 0.0});
      if (dy >= kStrayClearance_m) continue;
      reach = std::min(reach, along - std::sqrt(kStrayClearance_m * kStrayClearance_m - dy * dy));
    }
    return reach;
  };
  // At least two profiles wide, or the part leaves no room at that end.
  const double min_reach = 1.5 * l.profile_spacing_m;
  bool from_left = drawn_left;
  double reach = reach_from(from_left);
  if (reach < min_reach) {
    from_left = !from_left;
    reach = reach_from(from_left);
  }
  if (reach < min_reach) return false;
  const double x0 = from_left ? l.lo.x() : l.hi.x() - reach, x1 = from_left ? l.lo.x() + reach : l.hi.x();
  r.stray_edge = add_strip(points, l, support, x0, x1, y0, y1, l.part_depth_m, carrier_band_m, rng);
  r.stray_edge_from_left = from_left;
  return r.stray_edge.points > 0;
}

void apply_stray_points(std::vector<ScanPoint>& points, const Layout& l, const Plane& support, double carrier_band_m,
                        double strength, Rng& rng, PerturbReport& r) {
  const std::size_t n_in = points.size();
  // The hook is above the part's x centroid: the chain starts at the highest part point within kHookReach_m of it
  // in x (a part with a notch there: at the part point nearest to that line).
  double x_centre = 0.0;
  for (std::size_t i = 0; i < points.size(); ++i) x_centre += l.is_part[i] != 0 ? points[i].x : 0.0;
  x_centre /= static_cast<double>(l.part_points);
  std::size_t top = points.size();
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (l.is_part[i] == 0) continue;
    if (top == points.size()) {
      top = i;
      continue;
    }
    const double off = std::max(0.0, std::abs(points[i].x - x_centre) - kHookReach_m);
    const double off_top = std::max(0.0, std::abs(points[top].x - x_centre) - kHookReach_m);
    if (off < off_top || (off == off_top && points[i].y > points[top].y)) top = i;
  }
  const double width = rng.uniform(kChainWidthMin_m, kChainWidthMax_m) * strength;
  const double x_top = points[top].x, y_top = points[top].y;
  const double x0 = x_top + rng.uniform(-0.25, 0.25) * width - 0.5 * width;
  const double depth = support.signed_distance(as_vector(points[top]));
  // A chain narrower than the profile spacing is still seen by the profile nearest it.
  const double margin = width < l.profile_spacing_m ? 0.5 * l.profile_spacing_m : 0.0;
  r.chain = add_strip(points, l, support, std::min(x0, x_top - margin), std::max(x0 + width, x_top + margin), y_top,
                      l.hi.y(), depth, carrier_band_m, rng);
  // Specular outliers: anywhere in the scanned x-y range, in front of the carrier up to the part's greatest depth.
  const auto outliers = static_cast<std::size_t>(std::lround(kOutlierFraction * strength * static_cast<double>(n_in)));
  const double far = std::max(l.part_max_depth_m, 2.0 * carrier_band_m);
  for (std::size_t k = 0; k < outliers; ++k) {
    points.push_back(point_at_depth(support, rng.uniform(l.lo.x(), l.hi.x()), rng.uniform(l.lo.y(), l.hi.y()),
                                    rng.uniform(carrier_band_m, far)));
  }
  r.outliers = outliers;
}

void apply_glare(std::vector<ScanPoint>& points, const Layout& l, double strength, Rng& rng, PerturbReport& r) {
  std::size_t pick = static_cast<std::size_t>(rng.below(l.part_points));
  std::size_t centre = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (l.is_part[i] != 0 && pick-- == 0) {
      centre = i;
      break;
    }
  }
  // Vertical band (normal along x), horizontal (normal along y) or oblique (20–70° either way).
  const int orientation = static_cast<int>(rng.below(3));
  double angle = 0.0;  // of the band's normal from +x
  if (orientation == 1) angle = std::numbers::pi / 2;
  if (orientation == 2) angle = (rng.uniform() < 0.5 ? 1.0 : -1.0) * rng.uniform(20.0, 70.0) * std::numbers::pi / 180;
  r.glare_centre_xy = {points[centre].x, points[centre].y};
  r.glare_normal_xy = {std::cos(angle), std::sin(angle)};
  r.glare_width_m = rng.uniform(kGlareWidthMin_m, kGlareWidthMax_m) * strength;
  r.glare_loss = rng.uniform(kGlareLossMin, kGlareLossMax);
  std::vector<char> lost(points.size(), 0);
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (l.is_part[i] == 0) continue;
    const double across = r.glare_normal_xy.dot(Eigen::Vector2d(points[i].x, points[i].y) - r.glare_centre_xy);
    if (std::abs(across) <= 0.5 * r.glare_width_m && rng.uniform() < r.glare_loss) {
      lost[i] = 1;
      ++r.glare_removed;
    }
  }
  erase_flagged(points, lost);
}

void apply_thin(std::vector<ScanPoint>& points, double strength, PerturbReport& r) {
  // A sensor with 1 / stride of the rows along the laser line sees the points of every stride-th image row: the
  // same rows in every profile, whatever lies above them. (Keeping every stride-th point of each profile instead
  // shifts the kept rows by one wherever a profile has one point more above, the carrier's or an edge's: rows whose
  // end is kept in one profile and dropped in the next make a ragged outline no sensor draws.) A scan that records
  // no image rows (all 0: a PLY from elsewhere) is thinned by every stride-th point of each profile.
  const auto stride = static_cast<std::size_t>(std::max(1L, std::lround(strength))) + 1;
  const bool has_rows = std::any_of(points.begin(), points.end(), [](const ScanPoint& p) { return p.row != 0; });
  std::vector<char> lost(points.size(), 1);
  if (has_rows) {
    for (std::size_t i = 0; i < points.size(); ++i) lost[i] = points[i].row % stride == 0 ? 0 : 1;
  } else {
    for (const auto& profile : profiles_by_x(points, kProfileGap_m)) {
      for (std::size_t k = 0; k < profile.size(); k += stride) lost[profile[k]] = 0;
    }
  }
  const std::size_t before = points.size();
  erase_flagged(points, lost);
  r.thinned = before - points.size();
}

void apply_dropout(std::vector<ScanPoint>& points, double strength, Rng& rng, PerturbReport& r) {
  const auto profiles = profiles_by_x(points, kProfileGap_m);
  // Where each point sits in its profile, so a run can continue along it.
  std::vector<std::size_t> profile_of(points.size()), position(points.size());
  for (std::size_t p = 0; p < profiles.size(); ++p) {
    for (std::size_t k = 0; k < profiles[p].size(); ++k) {
      profile_of[profiles[p][k]] = p;
      position[profiles[p][k]] = k;
    }
  }
  const auto target = static_cast<std::size_t>(
      std::lround(std::min(1.0, kDropoutFraction * strength) * static_cast<double>(points.size())));
  std::vector<char> lost(points.size(), 0);
  std::size_t count = 0;
  while (count < target) {
    const std::size_t start = static_cast<std::size_t>(rng.below(points.size()));
    const bool run = rng.uniform() < kDropoutRunShare;
    const std::size_t length =
        run ? static_cast<std::size_t>(kDropoutRunMin +
                                       static_cast<int>(rng.below(kDropoutRunMax - kDropoutRunMin + 1)))
            : 1;
    const auto& profile = profiles[profile_of[start]];
    for (std::size_t k = position[start]; k < profile.size() && k < position[start] + length && count < target; ++k) {
      if (lost[profile[k]] == 0) {
        lost[profile[k]] = 1;
        ++count;
      }
    }
  }
  erase_flagged(points, lost);
  r.dropped = count;
}

void apply_noise(std::vector<ScanPoint>& points, double strength, Rng& rng, PerturbReport& r) {
  r.noise_sigma_z_m = kNoiseSigmaZ_m * strength;
  r.noise_sigma_y_m = r.noise_sigma_z_m * kNoiseYOverZ;
  for (ScanPoint& p : points) {
    p.z = static_cast<float>(p.z + rng.normal() * r.noise_sigma_z_m);
    p.y = static_cast<float>(p.y + rng.normal() * r.noise_sigma_y_m);
  }
}

bool parse_number(std::string_view text, double& out) {
  const char* end = text.data() + text.size();
  const auto [ptr, ec] = std::from_chars(text.data(), end, out);
  return ec == std::errc() && ptr == end && std::isfinite(out);
}

}  // namespace

bool PerturbSpec::empty() const {
  return std::none_of(kinds.begin(), kinds.end(), [](const PerturbSetting& s) { return s.on; });
}

std::string_view to_string(PerturbKind kind) {
  return kNames[static_cast<std::size_t>(kind)];
}

Expected<PerturbSpec> parse_perturb(std::string_view text) {
  PerturbSpec spec;
  spec.text = text.empty() ? "none" : std::string(text);
  const auto set = [&](PerturbKind kind, double strength, double share) -> Status {
    PerturbSetting& s = spec[kind];
    if (s.on)
      return make_error("perturb: '" + std::string(to_string(kind)) + "' is given twice in '" + spec.text + "'");
    s = {true, strength, share};
    return {};
  };
  std::size_t begin = 0;
  while (begin <= text.size()) {
    const std::size_t comma = std::min(text.find(',', begin), text.size());
    const std::string_view item = text.substr(begin, comma - begin);
    begin = comma + 1;
    if (item.empty()) {
      if (text.empty()) break;
      return make_error("perturb: empty item in '" + spec.text + "'");
    }
    const std::size_t at = item.find('@');
    const std::size_t colon = item.find(':');
    const std::string_view name = item.substr(0, std::min(colon, at));
    double strength = 1.0, share = 1.0;
    if (colon != std::string_view::npos) {
      const std::string_view s = item.substr(colon + 1, at == std::string_view::npos ? at : at - colon - 1);
      if (!parse_number(s, strength) || strength <= 0.0 || strength > kMaxStrength) {
        return make_error("perturb: strength '" + std::string(s) + "' of '" + std::string(name) +
                          "': expected a number in (0, 10]");
      }
    }
    if (at != std::string_view::npos) {
      const std::string_view s = item.substr(at + 1);
      if (at < colon && colon != std::string_view::npos) {
        return make_error("perturb: '" + std::string(item) + "': write KIND:STRENGTH@SHARE");
      }
      if (!parse_number(s, share) || share < 0.0 || share > 1.0) {
        return make_error("perturb: share '" + std::string(s) + "' of '" + std::string(name) +
                          "': expected a fraction in [0, 1]");
      }
    }
    if (name == "none") continue;
    if (name == "mixed") {
      if (at != std::string_view::npos) return make_error("perturb: 'mixed' sets its own shares; give it no @SHARE");
      for (const auto& [kind, kind_share] :
           {std::pair{PerturbKind::kNoise, 1.0}, std::pair{PerturbKind::kDropout, 1.0},
            std::pair{PerturbKind::kGlare, kMixedShare}, std::pair{PerturbKind::kStrayEdge, kMixedShare}}) {
        if (auto ok = set(kind, strength, kind_share); !ok) return ok.error();
      }
      continue;
    }
    const auto* found = std::find(kNames.begin(), kNames.end(), name);
    if (found == kNames.end()) {
      return make_error("perturb: unknown kind '" + std::string(name) + "' (valid: " + std::string(kValidKinds) + ")");
    }
    if (auto ok = set(static_cast<PerturbKind>(found - kNames.begin()), strength, share); !ok) return ok.error();
  }
  return spec;
}

std::vector<std::vector<std::size_t>> profiles_by_x(const std::vector<ScanPoint>& points, double gap_m) {
  std::vector<std::size_t> order(points.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return points[a].x < points[b].x; });
  std::vector<std::vector<std::size_t>> profiles;
  for (std::size_t k = 0; k < order.size(); ++k) {
    if (k == 0 || points[order[k]].x - points[order[k - 1]].x > gap_m) profiles.emplace_back();
    profiles.back().push_back(order[k]);
  }
  for (auto& profile : profiles) {
    std::stable_sort(profile.begin(), profile.end(),
                     [&](std::size_t a, std::size_t b) { return points[a].y < points[b].y; });
  }
  return profiles;
}

std::string describe(const PerturbReport& r) {
  std::string out;
  char buf[160];
  const auto add = [&](PerturbKind kind, const char* format, auto... values) {
    if (!r.applied[static_cast<std::size_t>(kind)]) return;
    std::snprintf(buf, sizeof buf, format, values...);
    out += (out.empty() ? "" : "; ") + std::string(to_string(kind)) + " " + buf;
  };
  constexpr double kMm = 1e3;
  add(PerturbKind::kSwing, "%.3f deg", r.swing_rad * 180.0 / std::numbers::pi);
  add(PerturbKind::kStrayEdge, "%s, x %.0f..%.0f mm, y %.0f..%.0f mm, %zu points",
      r.stray_edge_from_left ? "left" : "right", r.stray_edge.x_min_m * kMm, r.stray_edge.x_max_m * kMm,
      r.stray_edge.y_min_m * kMm, r.stray_edge.y_max_m * kMm, r.stray_edge.points);
  add(PerturbKind::kStrayPoints, "chain %.1f mm wide from y %.0f mm, %zu points; %zu outliers",
      (r.chain.x_max_m - r.chain.x_min_m) * kMm, r.chain.y_min_m * kMm, r.chain.points, r.outliers);
  add(PerturbKind::kGlare, "%.0f mm band, normal %.2f %.2f, %zu points lost", r.glare_width_m * kMm,
      r.glare_normal_xy.x(), r.glare_normal_xy.y(), r.glare_removed);
  add(PerturbKind::kThin, "%zu points dropped", r.thinned);
  add(PerturbKind::kDropout, "%zu points lost", r.dropped);
  add(PerturbKind::kNoise, "sigma z %.2f mm, y %.2f mm", r.noise_sigma_z_m * kMm, r.noise_sigma_y_m * kMm);
  return out.empty() ? "nothing applied" : out;
}

PerturbReport perturb_scan(std::vector<ScanPoint>& points, const PerturbSpec& spec, const Plane& support,
                           std::uint64_t seed) {
  PerturbReport r;
  r.points_in = points.size();
  for (std::size_t k = 0; k < kPerturbKinds; ++k) {
    const PerturbSetting& setting = spec.kinds[k];
    if (!setting.on || points.empty()) continue;
    const std::uint64_t kind_seed = mix_seed(seed, k + 1);
    Rng share_rng(mix_seed(kind_seed, kShareSalt));
    if (share_rng.uniform() >= setting.share) continue;
    Rng rng(kind_seed);
    // Measured again before each kind: the kinds before it changed the scan.
    const auto kind = static_cast<PerturbKind>(k);
    const bool needs_part = kind == PerturbKind::kSwing || kind == PerturbKind::kStrayEdge ||
                            kind == PerturbKind::kStrayPoints || kind == PerturbKind::kGlare;
    const Layout l = needs_part ? measure(points, support, spec.carrier_band_m) : Layout{};
    if (needs_part && l.part_points == 0) continue;
    bool applied = true;
    switch (kind) {
      case PerturbKind::kSwing: apply_swing(points, l, setting.strength, rng, r); break;
      case PerturbKind::kStrayEdge:
        applied = apply_stray_edge(points, l, support, spec.carrier_band_m, setting.strength, rng, r);
        break;
      case PerturbKind::kStrayPoints:
        apply_stray_points(points, l, support, spec.carrier_band_m, setting.strength, rng, r);
        break;
      case PerturbKind::kGlare: apply_glare(points, l, setting.strength, rng, r); break;
      case PerturbKind::kThin: apply_thin(points, setting.strength, r); break;
      case PerturbKind::kDropout: apply_dropout(points, setting.strength, rng, r); break;
      case PerturbKind::kNoise: apply_noise(points, setting.strength, rng, r); break;
    }
    r.applied[k] = applied;
  }
  r.points_out = points.size();
  return r;
}

}  // namespace cellsight::algo
