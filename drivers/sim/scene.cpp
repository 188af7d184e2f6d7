// Builds and queries the sheet-metal facets of parts and of the carrier.
#include "drivers/sim/scene.hpp"

#include <cmath>
#include <numbers>
#include <sstream>

#include "drivers/sim/rig.hpp"

namespace cellsight::sim {
namespace {

constexpr double kMm = 1e-3;
constexpr double kDeg = std::numbers::pi / 180.0;

std::vector<Eigen::Vector2d> rectangle(double u0, double v0, double u1, double v1) {
  return {{u0, v0}, {u1, v0}, {u1, v1}, {u0, v1}};
}

// A facet from an origin, two in-plane unit axes and an outline in those axes.
Facet make_facet(const Eigen::Vector3d& origin, const Eigen::Vector3d& axis_u, const Eigen::Vector3d& axis_v,
                 std::vector<Eigen::Vector2d> outline) {
  Facet f;
  f.origin = origin;
  f.axis_u = axis_u.normalized();
  f.axis_v = axis_v.normalized();
  f.outline = std::move(outline);
  return f;
}

// Offsets of `count` repeats centred on 0 with the given pitch.
double repeat_offset(int index, int count, double pitch) {
  return (index - (count - 1) * 0.5) * pitch;
}

void add_rib(std::vector<Facet>& facets, Facet& plate, const Eigen::Vector2d& centre, const FeatureSpec& f) {
  const Eigen::Vector3d along = f.vertical ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitX();
  const Eigen::Vector3d across = f.vertical ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  const double half_len = 0.5 * f.length_mm * kMm;
  const double half_base = 0.5 * f.width_mm * kMm;
  const double half_top = 0.25 * f.width_mm * kMm;  // trapezoidal bead, flanks at atan(rise / (w/4))
  const double rise = f.rise_mm * kMm;
  const Eigen::Vector3d c(centre.x(), centre.y(), 0.0);

  const Eigen::Vector2d half_extent =
      f.vertical ? Eigen::Vector2d(half_base, half_len) : Eigen::Vector2d(half_len, half_base);
  plate.rects.push_back({centre - half_extent, centre + half_extent});

  facets.push_back(make_facet(c - half_len * along - half_top * across + rise * up, along, across,
                              rectangle(0, 0, 2 * half_len, 2 * half_top)));
  for (int side : {-1, 1}) {
    const Eigen::Vector3d base = c + side * half_base * across - half_len * along;
    const Eigen::Vector3d slope = -side * (half_base - half_top) * across + rise * up;
    facets.push_back(make_facet(base, along, slope, rectangle(0, 0, 2 * half_len, slope.norm())));
  }
  for (int end : {-1, 1}) {  // end caps close the bead so the sheet behind never shows through
    const Eigen::Vector3d origin = c + end * half_len * along;
    facets.push_back(
        make_facet(origin, across, up, {{-half_base, 0.0}, {half_base, 0.0}, {half_top, rise}, {-half_top, rise}}));
  }
}

void add_louvre(std::vector<Facet>& facets, Facet& plate, const Eigen::Vector2d& centre, const FeatureSpec& f) {
  const Eigen::Vector3d along = f.vertical ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitX();
  const Eigen::Vector3d across = f.vertical ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  const double half_len = 0.5 * f.length_mm * kMm;
  const double half_w = 0.5 * f.width_mm * kMm;
  const Eigen::Vector2d half_extent =
      f.vertical ? Eigen::Vector2d(half_w, half_len) : Eigen::Vector2d(half_len, half_w);
  plate.rects.push_back({centre - half_extent, centre + half_extent});
  // The flap stays attached along its upper (or right) edge and opens toward the camera.
  const Eigen::Vector3d hinge = Eigen::Vector3d(centre.x(), centre.y(), 0.0) + half_w * across - half_len * along;
  const double a = f.angle_deg * kDeg;
  const Eigen::Vector3d flap_dir = -std::cos(a) * across + std::sin(a) * Eigen::Vector3d::UnitZ();
  facets.push_back(make_facet(hinge, along, flap_dir, rectangle(0, 0, 2 * half_len, 2 * half_w)));
}

void add_flange(std::vector<Facet>& facets, double half_w, double half_h, const FeatureSpec& f) {
  const double a = f.angle_deg * kDeg;
  const double depth = f.width_mm * kMm;
  const Eigen::Vector3d z = Eigen::Vector3d::UnitZ();
  switch (f.edge) {
    case Edge::kBottom:
      facets.push_back(make_facet({-half_w, -half_h, 0}, Eigen::Vector3d::UnitX(),
                                  -std::cos(a) * Eigen::Vector3d::UnitY() + std::sin(a) * z,
                                  rectangle(0, 0, 2 * half_w, depth)));
      break;
    case Edge::kTop:
      facets.push_back(make_facet({-half_w, half_h, 0}, Eigen::Vector3d::UnitX(),
                                  std::cos(a) * Eigen::Vector3d::UnitY() + std::sin(a) * z,
                                  rectangle(0, 0, 2 * half_w, depth)));
      break;
    case Edge::kLeft:
      facets.push_back(make_facet({-half_w, -half_h, 0}, Eigen::Vector3d::UnitY(),
                                  -std::cos(a) * Eigen::Vector3d::UnitX() + std::sin(a) * z,
                                  rectangle(0, 0, 2 * half_h, depth)));
      break;
    case Edge::kRight:
      facets.push_back(make_facet({half_w, -half_h, 0}, Eigen::Vector3d::UnitY(),
                                  std::cos(a) * Eigen::Vector3d::UnitX() + std::sin(a) * z,
                                  rectangle(0, 0, 2 * half_h, depth)));
      break;
  }
}

}  // namespace

bool point_in_polygon(const std::vector<Eigen::Vector2d>& poly, const Eigen::Vector2d& p) {
  bool inside = false;
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    const Eigen::Vector2d& a = poly[i];
    const Eigen::Vector2d& b = poly[j];
    if ((a.y() > p.y()) != (b.y() > p.y())) {
      const double x_cross = a.x() + (p.y() - a.y()) * (b.x() - a.x()) / (b.y() - a.y());
      if (p.x() < x_cross) inside = !inside;
    }
  }
  return inside;
}

