// The model database (DESIGN.md "Model database"): manifest.yaml, the taught scans, one template per part, the SVM.
// Every write is atomic; every file is checked (checksum, version, grid) before use and refused when it fails.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "algo/grid.hpp"
#include "algo/result.hpp"

namespace cellsight::app {

inline constexpr int kManifestFormatVersion = 1;

// Acceptance limits of one template, learnt by `cellsight train` from the part's own scans (algo/cascade).
struct PartThresholds {
  bool learnt = false;
  double max_error = 0.0;            // per-point Perfect Match cost
  double max_missing_area_m2 = 0.0;  // largest template region absent from a scan
  double max_extra_area_m2 = 0.0;    // largest scan region where the template has nothing
  double max_uncovered = 0.0;        // share of the template absent from a scan, all regions together
  double max_outliers = 0.0;         // share of a scan where the template has nothing
  double size_centre_x_m = 0.0;      // outer width / height of a scan less the template's, as its own scans show
  double size_centre_y_m = 0.0;
  double max_size_dev_m = 0.0;       // ... and the largest deviation from those accepted
};

struct ScanEntry {
  std::string file;  // relative to the database folder
  std::uint32_t crc32 = 0;
  std::string source;  // where it came from: "sim seed 12", or the imported file's path
};

struct PartEntry {
  std::string name;
  int id = 0;                 // PLC id (robot program), 1..65535, unique
  std::string template_file;  // relative; the .dmap checks itself (header + body checksums)
  std::string taught_at;      // local time
  std::vector<ScanEntry> scans;
  PartThresholds thresholds;
  // The taught scan the template was built from (teach picks the one that agrees best with the others); empty in a
  // database taught before that: the first scan.
  std::string template_scan;
  [[nodiscard]] const ScanEntry* template_scan_entry() const {
    for (const ScanEntry& s : scans) {
      if (s.file == template_scan) return &s;
    }
    return scans.empty() ? nullptr : &scans.front();
  }
  // Look-alikes learnt at training (algo::near_pass): verified too whenever this part passes. Names of parts.
  std::vector<std::string> confusable;
  // Taught scans (ScanEntry::file) the last training found disagreeing with the others (algo::learn_thresholds): they
  // did not widen the thresholds; `parts list` / `show` name them so the operator can look (glare, the wrong part).
  std::vector<std::string> flagged;
};

struct SvmEntry {
  bool present = false;
  std::string file;  // relative
  std::uint32_t crc32 = 0;
  std::string trained_at;
  std::string parts_fingerprint;  // of the parts and scans it was trained on: differs -> stale
  double test_accuracy = 0.0, cv_accuracy = 0.0;
  int train_scans = 0, test_scans = 0, active_features = 0;
  std::string hyper;  // readable C / gamma / degree
};

struct Manifest {
  int format_version = kManifestFormatVersion;
  std::uint32_t feature_version = 0;  // algo::kFeatureVersion at the last training
  algo::GridSpec grid{};
  std::vector<PartEntry> parts;
  SvmEntry svm;
};

// The manifest's text, checksum line last (what save() writes).
[[nodiscard]] std::string manifest_text(const Manifest& manifest);
// Checks the checksum line, then parses and validates every field; `path` names the file in messages. What open()
// does with the file's bytes, in memory (the fuzz target's entry point).
[[nodiscard]] Expected<Manifest> parse_manifest(const std::string& path, const std::string& bytes);

// Size caps of base::read_file for the database's files: far above any real one (a manifest of 1000 parts with
// 1000 scans each is ~200 MB, a model of 10 000 support vectors of 74 features 6 MB, a scan of the most vertices
// algo::PlyLimits lets in, written as ASCII, ~1 GB), low enough that a wrong path cannot exhaust the memory.
inline constexpr std::size_t kMaxManifestBytes = std::size_t{256} << 20;
inline constexpr std::size_t kMaxSvmModelBytes = std::size_t{1} << 30;
inline constexpr std::size_t kMaxTaughtScanBytes = std::size_t{4} << 30;

class ModelDb {
 public:
  // Opens the database at `dir`. A missing manifest gives an empty database when `create` is set (nothing is
  // written until save()), an error saying what to run otherwise. A manifest for another grid is refused.
  [[nodiscard]] static Expected<ModelDb> open(const std::string& dir, const algo::GridSpec& grid, bool create);
  // open() for teach, train and `parts delete`: then removes the temporary files an interrupted atomic write left
  // (a teach killed while writing a template leaves templates/NAME.dmap.tmp-XXXXXX, 130 MB), logging each.
  [[nodiscard]] static Expected<ModelDb> open_for_writing(const std::string& dir, const algo::GridSpec& grid,
                                                          bool create);

  [[nodiscard]] const std::string& dir() const { return dir_; }
  [[nodiscard]] const Manifest& manifest() const { return manifest_; }
  [[nodiscard]] Manifest& manifest() { return manifest_; }
  [[nodiscard]] std::string path_of(const std::string& relative) const { return dir_ + "/" + relative; }
  [[nodiscard]] std::string manifest_path() const { return dir_ + "/manifest.yaml"; }

  [[nodiscard]] const PartEntry* find(std::string_view name) const;
  [[nodiscard]] PartEntry* find(std::string_view name);

  // Identity of the taught parts and scans (names, ids, scan checksums): what a trained SVM depends on.
  [[nodiscard]] std::string parts_fingerprint() const;
  // Empty when the SVM matches the parts; otherwise why it is stale and what to run.
  [[nodiscard]] std::string svm_stale_reason() const;

  // Removes the templates (templates/*.dmap), taught scans (scans/PART/*.ply) and SVM models (svm-*.model) that the
  // manifest does not name: what a teach or train killed between writing its files and saving the manifest left, or
  // the model a training killed just after its save replaced. open_for_writing() calls it. Returns the paths removed.
  [[nodiscard]] std::vector<std::string> remove_unlisted_files() const;
  // Writes manifest.yaml atomically (checksum on its last line).
  [[nodiscard]] Status save() const;

  // Removes a part: its manifest entry first (saved), then its files. The SVM becomes stale.
  [[nodiscard]] Status delete_part(std::string_view name);

 private:
  std::string dir_;
  Manifest manifest_;
};

// Part names become file names: letters, digits, '_' and '-' only, 1..64 characters.
[[nodiscard]] bool valid_part_name(std::string_view name);

}  // namespace cellsight::app
