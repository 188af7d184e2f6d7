// The model database: manifest.yaml reader/writer with checksum, part bookkeeping, staleness of the SVM.
#include "app/model_db.hpp"

#include <cerrno>
#include <cinttypes>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <set>
#include <sstream>
#include <string>

#include "algo/features.hpp"
#include "base/atomic_file.hpp"
#include "base/crc32.hpp"
#include "base/file_read.hpp"
#include "base/local_time.hpp"
#include "drivers/log.hpp"
#include "formats/yaml_reader.hpp"

namespace cellsight::app {
namespace {

constexpr const char* kChecksumKey = "checksum_crc32";
constexpr int kMaxPartId = 65535;  // PART_ID is one Modbus register
constexpr std::size_t kMaxPartName = 64;

std::string hex32(std::uint32_t v) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "%08" PRIx32, v);
  return buf;
}

bool parse_hex32(const std::string& text, std::uint32_t& out) {
  if (text.size() != 8) return false;
  char* end = nullptr;
  errno = 0;
  const unsigned long v = std::strtoul(text.c_str(), &end, 16);
  if (errno != 0 || end != text.c_str() + text.size()) return false;
  out = static_cast<std::uint32_t>(v);
  return true;
}

std::string num(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

// YAML double-quoted scalar.
std::string quoted(const std::string& s) {
  std::string out = "\"";
  for (const char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    if (c == '\n') {
      out += "\\n";
      continue;
    }
    out += c;
  }
  return out + "\"";
}

std::size_t checksum_line_start(const std::string& text) {
  const std::string key = std::string(kChecksumKey) + ":";
  std::size_t found = std::string::npos;
  for (std::size_t pos = text.find(key); pos != std::string::npos; pos = text.find(key, pos + 1)) {
    if (pos == 0 || text[pos - 1] == '\n') found = pos;
  }
  return found;
}

}  // namespace