void Facet::finalise() {
  normal = axis_u.cross(axis_v).normalized();
  bounds.setEmpty();
  for (const auto& uv : outline) bounds.extend(at(uv));
}

bool Facet::contains(const Eigen::Vector2d& uv) const {
  if (!point_in_polygon(outline, uv)) return false;
  for (const auto& c : circles) {
    if ((uv - c.centre).squaredNorm() < c.radius * c.radius) return false;
  }
  for (const auto& r : rects) {
    if (uv.x() > r.min.x() && uv.x() < r.max.x() && uv.y() > r.min.y() && uv.y() < r.max.y()) return false;
  }
  for (const auto& a : arrays) {
    const Eigen::Vector2d rel = (uv - a.first_centre).cwiseQuotient(a.pitch);
    const int iu = static_cast<int>(std::lround(rel.x()));
    const int iv = static_cast<int>(std::lround(rel.y()));
    if (iu < 0 || iv < 0 || iu >= a.count_u || iv >= a.count_v) continue;
    const Eigen::Vector2d c = a.first_centre + Eigen::Vector2d(iu * a.pitch.x(), iv * a.pitch.y());
    if ((uv - c).squaredNorm() < a.radius * a.radius) return false;
  }
  return true;
}

void Facet::transform(const Eigen::Isometry3d& t) {
  origin = t * origin;
  axis_u = t.linear() * axis_u;
  axis_v = t.linear() * axis_v;
  finalise();
}

std::string validate_part(const PartSpec& spec) {
  std::ostringstream why;
  constexpr double kMinSizeMm = 50.0, kMaxSizeMm = 2000.0;
  if (spec.name.empty()) return "a part needs a name";
  if (!(spec.width_mm >= kMinSizeMm && spec.width_mm <= kMaxSizeMm) ||
      !(spec.height_mm >= kMinSizeMm && spec.height_mm <= kMaxSizeMm)) {
    why << "width_mm and height_mm must be in [" << kMinSizeMm << ", " << kMaxSizeMm << "] mm";
    return why.str();
  }
  if (!spec.outline_mm.empty() && spec.outline_mm.size() < 3) return "outline_mm needs at least 3 points";
  for (const auto& p : spec.outline_mm) {
    if (std::abs(p.x()) > 0.5 * spec.width_mm + 1e-9 || std::abs(p.y()) > 0.5 * spec.height_mm + 1e-9)
      return "outline_mm points must lie within +-width/2, +-height/2 of the centre";
  }
  for (std::size_t i = 0; i < spec.features.size(); ++i) {
    const FeatureSpec& f = spec.features[i];
    auto bad = [&](const char* reason) {
      why << "feature " << i << ": " << reason;
      return why.str();
    };
    if (std::abs(f.x_mm) > 0.5 * spec.width_mm || std::abs(f.y_mm) > 0.5 * spec.height_mm)
      return bad("centre outside the part");
    if (f.count_x < 1 || f.count_y < 1) return bad("counts must be >= 1");
    switch (f.kind) {
      case FeatureKind::kHole:
      case FeatureKind::kHoleArray:
        if (!(f.diameter_mm > 0)) return bad("diameter_mm must be > 0");
        if (f.kind == FeatureKind::kHoleArray && (f.pitch_x_mm <= f.diameter_mm && f.count_x > 1))
          return bad("pitch_x_mm must exceed diameter_mm");
        if (f.kind == FeatureKind::kHoleArray && (f.pitch_y_mm <= f.diameter_mm && f.count_y > 1))
          return bad("pitch_y_mm must exceed diameter_mm");
        break;
      case FeatureKind::kSlot:
      case FeatureKind::kWindow:
        if (!(f.width_mm > 0 && f.height_mm > 0)) return bad("width_mm and height_mm must be > 0");
        break;
      case FeatureKind::kRib:
        if (!(f.length_mm > 0 && f.width_mm > 0 && f.rise_mm > 0))
          return bad("length_mm, width_mm, rise_mm must be > 0");
        break;
      case FeatureKind::kLouvre:
        if (!(f.length_mm > 0 && f.width_mm > 0)) return bad("length_mm and width_mm must be > 0");
        if (!(f.angle_deg > 0 && f.angle_deg <= 90)) return bad("angle_deg must be in (0, 90]");
        break;
      case FeatureKind::kFlange:
        if (!(f.width_mm > 0)) return bad("width_mm (the flange depth) must be > 0");
        if (!(f.angle_deg > 0 && f.angle_deg <= 135)) return bad("angle_deg must be in (0, 135]");
        if (!spec.outline_mm.empty()) return bad("flanges need the default rectangular outline");
        break;
    }
  }
  return {};
}

