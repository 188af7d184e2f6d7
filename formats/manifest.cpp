// manifest.yaml: writer with a checksum line last, checking reader (checksum first, then every field).
#include "formats/manifest.hpp"

#include <algorithm>
#include <filesystem>
#include <set>
#include <sstream>
#include <string>

#include "algo/features.hpp"
#include "base/crc32.hpp"
#include "formats/yaml_reader.hpp"
#include "formats/yaml_text.hpp"

namespace cellsight::formats {
namespace {

using formats::hex32;
using formats::number;
using formats::parse_hex32;

constexpr const char* kChecksumKey = "checksum_crc32";
constexpr int kMaxPartId = 65535;  // PART_ID is one Modbus register
// PartThresholds::edge_centre_m / max_edge_dev_m, in algo::Edge order.
constexpr std::array<const char*, 4> kEdgeCentreKeys = {"edge_centre_left_m", "edge_centre_right_m",
                                                        "edge_centre_bottom_m", "edge_centre_top_m"};
constexpr std::array<const char*, 4> kEdgeDevKeys = {"max_edge_dev_left_m", "max_edge_dev_right_m",
                                                     "max_edge_dev_bottom_m", "max_edge_dev_top_m"};
constexpr std::array<const char*, 4> kEdgeGainKeys = {"edge_gain_left_m", "edge_gain_right_m", "edge_gain_bottom_m",
                                                      "edge_gain_top_m"};
constexpr std::array<const char*, 4> kEdgeMedianKeys = {"edge_median_left_m", "edge_median_right_m",
                                                        "edge_median_bottom_m", "edge_median_top_m"};
constexpr std::array<const char*, 4> kEdgeMedianDevKeys = {"max_edge_dev_median_left_m", "max_edge_dev_median_right_m",
                                                           "max_edge_dev_median_bottom_m", "max_edge_dev_median_top_m"};
constexpr double kMaxGainM = 1.0;  // metres per unit of slope: the range a gain is read in
constexpr std::size_t kMaxPartName = 64;

}  // namespace

std::string manifest_text(const Manifest& m) {
  std::ostringstream t;
  t << "# cellsight model database. Written by 'cellsight teach' and 'cellsight train'; do not edit by hand:\n"
       "# the checksum on the last line refuses a changed or damaged manifest. Use 'cellsight parts' to inspect\n"
       "# and delete parts.\n";
  t << "format_version: " << m.format_version << "\n";
  t << "feature_version: " << m.feature_version << "\n";
  t << "learn_version: " << m.learn_version << "\n";
  t << "grid: {nx: " << m.grid.nx << ", ny: " << m.grid.ny << ", nz: " << m.grid.nz
    << ", resolution_m: " << number(m.grid.resolution_m) << ", origin_m: [" << number(m.grid.origin_m.x()) << ", "
    << number(m.grid.origin_m.y()) << ", " << number(m.grid.origin_m.z()) << "]}\n";
  t << "parts:" << (m.parts.empty() ? " []" : "") << "\n";
  for (const PartEntry& p : m.parts) {
    t << "  - name: " << p.name << "\n";
    t << "    id: " << p.id << "\n";
    t << "    template: " << formats::yaml_quoted(p.template_file) << "\n";
    t << "    taught_at: " << formats::yaml_quoted(p.taught_at) << "\n";
    if (!p.template_scan.empty()) t << "    template_scan: " << formats::yaml_quoted(p.template_scan) << "\n";
    t << "    thresholds: {learnt: " << (p.thresholds.learnt ? "true" : "false")
      << ", max_error: " << number(p.thresholds.max_error)
      << ", max_missing_area_m2: " << number(p.thresholds.max_missing_area_m2)
      << ", max_extra_area_m2: " << number(p.thresholds.max_extra_area_m2)
      << ", max_uncovered: " << number(p.thresholds.max_uncovered)
      << ", max_outliers: " << number(p.thresholds.max_outliers)
      << ", max_hole_pattern_m2: " << number(p.thresholds.max_hole_pattern_m2)
      << ", size_centre_x_m: " << number(p.thresholds.size_centre_x_m)
      << ", size_centre_y_m: " << number(p.thresholds.size_centre_y_m)
      << ", max_size_dev_x_m: " << number(p.thresholds.max_size_dev_x_m)
      << ", max_size_dev_y_m: " << number(p.thresholds.max_size_dev_y_m)
      << ", max_size_dev_m: " << number(p.thresholds.max_size_dev_m);
    for (std::size_t e = 0; e < p.thresholds.edge_centre_m.size(); ++e) {
      t << ", " << kEdgeCentreKeys[e] << ": " << number(p.thresholds.edge_centre_m[e]) << ", " << kEdgeDevKeys[e]
        << ": " << number(p.thresholds.max_edge_dev_m[e]);
    }
    t << ", size_gain_x_m: " << number(p.thresholds.size_gain_x_m)
      << ", size_gain_y_m: " << number(p.thresholds.size_gain_y_m);
    for (std::size_t e = 0; e < p.thresholds.edge_gain_m.size(); ++e) {
      t << ", " << kEdgeGainKeys[e] << ": " << number(p.thresholds.edge_gain_m[e]);
    }
    for (std::size_t e = 0; e < p.thresholds.edge_median_m.size(); ++e) {
      t << ", " << kEdgeMedianKeys[e] << ": " << number(p.thresholds.edge_median_m[e]) << ", " << kEdgeMedianDevKeys[e]
        << ": " << number(p.thresholds.max_edge_dev_median_m[e]);
    }
    t << "}\n";
    if (!p.confusable.empty()) {
      std::string list;
      for (const std::string& c : p.confusable) list += (list.empty() ? "" : ",") + c;
      t << "    confusable: " << formats::yaml_quoted(list) << "\n";
    }
    if (!p.flagged.empty()) {
      std::string list;
      for (const std::string& f : p.flagged) list += (list.empty() ? "" : ",") + f;
      t << "    flagged: " << formats::yaml_quoted(list) << "\n";
    }
    t << "    scans:" << (p.scans.empty() ? " []" : "") << "\n";
    for (const ScanEntry& s : p.scans) {
      t << "      - {file: " << formats::yaml_quoted(s.file) << ", crc32: \"" << hex32(s.crc32)
        << "\", source: " << formats::yaml_quoted(s.source) << "}\n";
    }
  }
  const SvmEntry& s = m.svm;
  t << "svm:\n";
  t << "  present: " << (s.present ? "true" : "false") << "\n";
  if (s.present) {
    t << "  file: " << formats::yaml_quoted(s.file) << "\n";
    t << "  crc32: \"" << hex32(s.crc32) << "\"\n";
    t << "  trained_at: " << formats::yaml_quoted(s.trained_at) << "\n";
    t << "  parts_fingerprint: " << formats::yaml_quoted(s.parts_fingerprint) << "\n";
    t << "  test_accuracy: " << number(s.test_accuracy) << "\n";
    t << "  cv_accuracy: " << number(s.cv_accuracy) << "\n";
    t << "  train_scans: " << s.train_scans << "\n";
    t << "  test_scans: " << s.test_scans << "\n";
    t << "  active_features: " << s.active_features << "\n";
    t << "  hyper: " << formats::yaml_quoted(s.hyper) << "\n";
  }
  std::string text = t.str();
  text += std::string(kChecksumKey) + ": \"" + hex32(base::crc32(text)) + "\"\n";
  return text;
}

namespace {

void read_crc(YamlSection& s, const char* key, std::uint32_t& out) {
  std::string text;
  s.text(key, text);
  if (!text.empty() && !parse_hex32(text, out)) s.error(key, "'" + text + "' is not 8 hex digits");
}

// A relative path inside the database: no absolute paths, no "..".
bool safe_relative(const std::string& p) {
  if (p.empty() || p[0] == '/') return false;
  for (const auto& part : std::filesystem::path(p)) {
    if (part == "..") return false;
  }
  return true;
}

}  // namespace

namespace {

// The checksum line: present, readable and matching everything before it.
Status check_manifest_checksum(const std::string& path, const std::string& bytes) {
  const std::size_t at = formats::checksum_line_start(bytes, kChecksumKey);
  if (at == std::string::npos) {
    return make_error(path + ": no " + kChecksumKey + " line: the manifest is truncated or not cellsight's");
  }
  const std::string line = bytes.substr(at);
  std::uint32_t stored = 0;
  const std::size_t q1 = line.find('"');
  const std::size_t q2 = q1 == std::string::npos ? q1 : line.find('"', q1 + 1);
  if (q2 == std::string::npos || !parse_hex32(line.substr(q1 + 1, q2 - q1 - 1), stored)) {
    return make_error(path + ": unreadable " + kChecksumKey + " line");
  }
  const std::uint32_t actual = base::crc32(std::string_view(bytes).substr(0, at));
  if (actual != stored) {
    return make_error(path + ": checksum mismatch (stored " + hex32(stored) + ", content " + hex32(actual) +
                      "): the manifest was changed or damaged; restore it from a backup or teach again");
  }
  return {};
}

void read_grid(YamlSection g, algo::GridSpec& grid) {
  for (const char* key : {"nx", "ny", "nz", "resolution_m", "origin_m"}) g.require(key);
  g.integer("nx", grid.nx, 1, 4096, "cells");
  g.integer("ny", grid.ny, 1, 4096, "cells");
  g.integer("nz", grid.nz, 1, 4096, "cells");
  g.number("resolution_m", grid.resolution_m, 1e-5, 1.0, "m");
  g.vec3("origin_m", grid.origin_m, -100.0, 100.0, "m");
  g.finish();
}

// The learnt limits of a part as the manifest names them, with their ranges.
struct ThresholdField {
  const char* key;
  double PartThresholds::*value;
  double min, max;
  const char* unit;
};
constexpr ThresholdField kThresholdFields[] = {
    {"max_error", &PartThresholds::max_error, 0.0, 1.0, ""},
    {"max_missing_area_m2", &PartThresholds::max_missing_area_m2, 0.0, 100.0, "m2"},
    {"max_extra_area_m2", &PartThresholds::max_extra_area_m2, 0.0, 100.0, "m2"},
    {"max_uncovered", &PartThresholds::max_uncovered, 0.0, 1.0, ""},
    {"max_outliers", &PartThresholds::max_outliers, 0.0, 1.0, ""},
    {"max_hole_pattern_m2", &PartThresholds::max_hole_pattern_m2, 0.0, 100.0, "m2"},
    {"size_centre_x_m", &PartThresholds::size_centre_x_m, -1.0, 1.0, "m"},
    {"size_centre_y_m", &PartThresholds::size_centre_y_m, -1.0, 1.0, "m"},
    {"max_size_dev_x_m", &PartThresholds::max_size_dev_x_m, 0.0, 1.0, "m"},
    {"max_size_dev_y_m", &PartThresholds::max_size_dev_y_m, 0.0, 1.0, "m"},
    {"max_size_dev_m", &PartThresholds::max_size_dev_m, 0.0, 1.0, "m"},
};

void read_thresholds(YamlSection t, PartThresholds& thresholds) {
  t.boolean("learnt", thresholds.learnt);
  // Learnt limits are used as they stand: none may be left to a default. Limits from a version that learnt fewer
  // of them count as not learnt, so the database says 'run cellsight train' instead of refusing to open.
  for (const ThresholdField& f : kThresholdFields) {
    if (!t.has(f.key)) thresholds.learnt = false;
  }
  for (std::size_t e = 0; e < thresholds.edge_centre_m.size(); ++e) {
    if (!t.has(kEdgeCentreKeys[e]) || !t.has(kEdgeDevKeys[e])) thresholds.learnt = false;
  }
  for (const ThresholdField& f : kThresholdFields) t.number(f.key, thresholds.*f.value, f.min, f.max, f.unit);
  for (std::size_t e = 0; e < thresholds.edge_centre_m.size(); ++e) {
    t.number(kEdgeCentreKeys[e], thresholds.edge_centre_m[e], -1.0, 1.0, "m");
    t.number(kEdgeDevKeys[e], thresholds.max_edge_dev_m[e], 0.0, 1.0, "m");
  }
  // The gains are optional (absent: 0, the centres alone, as learnt before them).
  if (t.has("size_gain_x_m")) t.number("size_gain_x_m", thresholds.size_gain_x_m, -kMaxGainM, kMaxGainM, "m");
  if (t.has("size_gain_y_m")) t.number("size_gain_y_m", thresholds.size_gain_y_m, -kMaxGainM, kMaxGainM, "m");
  for (std::size_t e = 0; e < thresholds.edge_gain_m.size(); ++e) {
    if (t.has(kEdgeGainKeys[e])) t.number(kEdgeGainKeys[e], thresholds.edge_gain_m[e], -kMaxGainM, kMaxGainM, "m");
  }
  // So are the bands about the edges' medians (absent: none).
  for (std::size_t e = 0; e < thresholds.edge_median_m.size(); ++e) {
    if (t.has(kEdgeMedianKeys[e])) t.number(kEdgeMedianKeys[e], thresholds.edge_median_m[e], -1.0, 1.0, "m");
    if (t.has(kEdgeMedianDevKeys[e])) {
      t.number(kEdgeMedianDevKeys[e], thresholds.max_edge_dev_median_m[e], 0.0, 1.0, "m");
    }
  }
  t.finish();
}

// One entry of `parts`; `names` and `ids` (of the entries before it) catch a name or PLC id given twice.
PartEntry read_part(YamlSection& p, std::set<std::string>& names, std::set<int>& ids) {
  PartEntry e;
  for (const char* key : {"name", "id", "template", "taught_at", "thresholds", "scans"}) p.require(key);
  p.text("name", e.name);
  p.integer("id", e.id, 1, kMaxPartId, "");
  p.text("template", e.template_file);
  p.text("taught_at", e.taught_at, true);
  p.text("template_scan", e.template_scan, true);  // optional (older databases: the first scan)
  if (!valid_part_name(e.name)) p.error("name", "'" + e.name + "' is not a valid part name");
  if (!names.insert(e.name).second) p.error("name", "part '" + e.name + "' appears twice");
  if (!ids.insert(e.id).second) p.error("id", "PLC id " + std::to_string(e.id) + " appears twice");
  if (!safe_relative(e.template_file)) p.error("template", "must be a path inside the database");
  {
    std::string list;
    p.text("confusable", list, true);  // optional: a database trained before look-alikes were learnt has none
    std::stringstream in(list);
    for (std::string name; std::getline(in, name, ',');) {
      if (!valid_part_name(name)) {
        p.error("confusable", "'" + name + "' is not a valid part name");
      } else {
        e.confusable.push_back(name);
      }
    }
  }
  std::string flagged;
  p.text("flagged", flagged, true);  // optional: none flagged, or trained before scans were flagged
  read_thresholds(p.section("thresholds"), e.thresholds);
  for (YamlSection s : p.list("scans")) {
    ScanEntry se;
    s.require("file");
    s.require("crc32");
    s.text("file", se.file);
    read_crc(s, "crc32", se.crc32);
    s.text("source", se.source, true);
    if (!safe_relative(se.file)) s.error("file", "must be a path inside the database");
    s.finish();
    e.scans.push_back(std::move(se));
  }
  {
    std::stringstream in(flagged);
    for (std::string file; std::getline(in, file, ',');) {
      const bool known =
          std::any_of(e.scans.begin(), e.scans.end(), [&](const ScanEntry& se) { return se.file == file; });
      if (!known) {
        p.error("flagged", "'" + file + "' is not one of the part's scans");
      } else {
        e.flagged.push_back(file);
      }
    }
  }
  return e;
}

void read_svm(YamlSection s, SvmEntry& svm) {
  s.boolean("present", svm.present);
  if (svm.present) {
    for (const char* key : {"file", "crc32", "trained_at", "parts_fingerprint"}) s.require(key);
  }
  s.text("file", svm.file, true);
  read_crc(s, "crc32", svm.crc32);
  s.text("trained_at", svm.trained_at, true);
  s.text("parts_fingerprint", svm.parts_fingerprint, true);
  s.number("test_accuracy", svm.test_accuracy, 0.0, 1.0, "");
  s.number("cv_accuracy", svm.cv_accuracy, 0.0, 1.0, "");
  s.integer("train_scans", svm.train_scans, 0, 100000000, "");
  s.integer("test_scans", svm.test_scans, 0, 100000000, "");
  s.integer("active_features", svm.active_features, 0, algo::kFeatureCount, "");
  s.text("hyper", svm.hyper, true);
  if (svm.present && !safe_relative(svm.file)) s.error("file", "must be a path inside the database");
  s.finish();
}

}  // namespace

Expected<Manifest> parse_manifest(const std::string& path, const std::string& bytes) {
  if (Status checksum = check_manifest_checksum(path, bytes); !checksum) return checksum.error();
  YAML::Node root;
  try {
    root = YAML::Load(bytes);
  } catch (const YAML::Exception& e) {  // yaml-cpp reports through exceptions; stop them at this boundary
    return make_error(path + ":" + std::to_string(e.mark.line + 1) + ": YAML syntax error: " + e.msg);
  }
  if (!root.IsMap()) return make_error(path + ": not a manifest (expected a mapping)");
  YamlErrors errors(path);
  YamlSection top(root, "", &errors);
  Manifest m;
  for (const char* key : {"format_version", "feature_version", "grid", "parts", "svm", kChecksumKey}) top.require(key);
  top.integer("format_version", m.format_version, 1, 1000, "");
  if (m.format_version != kManifestFormatVersion) {
    return make_error(path + ": manifest format_version " + std::to_string(m.format_version) +
                      ", this cellsight reads " + std::to_string(kManifestFormatVersion));
  }
  std::int64_t feature_version = 0;
  top.integer("feature_version", feature_version, 0, 1000000, "");
  m.feature_version = static_cast<std::uint32_t>(feature_version);
  if (top.has("learn_version")) {  // optional: a database trained before it was recorded has none (0)
    std::int64_t learn_version = 0;
    top.integer("learn_version", learn_version, 0, 1000000, "");
    m.learn_version = static_cast<std::uint32_t>(learn_version);
  }
  read_grid(top.section("grid"), m.grid);
  std::set<std::string> names;
  std::set<int> ids;
  for (YamlSection p : top.list("parts")) {
    PartEntry e = read_part(p, names, ids);
    p.finish();
    m.parts.push_back(std::move(e));
  }
  read_svm(top.section("svm"), m.svm);
  std::string ignored;
  top.text(kChecksumKey, ignored);
  top.finish();
  if (!errors.empty()) return make_error(errors.joined());
  return m;
}

bool valid_part_name(std::string_view name) {
  if (name.empty() || name.size() > kMaxPartName) return false;
  for (const char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
    if (!ok) return false;
  }
  return true;
}

}  // namespace cellsight::formats
