// Random part catalogues: outlines, feature layouts and near twins drawn from sim::Rng only.
#include "drivers/sim/random_catalogue.hpp"

#include <algorithm>
#include <array>
#include <cassert>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <optional>
#include <sstream>
#include <tuple>

#include "drivers/sim/random.hpp"

namespace cellsight::sim {
namespace {

// Flanges stand out of the sheet toward the camera; the swing of the pose turns that depth into width, which at the
// pose extremes takes a 480 mm part out of the 0.65 m grid (a 480 x 800 mm plate keeps 1.7 mm). Flanged parts stay
// narrower.
constexpr double kFlangedMaxWidthMm = 460.0;
// Repeats of one feature (rib beads, louvres, holes of a row) keep at least this much sheet between them.
constexpr double kMinRepeatGapMm = 5.0;
// Tries before giving up on one random choice (a feature placement, a part); every try draws new numbers.
constexpr int kPlacementTries = 60;
constexpr int kFeatureTries = 8;
constexpr int kPartTries = 10000;
// Purpose tags mixed into the seed so the layout and each part draw independent sequences.
constexpr std::uint64_t kLayoutPurpose = 0x6c61796f7574ULL;  // "layout"
constexpr std::uint64_t kPartPurpose = 0x70617274ULL;        // "part"

// Unit half circle in 15 degree steps, as literals: libm's sin and cos are not bit-exact across platforms.
constexpr std::array<std::array<double, 2>, 13> kHalfCircle = {{{1.0, 0.0},
                                                                {0.96592582628906831, 0.25881904510252074},
                                                                {0.86602540378443865, 0.5},
                                                                {0.70710678118654752, 0.70710678118654752},
                                                                {0.5, 0.86602540378443865},
                                                                {0.25881904510252074, 0.96592582628906831},
                                                                {0.0, 1.0},
                                                                {-0.25881904510252074, 0.96592582628906831},
                                                                {-0.5, 0.86602540378443865},
                                                                {-0.70710678118654752, 0.70710678118654752},
                                                                {-0.86602540378443865, 0.5},
                                                                {-0.96592582628906831, 0.25881904510252074},
                                                                {-1.0, 0.0}}};

enum class OutlineKind { kRectangle, kChamfered, kTrapezoid, kRoundTop, kNotched };
constexpr std::array<const char*, 5> kOutlineNames = {"rectangular plate", "chamfered plate", "trapezoid",
                                                      "round-topped plate", "notched plate"};

// What the part a twin is made from must offer for the relation to apply.
struct Needs {
  bool rectangle = false;   // height + 5 mm: no outline to reshape
  bool rib = false;         // one rib less
  bool relief = false;      // other relief: ribs or louvres to swap
  bool mirrorable = false;  // mirrored: no vertical louvres (their hinge side does not mirror)
  double max_height_mm = kRandomHeightMaxMm;
};

Needs needs_for(TwinRelation relation) {
  Needs needs;
  switch (relation) {
    case TwinRelation::kOneRibLess: needs.rib = true; break;
    case TwinRelation::kMirrored: needs.mirrorable = true; break;
    case TwinRelation::kOtherRelief: needs.relief = true; break;
    case TwinRelation::kHeightPlus5mm:
      needs.rectangle = true;
      needs.max_height_mm = kRandomHeightMaxMm - kTwinHeightStepMm;
      break;
    case TwinRelation::kOneHoleMore:
    case TwinRelation::kOneSlotMore: break;
  }
  return needs;
}

int pick_int(Rng& rng, int lo, int hi) {
  return lo + static_cast<int>(rng.below(static_cast<std::uint64_t>(hi - lo + 1)));
}
// Whole millimetres: every generated size prints exactly and reads back to the same double.
double pick_mm(Rng& rng, double lo, double hi) {
  return std::round(rng.uniform(lo, hi));
}
// Multiples of 5 mm for part sizes (half of them is then a multiple of 2.5, exact in binary).
double pick_5mm(Rng& rng, double lo, double hi) {
  return 5.0 * std::round(rng.uniform(lo, hi) / 5.0);
}
bool chance(Rng& rng, double p) {
  return rng.uniform() < p;
}
double tenth_mm(double v) {
  return std::round(v * 10.0) / 10.0;
}

template <class T>
void shuffle(std::vector<T>& items, Rng& rng) {
  for (std::size_t i = items.size(); i > 1; --i) std::swap(items[i - 1], items[rng.below(i)]);
}

std::vector<Eigen::Vector2d> plate_polygon(const PartSpec& part) {
  if (!part.outline_mm.empty()) return part.outline_mm;
  const double w2 = 0.5 * part.width_mm, h2 = 0.5 * part.height_mm;
  return {{-w2, -h2}, {w2, -h2}, {w2, h2}, {-w2, h2}};
}

bool overlaps_open(const Eigen::AlignedBox2d& a, const Eigen::AlignedBox2d& b) {
  return (a.min().array() < b.max().array()).all() && (b.min().array() < a.max().array()).all();
}

// Whether segment a-b passes through the open box (Liang-Barsky clipping; touching the border does not count).
bool segment_enters_box(const Eigen::Vector2d& a, const Eigen::Vector2d& b, const Eigen::AlignedBox2d& box) {
  double t0 = 0.0, t1 = 1.0;
  const Eigen::Vector2d d = b - a;
  for (int axis = 0; axis < 2; ++axis) {
    if (d[axis] == 0.0) {
      if (a[axis] <= box.min()[axis] || a[axis] >= box.max()[axis]) return false;
      continue;
    }
    double ta = (box.min()[axis] - a[axis]) / d[axis];
    double tb = (box.max()[axis] - a[axis]) / d[axis];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
    if (t0 >= t1) return false;
  }
  return true;
}

bool box_inside_polygon(const std::vector<Eigen::Vector2d>& poly, const Eigen::AlignedBox2d& box) {
  for (auto corner : {Eigen::AlignedBox2d::BottomLeft, Eigen::AlignedBox2d::BottomRight, Eigen::AlignedBox2d::TopLeft,
                      Eigen::AlignedBox2d::TopRight}) {
    if (!point_in_polygon(poly, box.corner(corner))) return false;
  }
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    if (segment_enters_box(poly[j], poly[i], box)) return false;
  }
  return true;
}

// Half extent of one instance of a feature (no repeats), mm.
Eigen::Vector2d single_half_extent(const FeatureSpec& f) {
  switch (f.kind) {
    case FeatureKind::kHole:
    case FeatureKind::kHoleArray: return Eigen::Vector2d::Constant(0.5 * f.diameter_mm);
    case FeatureKind::kSlot:
    case FeatureKind::kWindow: return {0.5 * f.width_mm, 0.5 * f.height_mm};
    case FeatureKind::kRib:
    case FeatureKind::kLouvre:
      return f.vertical ? Eigen::Vector2d(0.5 * f.width_mm, 0.5 * f.length_mm)
                        : Eigen::Vector2d(0.5 * f.length_mm, 0.5 * f.width_mm);
    case FeatureKind::kFlange: break;
  }
  return Eigen::Vector2d::Zero();
}

const char* kind_name(FeatureKind kind) {
  switch (kind) {
    case FeatureKind::kHole: return "hole";
    case FeatureKind::kSlot: return "slot";
    case FeatureKind::kWindow: return "window";
    case FeatureKind::kHoleArray: return "hole_array";
    case FeatureKind::kRib: return "rib";
    case FeatureKind::kLouvre: return "louvre";
    case FeatureKind::kFlange: return "flange";
  }
  return "?";
}

void mirror_left_right(PartSpec& part) {
  for (auto& p : part.outline_mm) p.x() = -p.x();
  std::reverse(part.outline_mm.begin(), part.outline_mm.end());  // keeps the outline counter-clockwise
  for (auto& f : part.features) {
    f.x_mm = -f.x_mm;
    if (f.edge == Edge::kLeft) {
      f.edge = Edge::kRight;
    } else if (f.edge == Edge::kRight) {
      f.edge = Edge::kLeft;
    }
  }
}

// Same geometry regardless of the order features and outline points are listed in.
bool same_shape(PartSpec a, PartSpec b) {
  auto key = [](const FeatureSpec& f) {
    return std::make_tuple(f.kind, f.x_mm, f.y_mm, f.diameter_mm, f.width_mm, f.height_mm, f.length_mm, f.rise_mm,
                           f.angle_deg, f.vertical, f.count_x, f.count_y, f.pitch_x_mm, f.pitch_y_mm, f.edge);
  };
  auto by_key = [&](const FeatureSpec& x, const FeatureSpec& y) { return key(x) < key(y); };
  auto by_xy = [](const Eigen::Vector2d& p, const Eigen::Vector2d& q) {
    return std::make_pair(p.x(), p.y()) < std::make_pair(q.x(), q.y());
  };
  for (PartSpec* p : {&a, &b}) {
    std::sort(p->features.begin(), p->features.end(), by_key);
    std::sort(p->outline_mm.begin(), p->outline_mm.end(), by_xy);
  }
  return a.width_mm == b.width_mm && a.height_mm == b.height_mm && a.outline_mm == b.outline_mm &&
         a.features == b.features;
}

std::vector<Eigen::Vector2d> make_outline(OutlineKind kind, double width_mm, double height_mm, Rng& rng) {
  const double w2 = 0.5 * width_mm, h2 = 0.5 * height_mm;
  std::vector<Eigen::Vector2d> out;
  switch (kind) {
    case OutlineKind::kRectangle: break;
    case OutlineKind::kChamfered: {
      const double c = pick_mm(rng, 25, 80);
      std::array<double, 4> cut{};  // bottom-left, bottom-right, top-right, top-left
      for (double& v : cut) v = chance(rng, 0.6) ? c : 0.0;
      if (std::all_of(cut.begin(), cut.end(), [](double v) { return v == 0.0; })) cut[rng.below(4)] = c;
      // Each cut corner becomes two points, one on each side that meets there (counter-clockwise order).
      const std::array<Eigen::Vector2d, 4> corners = {Eigen::Vector2d(-w2, -h2), Eigen::Vector2d(w2, -h2),
                                                      Eigen::Vector2d(w2, h2), Eigen::Vector2d(-w2, h2)};
      for (std::size_t k = 0; k < corners.size(); ++k) {
        const Eigen::Vector2d& here = corners[k];
        if (cut[k] == 0.0) {
          out.push_back(here);
          continue;
        }
        const Eigen::Vector2d& previous = corners[(k + 3) % 4];
        const Eigen::Vector2d& next = corners[(k + 1) % 4];
        out.push_back(here + cut[k] * (previous - here).normalized());
        out.push_back(here + cut[k] * (next - here).normalized());
      }
      break;
    }
    case OutlineKind::kTrapezoid: {
      const double left = pick_mm(rng, 20, 70);
      const double right = chance(rng, 0.5) ? left : pick_mm(rng, 20, 70);
      if (chance(rng, 0.7)) {  // narrow at the top
        out = {{-w2, -h2}, {w2, -h2}, {w2 - right, h2}, {-w2 + left, h2}};
      } else {
        out = {{-w2 + left, -h2}, {w2 - right, -h2}, {w2, h2}, {-w2, h2}};
      }
      break;
    }
    case OutlineKind::kRoundTop: {
      const double rise = pick_mm(rng, 80, 200);  // the arc's height above the straight sides
      out = {{-w2, -h2}, {w2, -h2}};
      for (const auto& cs : kHalfCircle) out.emplace_back(tenth_mm(w2 * cs[0]), tenth_mm(h2 - rise + rise * cs[1]));
      break;
    }
    case OutlineKind::kNotched: {
      const double notch_w = pick_mm(rng, 50, 120), depth = pick_mm(rng, 30, 80);
      switch (rng.below(3)) {
        case 0: {  // in the bottom edge
          const double room = w2 - 0.5 * notch_w - 40.0;
          const double x0 = std::round(rng.uniform(-room, room));
          out = {{-w2, -h2},
                 {x0 - 0.5 * notch_w, -h2},
                 {x0 - 0.5 * notch_w, -h2 + depth},
                 {x0 + 0.5 * notch_w, -h2 + depth},
                 {x0 + 0.5 * notch_w, -h2},
                 {w2, -h2},
                 {w2, h2},
                 {-w2, h2}};
          break;
        }
        case 1: {  // in the right edge
          const double room = h2 - 0.5 * notch_w - 60.0;
          const double y0 = std::round(rng.uniform(-room, room));
          out = {{-w2, -h2},
                 {w2, -h2},
                 {w2, y0 - 0.5 * notch_w},
                 {w2 - depth, y0 - 0.5 * notch_w},
                 {w2 - depth, y0 + 0.5 * notch_w},
                 {w2, y0 + 0.5 * notch_w},
                 {w2, h2},
                 {-w2, h2}};
          break;
        }
        default:  // the bottom-right corner
          out = {{-w2, -h2}, {w2 - notch_w, -h2}, {w2 - notch_w, -h2 + depth}, {w2, -h2 + depth}, {w2, h2}, {-w2, h2}};
          break;
      }
      break;
    }
  }
  return out;
}

FeatureSpec make_feature(FeatureKind kind, const Needs& needs, Rng& rng) {
  FeatureSpec f;
  f.kind = kind;
  switch (kind) {
    case FeatureKind::kHole:
      f.diameter_mm = pick_mm(rng, kTwinHoleMinDiameterMm, 60);
      if (chance(rng, 0.5)) {
        const int n = pick_int(rng, 2, 3);
        const double pitch = f.diameter_mm + pick_mm(rng, 30, 120);
        if (chance(rng, 0.5)) {
          f.count_x = n;
          f.pitch_x_mm = pitch;
        } else {
          f.count_y = n;
          f.pitch_y_mm = pitch;
        }
      }
      break;
    case FeatureKind::kSlot: {
      const double narrow = pick_mm(rng, kTwinSlotMinWidthMm, 40), long_side = pick_mm(rng, 60, 200);
      const int n = pick_int(rng, 1, 4);
      const double pitch = n > 1 ? narrow + pick_mm(rng, 25, 80) : 0.0;
      if (chance(rng, 0.5)) {  // upright slots side by side
        f.width_mm = narrow;
        f.height_mm = long_side;
        f.count_x = n;
        f.pitch_x_mm = pitch;
      } else {
        f.width_mm = long_side;
        f.height_mm = narrow;
        f.count_y = n;
        f.pitch_y_mm = pitch;
      }
      break;
    }
    case FeatureKind::kWindow:
      f.width_mm = pick_mm(rng, 80, 200);
      f.height_mm = pick_mm(rng, 100, 300);
      if (chance(rng, 0.3)) {
        f.count_x = 2;
        f.pitch_x_mm = f.width_mm + pick_mm(rng, 40, 80);
      }
      break;
    case FeatureKind::kHoleArray:
      f.diameter_mm = pick_mm(rng, 10, 24);
      f.count_x = pick_int(rng, 3, 8);
      f.count_y = pick_int(rng, 3, 10);
      f.pitch_x_mm = f.diameter_mm + pick_mm(rng, 8, 25);
      f.pitch_y_mm = f.diameter_mm + pick_mm(rng, 8, 25);
      break;
    case FeatureKind::kRib: {
      f.vertical = chance(rng, 0.5);
      f.length_mm = pick_mm(rng, 150, 450);
      f.width_mm = pick_mm(rng, 30, 50);
      f.rise_mm = pick_mm(rng, kTwinRibMinRiseMm, 25);
      const int n = pick_int(rng, 1, 5);
      const double pitch = n > 1 ? f.width_mm + pick_mm(rng, 20, 60) : 0.0;
      (f.vertical ? f.count_x : f.count_y) = n;
      (f.vertical ? f.pitch_x_mm : f.pitch_y_mm) = pitch;
      break;
    }
    case FeatureKind::kLouvre: {
      f.vertical = !needs.mirrorable && chance(rng, 0.3);
      f.length_mm = pick_mm(rng, 80, 160);
      f.width_mm = pick_mm(rng, 25, 40);
      f.angle_deg = pick_mm(rng, 25, 45);
      const int across = pick_int(rng, 2, 6), along = pick_int(rng, 1, 2);
      const double pitch_across = f.width_mm + pick_mm(rng, 15, 40);
      const double pitch_along = along > 1 ? f.length_mm + pick_mm(rng, 30, 60) : 0.0;
      (f.vertical ? f.count_x : f.count_y) = across;
      (f.vertical ? f.pitch_x_mm : f.pitch_y_mm) = pitch_across;
      (f.vertical ? f.count_y : f.count_x) = along;
      (f.vertical ? f.pitch_y_mm : f.pitch_x_mm) = pitch_along;
      break;
    }
    case FeatureKind::kFlange: break;
  }
  return f;
}

// Puts `f` at a random free spot of the sheet; false when none of the tries keeps the layout margins.
bool place(PartSpec& part, FeatureSpec f, Rng& rng) {
  f.x_mm = f.y_mm = 0.0;
  const Eigen::Vector2d half = feature_footprint_mm(part, f).max();
  const double room_x = 0.5 * part.width_mm - kLayoutMarginMm - half.x();
  const double room_y = 0.5 * part.height_mm - kLayoutMarginMm - half.y();
  if (room_x < 0 || room_y < 0) return false;
  for (int t = 0; t < kPlacementTries; ++t) {
    f.x_mm = std::round(rng.uniform(-room_x, room_x));
    f.y_mm = std::round(rng.uniform(-room_y, room_y));
    part.features.push_back(f);
    if (check_layout(part, kLayoutMarginMm).empty()) return true;
    part.features.pop_back();
  }
  return false;
}

void add_flanges(PartSpec& part, Rng& rng) {
  static constexpr std::array<std::array<bool, 4>, 6> kPatterns = {{// left, right, top, bottom
                                                                    {false, false, false, true},
                                                                    {false, false, true, false},
                                                                    {true, true, false, false},
                                                                    {true, false, false, false},
                                                                    {false, true, false, false},
                                                                    {false, false, true, true}}};
  const auto& pattern = kPatterns[rng.below(kPatterns.size())];
  constexpr std::array<Edge, 4> kEdges = {Edge::kLeft, Edge::kRight, Edge::kTop, Edge::kBottom};
  const double depth = pick_mm(rng, 30, 70);
  for (std::size_t i = 0; i < kEdges.size(); ++i) {
    if (!pattern[i]) continue;
    FeatureSpec f;
    f.kind = FeatureKind::kFlange;
    f.edge = kEdges[i];
    f.width_mm = depth;
    f.angle_deg = kEdges[i] == Edge::kBottom ? 5.0 * std::round(rng.uniform(60, 120) / 5.0) : 90.0;
    part.features.push_back(f);
  }
  part.width_mm = std::min(part.width_mm, kFlangedMaxWidthMm);
}

std::string summary(const PartSpec& part, OutlineKind outline) {
  int holes = 0, slots = 0, windows = 0, ribs = 0, louvres = 0, flanges = 0;
  std::string perforation;
  for (const auto& f : part.features) {
    const int n = f.count_x * f.count_y;
    switch (f.kind) {
      case FeatureKind::kHole: holes += n; break;
      case FeatureKind::kSlot: slots += n; break;
      case FeatureKind::kWindow: windows += n; break;
      case FeatureKind::kRib: ribs += n; break;
      case FeatureKind::kLouvre: louvres += n; break;
      case FeatureKind::kFlange: ++flanges; break;
      case FeatureKind::kHoleArray:
        perforation += ", perforation " + std::to_string(f.count_x) + " x " + std::to_string(f.count_y);
        break;
    }
  }
  std::ostringstream out;
  out << kOutlineNames[static_cast<std::size_t>(outline)];
  auto add = [&](int n, const char* one, const char* many) {
    if (n > 0) out << ", " << n << ' ' << (n == 1 ? one : many);
  };
  add(holes, "hole", "holes");
  add(slots, "slot", "slots");
  add(windows, "window", "windows");
  add(ribs, "rib", "ribs");
  add(louvres, "louvre", "louvres");
  add(flanges, "flange", "flanges");
  out << perforation;
  return out.str();
}

std::optional<PartSpec> make_part(const Needs& needs, Rng& rng) {
  PartSpec part;
  part.width_mm = pick_5mm(rng, kRandomWidthMinMm, kRandomWidthMaxMm);
  part.height_mm = pick_5mm(rng, kRandomHeightMinMm, needs.max_height_mm);
  const auto outline =
      needs.rectangle ? OutlineKind::kRectangle : static_cast<OutlineKind>(rng.below(kOutlineNames.size()));
  if (outline == OutlineKind::kRectangle && chance(rng, 0.5)) add_flanges(part, rng);
  part.outline_mm = make_outline(outline, part.width_mm, part.height_mm, rng);

  std::vector<FeatureKind> kinds = {FeatureKind::kHole,      FeatureKind::kSlot, FeatureKind::kWindow,
                                    FeatureKind::kHoleArray, FeatureKind::kRib,  FeatureKind::kLouvre};
  shuffle(kinds, rng);
  kinds.resize(static_cast<std::size_t>(pick_int(rng, 2, 4)));
  auto has = [&](FeatureKind k) { return std::find(kinds.begin(), kinds.end(), k) != kinds.end(); };
  if (needs.rib && !has(FeatureKind::kRib)) kinds.push_back(FeatureKind::kRib);
  if (needs.relief && !has(FeatureKind::kRib) && !has(FeatureKind::kLouvre)) {
    kinds.push_back(chance(rng, 0.5) ? FeatureKind::kRib : FeatureKind::kLouvre);
  }
  // Large features first, while the sheet is still free.
  std::sort(kinds.begin(), kinds.end(), [](FeatureKind a, FeatureKind b) {
    constexpr auto rank = [](FeatureKind k) {
      switch (k) {
        case FeatureKind::kWindow: return 0;
        case FeatureKind::kHoleArray: return 1;
        case FeatureKind::kLouvre: return 2;
        case FeatureKind::kRib: return 3;
        case FeatureKind::kSlot: return 4;
        default: return 5;
      }
    };
    return rank(a) < rank(b);
  });
  for (FeatureKind kind : kinds) {
    const int wanted = kind == FeatureKind::kHole   ? pick_int(rng, 1, 3)
                       : kind == FeatureKind::kSlot ? pick_int(rng, 1, 2)
                                                    : 1;
    for (int n = 0; n < wanted; ++n) {
      for (int t = 0; t < kFeatureTries; ++t) {
        if (place(part, make_feature(kind, needs, rng), rng)) break;
      }
    }
  }
  auto placed = [&](FeatureKind k) {
    return std::any_of(part.features.begin(), part.features.end(), [&](const FeatureSpec& f) { return f.kind == k; });
  };
  const bool plate_features = std::any_of(part.features.begin(), part.features.end(),
                                          [](const FeatureSpec& f) { return f.kind != FeatureKind::kFlange; });
  if (!plate_features) return std::nullopt;
  if (needs.rib && !placed(FeatureKind::kRib)) return std::nullopt;
  if (needs.relief && !placed(FeatureKind::kRib) && !placed(FeatureKind::kLouvre)) return std::nullopt;
  part.description = summary(part, outline);
  return part;
}

std::optional<PartSpec> make_twin(const PartSpec& base, TwinRelation relation, Rng& rng) {
  PartSpec twin = base;
  switch (relation) {
    case TwinRelation::kOneHoleMore: {
      FeatureSpec hole;
      hole.kind = FeatureKind::kHole;
      hole.diameter_mm = pick_mm(rng, 30, 50);
      if (!place(twin, hole, rng)) return std::nullopt;
      break;
    }
    case TwinRelation::kOneSlotMore: {
      FeatureSpec slot;
      slot.kind = FeatureKind::kSlot;
      const double narrow = pick_mm(rng, 25, 35), long_side = pick_mm(rng, 70, 140);
      const bool upright = chance(rng, 0.5);
      slot.width_mm = upright ? narrow : long_side;
      slot.height_mm = upright ? long_side : narrow;
      if (!place(twin, slot, rng)) return std::nullopt;
      break;
    }
    case TwinRelation::kOneRibLess: {
      std::vector<std::size_t> ribs;
      for (std::size_t i = 0; i < twin.features.size(); ++i) {
        if (twin.features[i].kind == FeatureKind::kRib) ribs.push_back(i);
      }
      if (ribs.empty()) return std::nullopt;
      const std::size_t i = ribs[rng.below(ribs.size())];
      FeatureSpec& f = twin.features[i];
      int& count = f.vertical ? f.count_x : f.count_y;
      double& centre = f.vertical ? f.x_mm : f.y_mm;
      const double pitch = f.vertical ? f.pitch_x_mm : f.pitch_y_mm;
      if (count > 1) {
        // The remaining beads stay where they were: drop the first or the last and re-centre on the rest.
        --count;
        centre += (chance(rng, 0.5) ? 0.5 : -0.5) * pitch;
        if (count == 1) (f.vertical ? f.pitch_x_mm : f.pitch_y_mm) = 0.0;
      } else {
        twin.features.erase(twin.features.begin() + static_cast<std::ptrdiff_t>(i));
      }
      break;
    }
    case TwinRelation::kMirrored:
      mirror_left_right(twin);
      if (same_shape(twin, base)) return std::nullopt;  // a symmetric part has no distinct mirror image
      break;
    case TwinRelation::kOtherRelief: {
      bool swapped = false;
      for (auto& f : twin.features) {
        if (f.kind == FeatureKind::kRib) {  // the bead's footprint becomes a louvre's cut
          f.kind = FeatureKind::kLouvre;
          f.rise_mm = 0.0;
          f.angle_deg = 35.0;
          swapped = true;
        } else if (f.kind == FeatureKind::kLouvre) {
          f.kind = FeatureKind::kRib;
          f.angle_deg = 0.0;
          f.rise_mm = 15.0;
          swapped = true;
        }
      }
      if (!swapped) return std::nullopt;
      break;
    }
    case TwinRelation::kHeightPlus5mm:
      if (!twin.outline_mm.empty() || twin.height_mm + kTwinHeightStepMm > kRandomHeightMaxMm) return std::nullopt;
      twin.height_mm += kTwinHeightStepMm;
      break;
  }
  if (!validate_part(twin).empty() || !check_layout(twin, kLayoutMarginMm).empty()) return std::nullopt;
  return twin;
}

std::string part_name(std::size_t index, int count) {
  char name[16];
  std::snprintf(name, sizeof name, "rnd%0*zu", count > 100 ? 3 : 2, index);
  return name;
}

}  // namespace

