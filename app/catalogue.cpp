// Part catalogue reader and writer: every part and feature validated, unknown keys refused.
#include "app/catalogue.hpp"

#include <yaml-cpp/yaml.h>

#include <charconv>
#include <set>
#include <sstream>

#include "formats/yaml_reader.hpp"

namespace cellsight::app {
namespace {

constexpr double kMaxMm = 5000.0;

// The file's words for feature kinds and flange edges (read and written).
constexpr struct {
  const char* name;
  sim::FeatureKind kind;
} kKinds[] = {{"hole", sim::FeatureKind::kHole},     {"slot", sim::FeatureKind::kSlot},
              {"window", sim::FeatureKind::kWindow}, {"hole_array", sim::FeatureKind::kHoleArray},
              {"rib", sim::FeatureKind::kRib},       {"louvre", sim::FeatureKind::kLouvre},
              {"flange", sim::FeatureKind::kFlange}};
constexpr struct {
  const char* name;
  sim::Edge edge;
} kEdges[] = {
    {"left", sim::Edge::kLeft}, {"right", sim::Edge::kRight}, {"top", sim::Edge::kTop}, {"bottom", sim::Edge::kBottom}};

bool read_feature(formats::YamlSection& f, sim::FeatureSpec& out) {
  std::string type;
  f.require("type");
  f.choice("type", type, {"hole", "slot", "window", "hole_array", "rib", "louvre", "flange"});
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
  for (const auto& e : kEdges) {
    if (edge == e.name) out.edge = e.edge;
  }
  f.finish();
  return known;
}

// Shortest text that reads back to exactly `v` (std::to_chars round-trips).
std::string number_text(double v) {
  char buf[32];
  const auto end = std::to_chars(buf, buf + sizeof buf, v).ptr;
  return std::string(buf, end);
}

// A YAML double-quoted scalar (yaml-cpp escapes it): any text survives the round trip.
std::string quoted(const std::string& text) {
  YAML::Emitter out;
  out << YAML::DoubleQuoted << text;
  return out.c_str();
}

// One feature as a flow mapping; only the keys that differ from a feature's defaults (which the reader keeps).
std::string feature_yaml(const sim::FeatureSpec& f) {
  const sim::FeatureSpec defaults;
  std::string out = "{type: ";
  for (const auto& k : kKinds) {
    if (k.kind == f.kind) out += k.name;
  }
  auto number = [&](const char* key, double v, double fallback, bool always = false) {
    if (always || v != fallback) out += std::string(", ") + key + ": " + number_text(v);
  };
  const bool flange = f.kind == sim::FeatureKind::kFlange;
  number("x_mm", f.x_mm, defaults.x_mm, !flange);
  number("y_mm", f.y_mm, defaults.y_mm, !flange);
  number("diameter_mm", f.diameter_mm, defaults.diameter_mm);
  number("width_mm", f.width_mm, defaults.width_mm);
  number("height_mm", f.height_mm, defaults.height_mm);
  number("length_mm", f.length_mm, defaults.length_mm);
  number("rise_mm", f.rise_mm, defaults.rise_mm);
  number("angle_deg", f.angle_deg, defaults.angle_deg);
  if (f.vertical != defaults.vertical) out += std::string(", vertical: ") + (f.vertical ? "true" : "false");
  number("count_x", f.count_x, defaults.count_x);
  number("count_y", f.count_y, defaults.count_y);
  number("pitch_x_mm", f.pitch_x_mm, defaults.pitch_x_mm);
  number("pitch_y_mm", f.pitch_y_mm, defaults.pitch_y_mm);
  if (flange || f.edge != defaults.edge) {
    for (const auto& e : kEdges) {
      if (e.edge == f.edge) out += std::string(", edge: ") + e.name;
    }
  }
  return out + "}";
}

}  // namespace

std::string catalogue_yaml(const std::vector<sim::PartSpec>& parts, const std::string& header) {
  std::string out;
  std::istringstream lines(header);
  for (std::string line; std::getline(lines, line);) out += line.empty() ? "#\n" : "# " + line + "\n";
  out += "format_version: 1\nparts:\n";
  for (const sim::PartSpec& p : parts) {
    out += "  - name: " + quoted(p.name) + "\n";
    if (!p.description.empty()) out += "    description: " + quoted(p.description) + "\n";
    if (!p.family.empty()) out += "    family: " + quoted(p.family) + "\n";
    if (p.role != sim::PartRole::kUnspecified) {
      out += std::string("    role: ") + (p.role == sim::PartRole::kTaught ? "taught" : "untaught") + "\n";
    }
    out += "    width_mm: " + number_text(p.width_mm) + "\n";
    out += "    height_mm: " + number_text(p.height_mm) + "\n";
    if (!p.outline_mm.empty()) {
      out += "    outline_mm: [";
      for (std::size_t i = 0; i < p.outline_mm.size(); ++i) {
        out +=
            (i == 0 ? "[" : ", [") + number_text(p.outline_mm[i].x()) + ", " + number_text(p.outline_mm[i].y()) + "]";
      }
      out += "]\n";
    }
    out += p.features.empty() ? "    features: []\n" : "    features:\n";
    for (const auto& f : p.features) out += "      - " + feature_yaml(f) + "\n";
    out += "\n";
  }
  return out;
}

Expected<std::vector<sim::PartSpec>> load_catalogue(const std::string& path) {
  auto doc = formats::load_yaml_file(path);
  if (!doc) return doc.error();
  formats::YamlErrors errors(path);
  formats::YamlSection root(*doc, "", &errors);
  int version = 1;
  root.integer("format_version", version, 1, 1, "");
  std::vector<sim::PartSpec> parts;
  std::set<std::string> names;
  root.require("parts");
  for (formats::YamlSection p : root.list("parts")) {
    sim::PartSpec spec;
    p.require("name");
    p.require("width_mm");
    p.require("height_mm");
    p.text("name", spec.name);
    p.text("description", spec.description, true);
    p.text("family", spec.family);
    std::string role;
    p.choice("role", role, {"taught", "untaught"});
    spec.role = role == "taught"     ? sim::PartRole::kTaught
                : role == "untaught" ? sim::PartRole::kUntaught
                                     : sim::PartRole::kUnspecified;
    p.number("width_mm", spec.width_mm, 1.0, kMaxMm, "mm");
    p.number("height_mm", spec.height_mm, 1.0, kMaxMm, "mm");
    p.points2("outline_mm", spec.outline_mm, -kMaxMm, kMaxMm, "mm");
    bool features_ok = true;
    for (formats::YamlSection f : p.list("features")) {
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