std::string manifest_text(const Manifest& m) {
  std::ostringstream t;
  t << "# cellsight model database. Written by 'cellsight teach' and 'cellsight train'; do not edit by hand:\n"
       "# the checksum on the last line refuses a changed or damaged manifest. Use 'cellsight parts' to inspect\n"
       "# and delete parts.\n";
  t << "format_version: " << m.format_version << "\n";
  t << "feature_version: " << m.feature_version << "\n";
  t << "grid: {nx: " << m.grid.nx << ", ny: " << m.grid.ny << ", nz: " << m.grid.nz
    << ", resolution_m: " << num(m.grid.resolution_m) << ", origin_m: [" << num(m.grid.origin_m.x()) << ", "
    << num(m.grid.origin_m.y()) << ", " << num(m.grid.origin_m.z()) << "]}\n";
  t << "parts:" << (m.parts.empty() ? " []" : "") << "\n";
  for (const PartEntry& p : m.parts) {
    t << "  - name: " << p.name << "\n";
    t << "    id: " << p.id << "\n";
    t << "    template: " << quoted(p.template_file) << "\n";
    t << "    taught_at: " << quoted(p.taught_at) << "\n";
    if (!p.template_scan.empty()) t << "    template_scan: " << quoted(p.template_scan) << "\n";
    t << "    thresholds: {learnt: " << (p.thresholds.learnt ? "true" : "false")
      << ", max_error: " << num(p.thresholds.max_error)
      << ", max_missing_area_m2: " << num(p.thresholds.max_missing_area_m2)
      << ", max_extra_area_m2: " << num(p.thresholds.max_extra_area_m2)
      << ", max_uncovered: " << num(p.thresholds.max_uncovered) << ", max_outliers: " << num(p.thresholds.max_outliers)
      << ", size_centre_x_m: " << num(p.thresholds.size_centre_x_m)
      << ", size_centre_y_m: " << num(p.thresholds.size_centre_y_m)
      << ", max_size_dev_m: " << num(p.thresholds.max_size_dev_m) << "}\n";
    if (!p.confusable.empty()) {
      std::string list;
      for (const std::string& c : p.confusable) list += (list.empty() ? "" : ",") + c;
      t << "    confusable: " << quoted(list) << "\n";
    }
    if (!p.flagged.empty()) {
      std::string list;
      for (const std::string& f : p.flagged) list += (list.empty() ? "" : ",") + f;
      t << "    flagged: " << quoted(list) << "\n";
    }
    t << "    scans:" << (p.scans.empty() ? " []" : "") << "\n";
    for (const ScanEntry& s : p.scans) {
      t << "      - {file: " << quoted(s.file) << ", crc32: \"" << hex32(s.crc32) << "\", source: " << quoted(s.source)
        << "}\n";
    }
  }
  const SvmEntry& s = m.svm;
  t << "svm:\n";
  t << "  present: " << (s.present ? "true" : "false") << "\n";
  if (s.present) {
    t << "  file: " << quoted(s.file) << "\n";
    t << "  crc32: \"" << hex32(s.crc32) << "\"\n";
    t << "  trained_at: " << quoted(s.trained_at) << "\n";
    t << "  parts_fingerprint: " << quoted(s.parts_fingerprint) << "\n";
    t << "  test_accuracy: " << num(s.test_accuracy) << "\n";
    t << "  cv_accuracy: " << num(s.cv_accuracy) << "\n";
    t << "  train_scans: " << s.train_scans << "\n";
    t << "  test_scans: " << s.test_scans << "\n";
    t << "  active_features: " << s.active_features << "\n";
    t << "  hyper: " << quoted(s.hyper) << "\n";
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

Expected<Manifest> parse_manifest(const std::string& path, const std::string& bytes) {
  const std::size_t at = checksum_line_start(bytes);
  if (at == std::string::npos) {
    return make_error(path + ": no " + kChecksumKey + " line: the manifest is truncated or not cellsight's");
  }
  {
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
  }
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
    return make_error(path + ": manifest format_version " + std::to_string(m.format_version) + ", this cellsight reads " +
                      std::to_string(kManifestFormatVersion));
  }
  std::int64_t feature_version = 0;
  top.integer("feature_version", feature_version, 0, 1000000, "");
  m.feature_version = static_cast<std::uint32_t>(feature_version);
  {
    YamlSection g = top.section("grid");
    for (const char* key : {"nx", "ny", "nz", "resolution_m", "origin_m"}) g.require(key);
    g.integer("nx", m.grid.nx, 1, 4096, "cells");
    g.integer("ny", m.grid.ny, 1, 4096, "cells");
    g.integer("nz", m.grid.nz, 1, 4096, "cells");
    g.number("resolution_m", m.grid.resolution_m, 1e-5, 1.0, "m");
    g.vec3("origin_m", m.grid.origin_m, -100.0, 100.0, "m");
    g.finish();
  }
  std::set<std::string> names;
  std::set<int> ids;
  for (YamlSection p : top.list("parts")) {
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
    {
      YamlSection t = p.section("thresholds");
      t.boolean("learnt", e.thresholds.learnt);
      // Learnt limits are used as they stand: none may be left to a default. Limits from a version that learnt fewer
      // of them count as not learnt, so the database says 'run cellsight train' instead of refusing to open.
      for (const char* key : {"max_error", "max_missing_area_m2", "max_extra_area_m2", "max_uncovered", "max_outliers",
                              "size_centre_x_m", "size_centre_y_m", "max_size_dev_m"}) {
        if (!t.has(key)) e.thresholds.learnt = false;
      }
      t.number("max_error", e.thresholds.max_error, 0.0, 1.0, "");
      t.number("max_missing_area_m2", e.thresholds.max_missing_area_m2, 0.0, 100.0, "m2");
      t.number("max_extra_area_m2", e.thresholds.max_extra_area_m2, 0.0, 100.0, "m2");
      t.number("max_uncovered", e.thresholds.max_uncovered, 0.0, 1.0, "");
      t.number("max_outliers", e.thresholds.max_outliers, 0.0, 1.0, "");
      t.number("size_centre_x_m", e.thresholds.size_centre_x_m, -1.0, 1.0, "m");
      t.number("size_centre_y_m", e.thresholds.size_centre_y_m, -1.0, 1.0, "m");
      t.number("max_size_dev_m", e.thresholds.max_size_dev_m, 0.0, 1.0, "m");
      t.finish();
    }
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
        const bool known = std::any_of(e.scans.begin(), e.scans.end(), [&](const ScanEntry& se) { return se.file == file; });
        if (!known) {
          p.error("flagged", "'" + file + "' is not one of the part's scans");
        } else {
          e.flagged.push_back(file);
        }
      }
    }
    p.finish();
    m.parts.push_back(std::move(e));
  }
  {
    YamlSection s = top.section("svm");
    s.boolean("present", m.svm.present);
    if (m.svm.present) {
      for (const char* key : {"file", "crc32", "trained_at", "parts_fingerprint"}) s.require(key);
    }
    s.text("file", m.svm.file, true);
    read_crc(s, "crc32", m.svm.crc32);
    s.text("trained_at", m.svm.trained_at, true);
    s.text("parts_fingerprint", m.svm.parts_fingerprint, true);
    s.number("test_accuracy", m.svm.test_accuracy, 0.0, 1.0, "");
    s.number("cv_accuracy", m.svm.cv_accuracy, 0.0, 1.0, "");
    s.integer("train_scans", m.svm.train_scans, 0, 100000000, "");
    s.integer("test_scans", m.svm.test_scans, 0, 100000000, "");
    s.integer("active_features", m.svm.active_features, 0, algo::kFeatureCount, "");
    s.text("hyper", m.svm.hyper, true);
    if (m.svm.present && !safe_relative(m.svm.file)) s.error("file", "must be a path inside the database");
    s.finish();
  }
  std::string ignored;
  top.text(kChecksumKey, ignored);
  top.finish();
  if (!errors.empty()) return make_error(errors.joined());
  return m;
}