int twin_pair_count(int count) {
  if (count >= 12) return std::max(3, count / 10);
  if (count >= 8) return 2;
  return count >= 4 ? 1 : 0;
}

int untaught_count(int count) {
  return std::clamp(count - 2, 0, 3);
}

const char* twin_relation_text(TwinRelation relation) {
  switch (relation) {
    case TwinRelation::kOneHoleMore: return "one hole more";
    case TwinRelation::kOneRibLess: return "one rib less";
    case TwinRelation::kMirrored: return "mirrored left-right";
    case TwinRelation::kOtherRelief: return "same outline, ribs and louvres swapped";
    case TwinRelation::kHeightPlus5mm: return "5 mm taller";
    case TwinRelation::kOneSlotMore: return "one slot more";
  }
  return "?";
}

Eigen::AlignedBox2d feature_footprint_mm(const PartSpec& part, const FeatureSpec& f) {
  if (f.kind == FeatureKind::kFlange) {
    const double w2 = 0.5 * part.width_mm, h2 = 0.5 * part.height_mm;
    // Rounded to 0.1 mm so that libm's last bit of cos cannot move a layout decision from one machine to another.
    const double inward = std::max(1.0, tenth_mm(-std::cos(f.angle_deg * std::numbers::pi / 180.0) * f.width_mm));
    switch (f.edge) {
      case Edge::kBottom: return {Eigen::Vector2d(-w2, -h2), Eigen::Vector2d(w2, -h2 + inward)};
      case Edge::kTop: return {Eigen::Vector2d(-w2, h2 - inward), Eigen::Vector2d(w2, h2)};
      case Edge::kLeft: return {Eigen::Vector2d(-w2, -h2), Eigen::Vector2d(-w2 + inward, h2)};
      case Edge::kRight: return {Eigen::Vector2d(w2 - inward, -h2), Eigen::Vector2d(w2, h2)};
    }
  }
  const Eigen::Vector2d half =
      single_half_extent(f) + 0.5 * Eigen::Vector2d((f.count_x - 1) * f.pitch_x_mm, (f.count_y - 1) * f.pitch_y_mm);
  const Eigen::Vector2d centre(f.x_mm, f.y_mm);
  return {centre - half, centre + half};
}

