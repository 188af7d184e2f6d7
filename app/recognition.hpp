// The production recogniser: support removal -> grid -> depth image -> 74 features -> SVM -> Perfect Match cascade,
// over the model database, sized once at start-up so recognise() never allocates.
#pragma once

#include <memory>
#include <opencv2/core.hpp>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "algo/canonical.hpp"
#include "algo/cascade.hpp"
#include "algo/features.hpp"
#include "algo/grid.hpp"
#include "algo/part_isolation.hpp"
#include "algo/perfect_match.hpp"
#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"
#include "algo/svm.hpp"
#include "app/config.hpp"
#include "app/model_db.hpp"
#include "formats/template_file.hpp"
#include "runtime/recogniser.hpp"

namespace cellsight::app {

[[nodiscard]] algo::GridSpec grid_spec(const Config& config);

// What became of one scan on its way to the features.
enum class PrepareStatus : std::uint8_t {
  kOk,
  kEmpty,         // no point at all
  kNoPart,        // nothing left in front of the carrier
  kOutsideGrid,   // too much of the part lies outside the grid (it would be cut off)
  kTooFewPoints,  // a few stray points, not a part
};
[[nodiscard]] std::string_view to_string(PrepareStatus status);

struct PrepareReport {
  PrepareStatus status = PrepareStatus::kEmpty;
  std::size_t raw_points = 0, support_points = 0, outside_points = 0, part_points = 0;
  std::size_t stray_points = 0;  // not connected to the part (a neighbour's part at the field's edge, clutter, ghosts)
  int stray_pieces = 0;
  int edge_pieces = 0;  // of stray_pieces: large ones dropped for reaching the field's edge (a neighbour's part?)
  std::size_t hanger_points = 0;               // the chain or hook above the part, cut off where it meets the part
  [[nodiscard]] std::string describe() const;  // "12345 points, 2345 carrier, 0 outside the grid"
};

// Support removal -> the part's own frame -> occupancy grid -> depth image -> 74 features, with every buffer sized at
// construction: the
// part of the cycle that turns a raw scan into what the SVM and Perfect Match take. prepare() never allocates.
class ScanPreparer {
 public:
  static constexpr double kMaxOutsideFraction = 0.02;  // more of the part outside the grid: refused
  static constexpr std::size_t kMinPartPoints = 500;   // fewer: stray points, not a part

  ScanPreparer(const Config& config, const algo::Plane& support, std::size_t max_points);

  // keep_edge_pieces: large pieces at the field's ends stay (see algo::PartIsolator::isolate).
  [[nodiscard]] PrepareReport prepare(std::span<const algo::ScanPoint> raw, bool keep_edge_pieces = false);
  // The same from a part's points whose carrier is already gone (a synthetic training variant, algo/augment).
  [[nodiscard]] PrepareReport prepare_part(std::span<const algo::ScanPoint> part);
  // Valid after prepare() returned kOk. part_points() are in the carrier frame (what Perfect Match needs);
  // canonical_points() are the same points in the part's own frame (algo/canonical), what the grid, the depth
  // image and the features see.
  [[nodiscard]] std::span<const algo::ScanPoint> part_points() const { return part_.points(); }
  [[nodiscard]] std::span<const algo::ScanPoint> canonical_points() const { return {canonical_.data(), part_.size()}; }
  [[nodiscard]] const algo::CanonicalPose& canonical_pose() const { return canonical_pose_; }
  [[nodiscard]] const algo::FeatureVector& features() const { return features_; }
  [[nodiscard]] const algo::OccupancyGrid& grid() const { return grid_; }
  [[nodiscard]] const cv::Mat& depth_image() const { return depth_; }
  [[nodiscard]] std::size_t max_points() const { return part_.capacity(); }

 private:
  // part_ -> canonical frame -> grid -> depth image -> features.
  [[nodiscard]] PrepareReport describe_part(PrepareReport r);

