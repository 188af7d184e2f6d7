// Scene geometry of the simulated cell: planar sheet-metal facets with holes, the carrier, and parametric parts.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

namespace cellsight::sim {

struct CircleHole {
  Eigen::Vector2d centre;
  double radius;
};
struct RectHole {
  Eigen::Vector2d min, max;
};
// A regular pattern of round holes (perforated sheet), tested in O(1).
struct HoleArray {
  Eigen::Vector2d first_centre;
  Eigen::Vector2d pitch;
  int count_u, count_v;
  double radius;
};

// Even-odd test of a point against a simple polygon (points on the boundary may go either way).
[[nodiscard]] bool point_in_polygon(const std::vector<Eigen::Vector2d>& poly, const Eigen::Vector2d& p);

// One planar piece of sheet metal, zero thickness, visible from both sides.
// Points are origin + u * axis_u + v * axis_v with (u, v) inside `outline` and outside every hole.
struct Facet {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis_u = Eigen::Vector3d::UnitX();
  Eigen::Vector3d axis_v = Eigen::Vector3d::UnitY();
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  std::vector<Eigen::Vector2d> outline;  // simple polygon in (u, v)
  std::vector<CircleHole> circles;
  std::vector<RectHole> rects;
  std::vector<HoleArray> arrays;
  bool is_part = true;
  Eigen::AlignedBox3d bounds;  // filled by finalise()

  void finalise();  // normal and bounds from the axes and outline
  [[nodiscard]] bool contains(const Eigen::Vector2d& uv) const;
  [[nodiscard]] Eigen::Vector2d to_uv(const Eigen::Vector3d& p) const {
    const Eigen::Vector3d d = p - origin;
    return {d.dot(axis_u), d.dot(axis_v)};
  }
  [[nodiscard]] Eigen::Vector3d at(const Eigen::Vector2d& uv) const {
    return origin + uv.x() * axis_u + uv.y() * axis_v;
  }
  void transform(const Eigen::Isometry3d& t);
};

// --- Parametric parts (the catalogue is data: config/parts.yaml) ------------------------------------------
// Part frame: origin at the centre of the outline's bounding box, the sheet in z = 0, features rise toward +z.
enum class FeatureKind { kHole, kSlot, kWindow, kHoleArray, kRib, kLouvre, kFlange };
enum class Edge { kLeft, kRight, kTop, kBottom };

struct FeatureSpec {
  FeatureKind kind = FeatureKind::kHole;
  double x_mm = 0, y_mm = 0;           // centre
  double diameter_mm = 0;              // hole, hole_array
  double width_mm = 0, height_mm = 0;  // slot/window size; rib/louvre: width across; flange: depth
  double length_mm = 0;                // rib, louvre
  double rise_mm = 0;                  // rib height above the sheet
  double angle_deg = 0;                // louvre opening, flange bend
  bool vertical = false;               // rib/louvre/slot direction
  int count_x = 1, count_y = 1;        // hole_array, and repeats of rib/louvre/slot
  double pitch_x_mm = 0, pitch_y_mm = 0;
  Edge edge = Edge::kBottom;  // flange

  friend bool operator==(const FeatureSpec&, const FeatureSpec&) = default;
};

// What an evaluation does with a part: teach it, or keep it back as one the recogniser must call unknown.
enum class PartRole { kUnspecified, kTaught, kUntaught };

struct PartSpec {
  std::string name;
  std::string description;
  double width_mm = 0, height_mm = 0;
  std::vector<Eigen::Vector2d> outline_mm;  // optional; empty = width x height rectangle
  std::vector<FeatureSpec> features;
  std::string family;  // optional: shared by near twins (look-alike parts)
  PartRole role = PartRole::kUnspecified;

  friend bool operator==(const PartSpec&, const PartSpec&) = default;
};

// Builds the facets of a part in its own frame (metres). Fails only on specs that validate_part() rejects.
[[nodiscard]] std::vector<Facet> build_part(const PartSpec& spec);
// Empty string when the spec is buildable, else what is wrong (feature index and reason).
[[nodiscard]] std::string validate_part(const PartSpec& spec);

// The carrier (thesis Fig. 6.8): a planar frame of flat bars behind the part, in carrier coordinates.
struct CarrierParams;
[[nodiscard]] std::vector<Facet> build_carrier(const CarrierParams& params);

}  // namespace cellsight::sim