std::string check_layout(const PartSpec& part, double margin_mm) {
  const std::vector<Eigen::Vector2d> polygon = plate_polygon(part);
  std::ostringstream why;
  for (std::size_t i = 0; i < part.features.size(); ++i) {
    const FeatureSpec& f = part.features[i];
    if (f.kind == FeatureKind::kFlange) continue;
    const Eigen::Vector2d size = 2.0 * single_half_extent(f);
    if ((f.count_x > 1 && f.pitch_x_mm < size.x() + kMinRepeatGapMm) ||
        (f.count_y > 1 && f.pitch_y_mm < size.y() + kMinRepeatGapMm)) {
      why << "feature " << i << " (" << kind_name(f.kind) << "): its repeats touch (pitch below size + "
          << kMinRepeatGapMm << " mm)";
      return why.str();
    }
    Eigen::AlignedBox2d grown = feature_footprint_mm(part, f);
    grown.min().array() -= margin_mm;
    grown.max().array() += margin_mm;
    if (!box_inside_polygon(polygon, grown)) {
      why << "feature " << i << " (" << kind_name(f.kind) << ") comes within " << margin_mm << " mm of the outline";
      return why.str();
    }
    for (std::size_t j = 0; j < part.features.size(); ++j) {
      if (j != i && overlaps_open(grown, feature_footprint_mm(part, part.features[j]))) {
        why << "feature " << i << " (" << kind_name(f.kind) << ") comes within " << margin_mm << " mm of feature " << j
            << " (" << kind_name(part.features[j].kind) << ")";
        return why.str();
      }
    }
  }
  return {};
}