  algo::Plane support_{};
  double support_threshold_m_ = 0.0;
  algo::ScanBuffer part_;
  algo::PartIsolator isolator_;
  std::vector<algo::ScanPoint> canonical_;  // part_ in the part's own frame, same capacity
  algo::CanonicalParams canonical_params_{};
  algo::CanonicalScratch canonical_scratch_;
  algo::CanonicalPose canonical_pose_{};
  algo::OccupancyGrid grid_;
  cv::Mat depth_;
  algo::FeatureExtractor extractor_;
  algo::FeatureVector features_{};
};

// Parameters of the recognition stages from the configuration.
[[nodiscard]] algo::PerfectMatchParams perfect_match_params(const Config& config);
[[nodiscard]] algo::CascadeParams cascade_params(const Config& config);
// A part's learnt limits between the manifest (formats::PartThresholds) and the cascade (algo::TemplateThresholds),
// field by field: the one place that maps them.
[[nodiscard]] algo::TemplateThresholds template_thresholds(const formats::PartThresholds& p);
[[nodiscard]] formats::PartThresholds part_thresholds(const algo::TemplateThresholds& t, bool learnt);

// The memory-mapped templates of every part, by class index (manifest order). A template that is missing or refused
// leaves an empty map in `models` (its class can never be accepted) and a line in `problems`.
struct LoadedTemplates {
  std::vector<std::optional<formats::TemplateFile>> files;
  std::vector<std::vector<int>> confusable;  // class indices; the models' spans borrow them
  std::vector<algo::TemplateModel> models;
  std::vector<std::string> problems;
};
[[nodiscard]] LoadedTemplates open_templates(const Config& config, const ModelDb& db);

// What a model database takes in memory once loaded: every template read whole, and the SVM model file.
// From the templates' headers and the SVM file's size; a template whose header cannot be read counts nothing (it will
// not be loaded either).
struct ModelFootprint {
  std::size_t templates = 0;  // counted (readable headers)
  std::uint64_t template_bytes = 0;
  std::uint64_t largest_template_bytes = 0;
  std::uint64_t svm_bytes = 0;
  [[nodiscard]] std::uint64_t total_bytes() const { return template_bytes + svm_bytes; }
};
[[nodiscard]] ModelFootprint model_footprint(const ModelDb& db);
// runtime.model_memory_mb against the footprint: an error that names the database, its need, the budget and where
// it is set, and what to do, when the database does not fit.
[[nodiscard]] Status check_model_budget(const Config& config, const ModelDb& db, const ModelFootprint& footprint);

// One opened model database, ready to recognise: the SVM and the memory-mapped templates. A part whose template
// is missing or refused (checksum, version, another grid) stays in `problems` and can never be accepted; the other
// parts keep working.
struct LoadedModels {
  std::vector<std::string> class_names;
  algo::SvmModel svm;
  LoadedTemplates templates;
};
[[nodiscard]] Expected<LoadedModels> load_models(const Config& config, const ModelDb& db);
// The trained SVM as load_models checks it (checksum against the manifest, the model itself, its classes against the
// parts), staleness aside; `parts list` uses it to find a damaged model before classify does.
[[nodiscard]] Expected<algo::SvmModel> load_svm(const ModelDb& db);

enum class RecogniserMode : std::uint8_t {
  kCascade,  // production: thesis 6.4.4 cascade with verification
  kSvmOnly,  // debug: the SVM's best class, no Perfect Match, no verification
  kPmOnly,   // debug: Perfect Match against every template, lowest error that passes its thresholds
};

// The support plane the scans are cleaned with: calibration.yaml's support section (cellsight calibrate support).
[[nodiscard]] Expected<algo::Plane> load_support_plane(const std::string& calibration_path);

// Opens the model database at `models_dir` (manifest, SVM model, templates, calibration's support plane) and builds
// the recogniser. A missing, stale or corrupt database is a clear error that says what to run.
[[nodiscard]] Expected<std::unique_ptr<runtime::Recogniser>> make_recogniser(
    const Config& config, const std::string& models_dir, const std::string& calibration_path,
    RecogniserMode mode = RecogniserMode::kCascade);

}  // namespace cellsight::app
