// The model database (DESIGN.md "Model database"): manifest.yaml (formats/manifest), the taught scans, one template
// per part, the SVM. Every write is atomic; every file is checked (checksum, version, grid) before use and refused
// when it fails.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "algo/grid.hpp"
#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "formats/manifest.hpp"

namespace cellsight::app {

// Size caps of base::read_file for the database's files: far above any real one (a manifest of 1000 parts with
// 1000 scans each is ~200 MB, a model of 10 000 support vectors of 74 features 6 MB, a scan of the most vertices
// algo::PlyLimits lets in, written as ASCII, ~1 GB), low enough that a wrong path cannot exhaust the memory.
inline constexpr std::size_t kMaxManifestBytes = std::size_t{256} << 20;
inline constexpr std::size_t kMaxSvmModelBytes = std::size_t{1} << 30;
inline constexpr std::size_t kMaxTaughtScanBytes = std::size_t{4} << 30;

// Taught scans are stored as formats/scan_file (scans/PART/NNNNN.cscan): its own extension, so that nobody takes
// one for a PLY and remove_unlisted_files knows what is the database's.
inline constexpr std::string_view kTaughtScanExtension = ".cscan";
// A database taught before issue 11 holds binary PLY scans (scans/PART/NNNNN.ply); they keep working.
inline constexpr std::string_view kLegacyTaughtScanExtension = ".ply";

// The points of a taught scan file's bytes, whichever way it was stored: the compact format (told by its magic) or
// PLY. The caller has read the file and checked its CRC against the manifest.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> parse_taught_scan(std::string_view bytes);

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
  [[nodiscard]] const formats::Manifest& manifest() const { return manifest_; }
  [[nodiscard]] formats::Manifest& manifest() { return manifest_; }
  [[nodiscard]] std::string path_of(const std::string& relative) const { return dir_ + "/" + relative; }
  [[nodiscard]] std::string manifest_path() const { return dir_ + "/manifest.yaml"; }

  [[nodiscard]] const formats::PartEntry* find(std::string_view name) const;
  [[nodiscard]] formats::PartEntry* find(std::string_view name);

  // Identity of the taught parts and scans (names, ids, scan checksums): what a trained SVM depends on.
  [[nodiscard]] std::string parts_fingerprint() const;
  // Empty when the SVM matches the parts; otherwise why it is stale and what to run.
  [[nodiscard]] std::string svm_stale_reason() const;

  // Removes the templates (templates/*.dmap), taught scans (scans/PART/*.cscan or *.ply) and SVM models (svm-*.model)
  // that the manifest does not name: what a teach or train killed between writing its files and saving the manifest
  // left, or the model a training killed just after its save replaced. open_for_writing() calls it. Returns the paths
  // removed.
  [[nodiscard]] std::vector<std::string> remove_unlisted_files() const;
  // Writes manifest.yaml atomically (checksum on its last line).
  [[nodiscard]] Status save() const;

  // Removes a part: its manifest entry first (saved), then its files. The SVM becomes stale.
  [[nodiscard]] Status delete_part(std::string_view name);

 private:
  std::string dir_;
  formats::Manifest manifest_;
};

}  // namespace cellsight::app