namespace {

bool same_grid(const algo::GridSpec& a, const algo::GridSpec& b) {
  constexpr double kTolerance = 1e-9;
  return a.nx == b.nx && a.ny == b.ny && a.nz == b.nz && std::abs(a.resolution_m - b.resolution_m) < kTolerance &&
         (a.origin_m - b.origin_m).norm() < kTolerance;
}

std::string grid_text(const algo::GridSpec& g) {
  std::ostringstream t;
  t << g.nx << "x" << g.ny << "x" << g.nz << " cells of " << g.resolution_m * 1e3 << " mm at (" << g.origin_m.x()
    << ", " << g.origin_m.y() << ", " << g.origin_m.z() << ") m";
  return t.str();
}

}  // namespace

bool valid_part_name(std::string_view name) {
  if (name.empty() || name.size() > kMaxPartName) return false;
  for (const char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
    if (!ok) return false;
  }
  return true;
}

Expected<ModelDb> ModelDb::open(const std::string& dir, const algo::GridSpec& grid, bool create) {
  ModelDb db;
  db.dir_ = dir;
  const std::string path = db.manifest_path();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    if (!create) {
      return make_error("model database " + dir + ": " + path +
                        " is not there; teach the parts first ('cellsight teach --part NAME ...'), then "
                        "'cellsight train'");
    }
    db.manifest_.grid = grid;
    db.manifest_.feature_version = algo::kFeatureVersion;
    return db;
  }
  auto bytes = base::read_file(path, kMaxManifestBytes);
  if (!bytes) return bytes.error();
  auto manifest = parse_manifest(path, *bytes);
  if (!manifest) return manifest.error();
  if (!same_grid(manifest->grid, grid)) {
    return make_error(path + ": the database was taught on the grid " + grid_text(manifest->grid) +
                      ", the configuration has " + grid_text(grid) +
                      "; use the matching config or teach a new database (--models DIR)");
  }
  db.manifest_ = std::move(*manifest);
  return db;
}

Expected<ModelDb> ModelDb::open_for_writing(const std::string& dir, const algo::GridSpec& grid, bool create) {
  auto db = open(dir, grid, create);
  if (!db) return db;
  for (const std::string& path : remove_orphaned_temp_files(dir)) {
    CS_LOG_WARN("model_db", "removed %s: the temporary file of a write that was interrupted (killed before its rename)",
                path.c_str());
  }
  for (const std::string& path : db->remove_unlisted_files()) {
    CS_LOG_WARN("model_db",
                "removed %s: not in the manifest (a teach or train interrupted before it saved the "
                "manifest, or the model a training replaced)",
                path.c_str());
  }
  return db;
}

