// The model database's manifest.yaml (DESIGN.md "Model database"): what it records, its text with a checksum line
// last, and a reader that checks the checksum and validates every field before anything is used.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "algo/grid.hpp"
#include "algo/result.hpp"

namespace cellsight::formats {

inline constexpr int kManifestFormatVersion = 1;

// Acceptance limits of one template, learnt by `cellsight train` from the part's own scans (algo/cascade).
struct PartThresholds {
  bool learnt = false;
  double max_error = 0.0;            // per-point Perfect Match cost
  double max_missing_area_m2 = 0.0;  // largest template region absent from a scan
  double max_extra_area_m2 = 0.0;    // largest scan region where the template has nothing
  double max_uncovered = 0.0;        // share of the template absent from a scan, all regions together
  double max_outliers = 0.0;         // share of a scan where the template has nothing
  double max_hole_pattern_m2 = 0.0;  // holes of one surface where the other is solid (algo::MatchReport)
  double size_centre_x_m = 0.0;      // outer width / height of a scan less the template's, as its own scans show
  double size_centre_y_m = 0.0;
  double max_size_dev_x_m = 0.0;  // ... and the largest deviation from those accepted, per axis
  double max_size_dev_y_m = 0.0;
  double max_size_dev_m = 0.0;  // the larger of the two
  // Each edge's outward offset beyond the template's as its own scans show it, and the largest deviation accepted;
  // left, right, bottom, top (algo::Edge; manifest keys edge_centre_left_m .. max_edge_dev_top_m).
  std::array<double, 4> edge_centre_m{};
  std::array<double, 4> max_edge_dev_m{};
  // Where the own scans show it, the centres move with the part's swing and tilt against the template's: metres per
  // unit of depth slope (algo::TemplateThresholds::edge_gain_m; keys size_gain_x_m, .., edge_gain_left_m ..).
  // Optional: a database trained before them has none (0: the centres alone).
  double size_gain_x_m = 0.0;
  double size_gain_y_m = 0.0;
  std::array<double, 4> edge_gain_m{};
  // Beside an edge's line, the band its own scans span about their median (algo::TemplateThresholds::edge_median_m;
  // keys edge_median_left_m, max_edge_dev_median_left_m, ..). Optional: absent, no band (0), as learnt before it.
  std::array<double, 4> edge_median_m{};
  std::array<double, 4> max_edge_dev_median_m{};
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
  std::uint32_t learn_version = 0;    // algo::kLearnVersion at the last training (0: trained before it was recorded)
  algo::GridSpec grid{};
  std::vector<PartEntry> parts;
  SvmEntry svm;
};

// The manifest's text, checksum line last (what save() writes).
[[nodiscard]] std::string manifest_text(const Manifest& manifest);
// Checks the checksum line, then parses and validates every field; `path` names the file in messages. What open()
// does with the file's bytes, in memory (the fuzz target's entry point).
[[nodiscard]] Expected<Manifest> parse_manifest(const std::string& path, const std::string& bytes);

// Part names become file names: letters, digits, '_' and '-' only, 1..64 characters.
[[nodiscard]] bool valid_part_name(std::string_view name);

}  // namespace cellsight::formats