std::vector<Facet> build_part(const PartSpec& spec) {
  std::vector<Facet> facets;
  const double half_w = 0.5 * spec.width_mm * kMm;
  const double half_h = 0.5 * spec.height_mm * kMm;
  Facet plate;
  if (spec.outline_mm.empty()) {
    plate.outline = rectangle(-half_w, -half_h, half_w, half_h);
  } else {
    for (const auto& p : spec.outline_mm) plate.outline.emplace_back(p * kMm);
  }
  for (const FeatureSpec& f : spec.features) {
    for (int iy = 0; iy < f.count_y; ++iy) {
      for (int ix = 0; ix < f.count_x; ++ix) {
        const Eigen::Vector2d centre((f.x_mm + repeat_offset(ix, f.count_x, f.pitch_x_mm)) * kMm,
                                     (f.y_mm + repeat_offset(iy, f.count_y, f.pitch_y_mm)) * kMm);
        switch (f.kind) {
          case FeatureKind::kHole: plate.circles.push_back({centre, 0.5 * f.diameter_mm * kMm}); break;
          case FeatureKind::kSlot:
          case FeatureKind::kWindow: {
            const Eigen::Vector2d half(0.5 * f.width_mm * kMm, 0.5 * f.height_mm * kMm);
            plate.rects.push_back({centre - half, centre + half});
            break;
          }
          case FeatureKind::kHoleArray: break;  // one O(1) pattern, added below
          case FeatureKind::kRib: add_rib(facets, plate, centre, f); break;
          case FeatureKind::kLouvre: add_louvre(facets, plate, centre, f); break;
          case FeatureKind::kFlange: break;  // once per feature, below
        }
      }
    }
    if (f.kind == FeatureKind::kHoleArray) {
      const Eigen::Vector2d first((f.x_mm - 0.5 * (f.count_x - 1) * f.pitch_x_mm) * kMm,
                                  (f.y_mm - 0.5 * (f.count_y - 1) * f.pitch_y_mm) * kMm);
      plate.arrays.push_back({first,
                              Eigen::Vector2d(std::max(f.pitch_x_mm, 1.0) * kMm, std::max(f.pitch_y_mm, 1.0) * kMm),
                              f.count_x, f.count_y, 0.5 * f.diameter_mm * kMm});
    }
    if (f.kind == FeatureKind::kFlange) add_flange(facets, half_w, half_h, f);
  }
  facets.insert(facets.begin(), std::move(plate));
  for (auto& facet : facets) {
    facet.is_part = true;
    facet.finalise();
  }
  return facets;
}

std::vector<Facet> build_carrier(const CarrierParams& p) {
  std::vector<Facet> bars;
  const double z = p.plane_z_m;
  const double bw = p.bar_width_m;
  const double margin = 0.5 * bw;
  const double bottom = 0.02;
  auto bar = [&](double x0, double y0, double x1, double y1) {
    Facet f = make_facet({0, 0, z}, Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY(), rectangle(x0, y0, x1, y1));
    f.is_part = false;
    f.finalise();
    bars.push_back(std::move(f));
  };
  bar(margin, bottom, margin + bw, p.height_m - bw);                            // left post
  bar(p.length_m - margin - bw, bottom, p.length_m - margin, p.height_m - bw);  // right post
  bar(margin, p.height_m - bw, p.length_m - margin, p.height_m);                // top bar
  bar(margin + bw, bottom, p.length_m - margin - bw, bottom + bw);              // bottom bar
  const double strap_w = 0.5 * bw;
  const double strap_bottom = p.hook_height_m - 0.12;  // reaches down behind the part's top edge
  for (int side : {-1, 1}) {
    const double xc = 0.5 * p.length_m + side * 0.5 * p.hanger_spacing_m;
    bar(xc - 0.5 * strap_w, strap_bottom, xc + 0.5 * strap_w, p.height_m - bw);
  }
  return bars;
}

}  // namespace cellsight::sim
