// Part catalogue reader: every part and feature validated, unknown keys refused.
#include "app/catalogue.hpp"

#include <set>

#include "app/yaml_reader.hpp"

namespace cellsight::app {
namespace {

constexpr double kMaxMm = 5000.0;

bool read_feature(YamlSection& f, sim::FeatureSpec& out) {
  std::string type;
  f.require("type");
  f.choice("type", type, {"hole", "slot", "window", "hole_array", "rib", "louvre", "flange"});
  static const struct {
    const char* name;
    sim::FeatureKind kind;
  } kKinds[] = {{"hole", sim::FeatureKind::kHole},         {"slot", sim::FeatureKind::kSlot},
                {"window", sim::FeatureKind::kWindow},     {"hole_array", sim::FeatureKind::kHoleArray},
                {"rib", sim::FeatureKind::kRib},           {"louvre", sim::FeatureKind::kLouvre},
                {"flange", sim::FeatureKind::kFlange}};
  bool known = false;
  for (const auto& k : kKinds) {
    if (type == k.name) {
      out.kind = k.kind;
      known = true;
    }
  }
  f.number("x_mm", out.x_mm, -kMaxMm, kMaxMm, "mm");
  f.number("y_mm", out.y_mm, -kMaxMm, kMaxMm, "mm");
  f.number("diameter_mm", out.diameter_mm, 0.0, kMaxMm, "mm");
  f.number("width_mm", out.width_mm, 0.0, kMaxMm, "mm");
  f.number("height_mm", out.height_mm, 0.0, kMaxMm, "mm");
  f.number("length_mm", out.length_mm, 0.0, kMaxMm, "mm");
  f.number("rise_mm", out.rise_mm, 0.0, 500.0, "mm");
  f.number("angle_deg", out.angle_deg, 0.0, 180.0, "deg");
  f.boolean("vertical", out.vertical);
  f.integer("count_x", out.count_x, 1, 1000, "");
  f.integer("count_y", out.count_y, 1, 1000, "");
  f.number("pitch_x_mm", out.pitch_x_mm, 0.0, kMaxMm, "mm");
  f.number("pitch_y_mm", out.pitch_y_mm, 0.0, kMaxMm, "mm");
  std::string edge = "bottom";
  f.choice("edge", edge, {"left", "right", "top", "bottom"});
  out.edge = edge == "left" ? sim::Edge::kLeft : edge == "right" ? sim::Edge::kRight : edge == "top" ? sim::Edge::kTop : sim::Edge::kBottom;
  f.finish();
  return known;
}

}  // namespace

Expected<std::vector<sim::PartSpec>> load_catalogue(const std::string& path) {
  auto doc = load_yaml_file(path);
  if (!doc) return doc.error();
  YamlErrors errors(path);
  YamlSection root(*doc, "", &errors);
  int version = 1;
  root.integer("format_version", version, 1, 1, "");
  std::vector<sim::PartSpec> parts;
  std::set<std::string> names;
  root.require("parts");
  for (YamlSection p : root.list("parts")) {
    sim::PartSpec spec;
    p.require("name");
    p.require("width_mm");
    p.require("height_mm");
    p.text("name", spec.name);
    p.text("description", spec.description, true);
    p.number("width_mm", spec.width_mm, 1.0, kMaxMm, "mm");
    p.number("height_mm", spec.height_mm, 1.0, kMaxMm, "mm");
    p.points2("outline_mm", spec.outline_mm, -kMaxMm, kMaxMm, "mm");
    bool features_ok = true;
    for (YamlSection f : p.list("features")) {
      sim::FeatureSpec feature;
      features_ok = read_feature(f, feature) && features_ok;
      spec.features.push_back(feature);
    }
    p.finish();
    if (!spec.name.empty() && !names.insert(spec.name).second) p.error("name", "'" + spec.name + "' appears twice");
    if (features_ok && errors.empty()) {
      const std::string why = sim::validate_part(spec);
      if (!why.empty()) p.error("features", "part '" + spec.name + "': " + why);
    }
    parts.push_back(std::move(spec));
  }
  root.finish();
  if (!errors.empty()) return make_error(errors.joined());
  if (parts.empty()) return make_error(path + ": parts: the catalogue is empty");
  return parts;
}

}  // namespace cellsight::app