std::vector<std::string> ModelDb::remove_unlisted_files() const {
  namespace fs = std::filesystem;
  // What teach and train write before the manifest that names it (DESIGN.md "Model database": files first, the
  // manifest last): templates/*.dmap, scans/PART/*.ply and svm-*.model in the folder itself.
  std::set<std::string> listed;
  for (const PartEntry& p : manifest_.parts) {
    listed.insert(p.template_file);
    for (const ScanEntry& s : p.scans) listed.insert(s.file);
  }
  if (manifest_.svm.present) listed.insert(manifest_.svm.file);
  return remove_files_below(dir_, [&](const fs::path& relative) {
    const std::string name = relative.filename().string();
    const auto depth = std::distance(relative.begin(), relative.end());
    const bool ours = depth == 1   ? name.starts_with("svm-") && name.ends_with(".model")
                      : depth == 2 ? *relative.begin() == "templates" && name.ends_with(".dmap")
                                   : depth == 3 && *relative.begin() == "scans" && name.ends_with(".ply");
    return ours && listed.count(relative.generic_string()) == 0;
  });
}

const PartEntry* ModelDb::find(std::string_view name) const {
  for (const PartEntry& p : manifest_.parts) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

PartEntry* ModelDb::find(std::string_view name) {
  for (PartEntry& p : manifest_.parts) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

std::string ModelDb::parts_fingerprint() const {
  std::string identity;
  for (const PartEntry& p : manifest_.parts) {
    identity += p.name + "#" + std::to_string(p.id) + ":";
    for (const ScanEntry& s : p.scans) identity += hex32(s.crc32) + ",";
    identity += ";";
  }
  return hex32(base::crc32(identity)) + "-" + std::to_string(manifest_.parts.size());
}

std::string ModelDb::svm_stale_reason() const {
  if (manifest_.parts.empty()) return "no part is taught yet: run 'cellsight teach --part NAME ...'";
  if (!manifest_.svm.present) return "the SVM has not been trained: run 'cellsight train'";
  if (manifest_.feature_version != algo::kFeatureVersion) {
    return "the SVM was trained with feature version " + std::to_string(manifest_.feature_version) +
           ", this cellsight computes version " + std::to_string(algo::kFeatureVersion) + ": run 'cellsight train'";
  }
  if (manifest_.svm.parts_fingerprint != parts_fingerprint()) {
    return "parts or scans changed since the last training (" + manifest_.svm.trained_at +
           "): run 'cellsight train'";
  }
  for (const PartEntry& p : manifest_.parts) {
    if (!p.thresholds.learnt) return "part '" + p.name + "' has no learnt thresholds: run 'cellsight train'";
  }
  return {};
}

Status ModelDb::save() const {
  std::error_code ec;
  std::filesystem::create_directories(dir_, ec);
  if (ec) return make_error(dir_ + ": cannot create the model database folder: " + ec.message());
  return write_file_atomic(manifest_path(), manifest_text(manifest_));
}

Status ModelDb::delete_part(std::string_view name) {
  PartEntry* p = find(name);
  if (p == nullptr) return make_error("no part '" + std::string(name) + "' in " + manifest_path());
  const PartEntry removed = *p;
  std::erase_if(manifest_.parts, [&](const PartEntry& e) { return e.name == name; });
  if (auto ok = save(); !ok) {
    manifest_.parts.push_back(removed);
    return ok;
  }
  // The manifest no longer refers to them; a failure here leaves harmless orphans, reported.
  std::error_code ec;
  std::filesystem::remove(path_of(removed.template_file), ec);
  for (const ScanEntry& s : removed.scans) std::filesystem::remove(path_of(s.file), ec);
  std::filesystem::remove(path_of("scans/" + removed.name), ec);
  if (ec) return make_error("part '" + removed.name + "' removed from the manifest; some of its files remain: " +
                            ec.message());
  return {};
}

}  // namespace cellsight::app