RandomCatalogue generate_random_catalogue(int count, std::uint64_t seed) {
  count = std::clamp(count, kRandomCatalogueMinParts, kRandomCatalogueMaxParts);
  const auto n = static_cast<std::size_t>(count);
  Rng layout(mix_seed(seed, kLayoutPurpose));

  // Which parts pair up, and how: every relation once (shuffled) before any repeats; +5 mm never repeats.
  std::vector<TwinRelation> relations = {TwinRelation::kOneHoleMore,   TwinRelation::kOneRibLess,
                                         TwinRelation::kMirrored,      TwinRelation::kOtherRelief,
                                         TwinRelation::kHeightPlus5mm, TwinRelation::kOneSlotMore};
  shuffle(relations, layout);
  const std::vector<TwinRelation> repeatable = {TwinRelation::kOneHoleMore, TwinRelation::kOneRibLess,
                                                TwinRelation::kMirrored, TwinRelation::kOtherRelief,
                                                TwinRelation::kOneSlotMore};
  std::vector<std::size_t> order(n);
  for (std::size_t i = 0; i < n; ++i) order[i] = i;
  shuffle(order, layout);
  RandomCatalogue out;
  const auto pairs = static_cast<std::size_t>(twin_pair_count(count));
  for (std::size_t k = 0; k < pairs; ++k) {
    const TwinRelation r = k < relations.size() ? relations[k] : repeatable[layout.below(repeatable.size())];
    out.twins.push_back({std::min(order[2 * k], order[2 * k + 1]), std::max(order[2 * k], order[2 * k + 1]), r});
  }

  out.parts.resize(n);
  std::vector<bool> done(n, false);
  for (std::size_t i = 0; i < n; ++i) {
    if (done[i]) continue;
    const auto pair = std::find_if(out.twins.begin(), out.twins.end(), [&](const TwinPair& p) { return p.base == i; });
    const Needs needs = pair == out.twins.end() ? Needs{} : needs_for(pair->relation);
    for (int attempt = 0; attempt < kPartTries && !done[i]; ++attempt) {
      Rng rng(mix_seed(mix_seed(seed, kPartPurpose + i), static_cast<std::uint64_t>(attempt)));
      auto part = make_part(needs, rng);
      if (!part) continue;
      part->name = part_name(i, count);
      part->family = part->name;
      if (pair == out.twins.end()) {
        out.parts[i] = std::move(*part);
        done[i] = true;
        continue;
      }
      auto twin = make_twin(*part, pair->relation, rng);
      if (!twin) continue;
      twin->name = part_name(pair->twin, count);
      twin->description = "twin of " + part->name + ": " + twin_relation_text(pair->relation);
      if (pair->relation == TwinRelation::kHeightPlus5mm) {
        twin->description += " (the deliberately hard case: about two grid cells)";
      }
      part->description += "; near twin " + twin->name;
      out.parts[i] = std::move(*part);
      out.parts[pair->twin] = std::move(*twin);
      done[i] = done[pair->twin] = true;
    }
    assert(done[i] && "the generator found no layout in kPartTries tries");
  }

  // Roles: one untaught part is the twin of a taught one (a visible relation when there is one), the rest of the
  // untaught parts belong to no pair.
  for (auto& p : out.parts) p.role = PartRole::kTaught;
  int untaught = untaught_count(count);
  if (untaught > 0 && !out.twins.empty()) {
    auto pick = std::find_if(out.twins.begin(), out.twins.end(),
                             [](const TwinPair& p) { return p.relation != TwinRelation::kHeightPlus5mm; });
    if (pick == out.twins.end()) pick = out.twins.begin();
    out.parts[pick->twin].role = PartRole::kUntaught;
    --untaught;
  }
  std::vector<std::size_t> unrelated;
  for (std::size_t i = 0; i < n; ++i) {
    const bool paired =
        std::any_of(out.twins.begin(), out.twins.end(), [&](const TwinPair& p) { return p.base == i || p.twin == i; });
    if (!paired) unrelated.push_back(i);
  }
  shuffle(unrelated, layout);
  for (std::size_t k = 0; k < unrelated.size() && untaught > 0; ++k, --untaught) {
    out.parts[unrelated[k]].role = PartRole::kUntaught;
  }
  return out;
}

std::vector<PartSpec> random_catalogue(int count, std::uint64_t seed) {
  return generate_random_catalogue(count, seed).parts;
}

}  // namespace cellsight::sim
