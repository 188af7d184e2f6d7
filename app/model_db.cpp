// The model database: opening and saving it, part bookkeeping, leftovers of interrupted writes, staleness of the SVM.
#include "app/model_db.hpp"

#include <cmath>
#include <filesystem>
#include <set>
#include <sstream>
#include <string>

#include "algo/cascade.hpp"
#include "algo/features.hpp"
#include "base/atomic_file.hpp"
#include "base/crc32.hpp"
#include "base/file_read.hpp"
#include "drivers/log.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "formats/yaml_text.hpp"

namespace cellsight::app {
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

Expected<std::vector<algo::ScanPoint>> parse_taught_scan(std::string_view bytes) {
  return formats::is_scan_file(bytes) ? formats::parse_scan_file(bytes) : formats::parse_ply(bytes);
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
    db.manifest_.learn_version = algo::kLearnVersion;
    return db;
  }
  auto bytes = base::read_file(path, kMaxManifestBytes);
  if (!bytes) return bytes.error();
  auto manifest = formats::parse_manifest(path, *bytes);
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
  for (const std::string& path : base::remove_orphaned_temp_files(dir)) {
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
  // manifest last): templates/*.dmap, scans/PART/*.cscan (*.ply before issue 11) and svm-*.model in the folder itself.
  std::set<std::string> listed;
  for (const formats::PartEntry& p : manifest_.parts) {
    listed.insert(p.template_file);
    for (const formats::ScanEntry& s : p.scans) listed.insert(s.file);
  }
  if (manifest_.svm.present) listed.insert(manifest_.svm.file);
  return base::remove_files_below(dir_, [&](const fs::path& relative) {
    const std::string name = relative.filename().string();
    const auto depth = std::distance(relative.begin(), relative.end());
    const bool ours = depth == 1 ? name.starts_with("svm-") && name.ends_with(".model")
                      : depth == 2
                          ? *relative.begin() == "templates" && name.ends_with(".dmap")
                          : depth == 3 && *relative.begin() == "scans" &&
                                (name.ends_with(kTaughtScanExtension) || name.ends_with(kLegacyTaughtScanExtension));
    return ours && listed.count(relative.generic_string()) == 0;
  });
}

const formats::PartEntry* ModelDb::find(std::string_view name) const {
  for (const formats::PartEntry& p : manifest_.parts) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

formats::PartEntry* ModelDb::find(std::string_view name) {
  for (formats::PartEntry& p : manifest_.parts) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

std::string ModelDb::parts_fingerprint() const {
  std::string identity;
  for (const formats::PartEntry& p : manifest_.parts) {
    identity += p.name + "#" + std::to_string(p.id) + ":";
    for (const formats::ScanEntry& s : p.scans) identity += formats::hex32(s.crc32) + ",";
    identity += ";";
  }
  return formats::hex32(base::crc32(identity)) + "-" + std::to_string(manifest_.parts.size());
}

std::string ModelDb::svm_stale_reason() const {
  if (manifest_.parts.empty()) return "no part is taught yet: run 'cellsight teach --part NAME ...'";
  if (!manifest_.svm.present) return "the SVM has not been trained: run 'cellsight train'";
  if (manifest_.feature_version != algo::kFeatureVersion) {
    return "the SVM was trained with feature version " + std::to_string(manifest_.feature_version) +
           ", this cellsight computes version " + std::to_string(algo::kFeatureVersion) + ": run 'cellsight train'";
  }
  if (manifest_.learn_version != algo::kLearnVersion) {
    return "the parts' limits were learnt by a cellsight of learn version " + std::to_string(manifest_.learn_version) +
           ", this one learns version " + std::to_string(algo::kLearnVersion) +
           " (limits learnt before may not keep near twins apart): run 'cellsight train'";
  }
  if (manifest_.svm.parts_fingerprint != parts_fingerprint()) {
    return "parts or scans changed since the last training (" + manifest_.svm.trained_at + "): run 'cellsight train'";
  }
  for (const formats::PartEntry& p : manifest_.parts) {
    if (!p.thresholds.learnt) return "part '" + p.name + "' has no learnt thresholds: run 'cellsight train'";
  }
  return {};
}

Status ModelDb::save() const {
  std::error_code ec;
  std::filesystem::create_directories(dir_, ec);
  if (ec) return make_error(dir_ + ": cannot create the model database folder: " + ec.message());
  return base::write_file_atomic(manifest_path(), formats::manifest_text(manifest_));
}

Status ModelDb::delete_part(std::string_view name) {
  formats::PartEntry* p = find(name);
  if (p == nullptr) return make_error("no part '" + std::string(name) + "' in " + manifest_path());
  const formats::PartEntry removed = *p;
  std::erase_if(manifest_.parts, [&](const formats::PartEntry& e) { return e.name == name; });
  if (auto ok = save(); !ok) {
    manifest_.parts.push_back(removed);
    return ok;
  }
  // The manifest no longer refers to them; a failure here leaves harmless orphans, reported.
  std::error_code ec;
  std::filesystem::remove(path_of(removed.template_file), ec);
  for (const formats::ScanEntry& s : removed.scans) std::filesystem::remove(path_of(s.file), ec);
  std::filesystem::remove(path_of("scans/" + removed.name), ec);
  if (ec)
    return make_error("part '" + removed.name +
                      "' removed from the manifest; some of its files remain: " + ec.message());
  return {};
}

}  // namespace cellsight::app
