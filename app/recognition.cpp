// The production recogniser (see recognition.hpp).
#include "app/recognition.hpp"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>

#include "algo/support.hpp"
#include "app/scan_acquisition.hpp"
#include "base/crc32.hpp"
#include "base/file_read.hpp"
#include "drivers/log.hpp"
#include "formats/calibration_file.hpp"

namespace cellsight::app {

algo::GridSpec grid_spec(const Config& config) {
  algo::GridSpec spec;
  spec.origin_m = config.grid.origin_m;
  spec.nx = config.grid.nx;
  spec.ny = config.grid.ny;
  spec.nz = config.grid.nz;
  spec.resolution_m = config.grid.resolution_m;
  return spec;
}

std::string_view to_string(PrepareStatus status) {
  switch (status) {
    case PrepareStatus::kOk: return "ok";
    case PrepareStatus::kEmpty: return "the scan has no point";
    case PrepareStatus::kNoPart: return "nothing in front of the carrier";
    case PrepareStatus::kOutsideGrid: return "the part does not fit the grid";
    case PrepareStatus::kTooFewPoints: return "too few points for a part";
  }
  return "invalid";
}

std::string PrepareReport::describe() const {
  return std::to_string(raw_points) + " points, " + std::to_string(support_points) + " on the carrier, " +
         (stray_points > 0 ? std::to_string(stray_points) + " in " + std::to_string(stray_pieces) +
                                 " pieces not connected to the part, "
                           : std::string()) +
         (hanger_points > 0 ? std::to_string(hanger_points) + " on the hanger, " : std::string()) +
         std::to_string(outside_points) + " of the part outside the grid, " + std::to_string(part_points) +
         " on the part";
}

ScanPreparer::ScanPreparer(const Config& config, const algo::Plane& support, std::size_t max_points)
    : support_(support),
      support_threshold_m_(config.support.distance_threshold_mm * 1e-3),
      part_(max_points),
      isolator_(grid_spec(config), algo::IsolationParams{}),
      canonical_(max_points),
      canonical_scratch_(grid_spec(config)),
      grid_(grid_spec(config), max_points) {
  const algo::GridSpec spec = grid_spec(config);
  extractor_ = algo::FeatureExtractor(spec.ny, spec.nx, algo::feature_params_for(spec));
  depth_.create(spec.ny, spec.nx, CV_8UC1);
}

PrepareReport ScanPreparer::prepare(std::span<const algo::ScanPoint> raw, bool keep_edge_pieces) {
  PrepareReport r;
  r.raw_points = raw.size();
  part_.clear();
  grid_.clear();
  if (raw.empty()) return r;
  double x0 = std::numeric_limits<double>::infinity(), x1 = -std::numeric_limits<double>::infinity();
  double y1 = -std::numeric_limits<double>::infinity();
  for (const algo::ScanPoint& p : raw) {
    (void)part_.push(p);  // a scan beyond capacity keeps what fits
    if (std::isfinite(p.x) && std::isfinite(p.y)) {
      x0 = std::min(x0, static_cast<double>(p.x));
      x1 = std::max(x1, static_cast<double>(p.x));
      y1 = std::max(y1, static_cast<double>(p.y));
    }
  }
  r.support_points = algo::remove_support(part_, support_, support_threshold_m_);
  const algo::IsolationReport isolated = isolator_.isolate(part_, x0, x1, keep_edge_pieces);
  r.stray_points = isolated.dropped_points;
  r.stray_pieces = isolated.dropped_pieces;
  r.edge_pieces = isolated.edge_pieces;
  r.hanger_points = isolator_.remove_hanger(part_, y1).removed_points;
  const algo::GhostReport ghosts = isolator_.drop_ghosts(part_);
  r.stray_points += ghosts.removed_points;
  r.stray_pieces += ghosts.pieces;
  r.part_points = part_.size();
  if (part_.size() == 0) {
    r.status = PrepareStatus::kNoPart;
    return r;
  }
  return describe_part(r);
}

PrepareReport ScanPreparer::prepare_part(std::span<const algo::ScanPoint> part) {
  PrepareReport r;
  r.raw_points = part.size();
  part_.clear();
  grid_.clear();
  for (const algo::ScanPoint& p : part) (void)part_.push(p);
  r.part_points = part_.size();
  if (part_.size() == 0) {
    r.status = PrepareStatus::kNoPart;
    return r;
  }
  return describe_part(r);
}

PrepareReport ScanPreparer::describe_part(PrepareReport r) {
  const algo::GridSpec& spec = grid_.spec();
  for (const algo::ScanPoint& p : part_.points()) {  // the part as it hangs must fit the grid
    int ix = 0, iy = 0, iz = 0;
    r.outside_points += spec.cell_of({p.x, p.y, p.z}, ix, iy, iz) ? 0 : 1;
  }
  if (static_cast<double>(r.outside_points) > kMaxOutsideFraction * static_cast<double>(part_.size())) {
    r.status = PrepareStatus::kOutsideGrid;
    return r;
  }
  if (part_.size() - r.outside_points < kMinPartPoints) {
    r.status = PrepareStatus::kTooFewPoints;
    return r;
  }
  if (algo::canonicalise(part_.points(), spec, canonical_params_, canonical_scratch_, canonical_, canonical_pose_) !=
      algo::CanonicalStatus::kOk) {
    r.status = PrepareStatus::kNoPart;
    return r;
  }
  (void)grid_.accumulate(canonical_points());  // a corner turned out of the grid is not the part's fault
  grid_.depth_image(depth_);
  if (extractor_.compute(depth_, features_) != algo::FeatureStatus::kOk) {
    r.status = PrepareStatus::kNoPart;
    return r;
  }
  r.status = PrepareStatus::kOk;
  return r;
}

algo::PerfectMatchParams perfect_match_params(const Config& config) {
  return config.pm;
}

algo::CascadeParams cascade_params(const Config& config) {
  return config.cascade;
}

algo::TemplateThresholds template_thresholds(const formats::PartThresholds& p) {
  algo::TemplateThresholds t;
  t.max_error = p.max_error;
  t.max_missing_area_m2 = p.max_missing_area_m2;
  t.max_extra_area_m2 = p.max_extra_area_m2;
  t.max_uncovered = p.max_uncovered;
  t.max_outliers = p.max_outliers;
  t.max_hole_pattern_m2 = p.max_hole_pattern_m2;
  t.size_centre_x_m = p.size_centre_x_m;
  t.size_centre_y_m = p.size_centre_y_m;
  t.max_size_dev_x_m = p.max_size_dev_x_m;
  t.max_size_dev_y_m = p.max_size_dev_y_m;
  t.max_size_dev_m = p.max_size_dev_m;
  t.edge_centre_m = p.edge_centre_m;
  t.max_edge_dev_m = p.max_edge_dev_m;
  t.size_gain_x_m = p.size_gain_x_m;
  t.size_gain_y_m = p.size_gain_y_m;
  t.edge_gain_m = p.edge_gain_m;
  t.edge_median_m = p.edge_median_m;
  t.max_edge_dev_median_m = p.max_edge_dev_median_m;
  return t;
}

formats::PartThresholds part_thresholds(const algo::TemplateThresholds& t, bool learnt) {
  formats::PartThresholds p;
  p.learnt = learnt;
  p.max_error = t.max_error;
  p.max_missing_area_m2 = t.max_missing_area_m2;
  p.max_extra_area_m2 = t.max_extra_area_m2;
  p.max_uncovered = t.max_uncovered;
  p.max_outliers = t.max_outliers;
  p.max_hole_pattern_m2 = t.max_hole_pattern_m2;
  p.size_centre_x_m = t.size_centre_x_m;
  p.size_centre_y_m = t.size_centre_y_m;
  p.max_size_dev_x_m = t.max_size_dev_x_m;
  p.max_size_dev_y_m = t.max_size_dev_y_m;
  p.max_size_dev_m = t.max_size_dev_m;
  p.edge_centre_m = t.edge_centre_m;
  p.max_edge_dev_m = t.max_edge_dev_m;
  p.size_gain_x_m = t.size_gain_x_m;
  p.size_gain_y_m = t.size_gain_y_m;
  p.edge_gain_m = t.edge_gain_m;
  p.edge_median_m = t.edge_median_m;
  p.max_edge_dev_median_m = t.max_edge_dev_median_m;
  return p;
}

LoadedTemplates open_templates(const Config& config, const ModelDb& db) {
  LoadedTemplates out;
  const algo::GridSpec grid = grid_spec(config);
  const formats::Manifest& m = db.manifest();
  out.files.reserve(m.parts.size());  // the models borrow from the files: no reallocation after the first
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    const formats::PartEntry& p = m.parts[c];
    algo::TemplateModel model;
    model.class_index = static_cast<int>(c);
    model.part_id = p.id;
    model.thresholds = template_thresholds(p.thresholds);
    auto file = formats::TemplateFile::open(db.path_of(p.template_file), grid);
    if (!file) {
      out.problems.push_back("part '" + p.name + "' disabled: " + file.error().message);
      out.files.emplace_back(std::nullopt);
    } else {
      out.files.emplace_back(std::move(*file));
      const formats::TemplateFile& t = *out.files.back();
      model.map = t.view();
      model.centroid_m = t.centroid_m();
      model.centroid_z_m = t.centroid_z_m();
      model.surface_cells = t.surface_cells();
    }
    out.models.push_back(model);
  }
  // Look-alikes by class index (names of parts no longer in the database are dropped); the spans are taken once the
  // vectors are complete.
  out.confusable.resize(m.parts.size());
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    for (const std::string& name : m.parts[c].confusable) {
      for (std::size_t o = 0; o < m.parts.size(); ++o) {
        if (o != c && m.parts[o].name == name) out.confusable[c].push_back(static_cast<int>(o));
      }
    }
    out.models[c].confusable = out.confusable[c];
  }
  return out;
}

Expected<algo::SvmModel> load_svm(const ModelDb& db) {
  const formats::Manifest& m = db.manifest();
  const std::string svm_path = db.path_of(m.svm.file);
  auto blob = base::read_file(svm_path, kMaxSvmModelBytes);
  if (!blob) return blob.error();
  if (base::crc32(*blob) != m.svm.crc32) {
    return make_error(svm_path +
                      ": checksum differs from the manifest: the model was changed or damaged; run "
                      "'cellsight train' again");
  }
  auto svm = algo::SvmModel::deserialize(*blob);
  if (!svm) return make_error(svm_path + ": " + svm.error().message + "; run 'cellsight train' again");
  if (svm->classes().size() != m.parts.size()) {
    return make_error(svm_path + ": the model knows " + std::to_string(svm->classes().size()) +
                      " parts, the manifest " + std::to_string(m.parts.size()) + "; run 'cellsight train'");
  }
  for (std::size_t c = 0; c < m.parts.size(); ++c) {
    const formats::PartEntry& p = m.parts[c];
    if (svm->classes()[c].name != p.name || svm->classes()[c].id != p.id) {
      return make_error(svm_path + ": class " + std::to_string(c) + " is '" + svm->classes()[c].name +
                        "' in the model, '" + p.name + "' in the manifest; run 'cellsight train'");
    }
  }
  return svm;
}

ModelFootprint model_footprint(const ModelDb& db) {
  ModelFootprint f;
  for (const formats::PartEntry& p : db.manifest().parts) {
    auto info = formats::read_template_info(db.path_of(p.template_file));
    if (!info) continue;
    ++f.templates;
    f.template_bytes += info->file_bytes;
    f.largest_template_bytes = std::max(f.largest_template_bytes, info->file_bytes);
  }
  if (db.manifest().svm.present) {
    std::error_code ec;
    const std::uintmax_t size = std::filesystem::file_size(db.path_of(db.manifest().svm.file), ec);
    if (!ec) f.svm_bytes = size;
  }
  return f;
}

Status check_model_budget(const Config& config, const ModelDb& db, const ModelFootprint& footprint) {
  constexpr std::uint64_t kBytesPerMb = 1000000;  // as parts list and the file sizes print them
  const auto budget = static_cast<std::uint64_t>(config.runtime.model_memory_mb) * kBytesPerMb;
  if (footprint.total_bytes() <= budget) return {};
  const auto mb = [&](std::uint64_t bytes) {
    char text[32];
    std::snprintf(text, sizeof text, "%.1f MB", static_cast<double>(bytes) / static_cast<double>(kBytesPerMb));
    return std::string(text);
  };
  const auto ram =
      static_cast<std::uint64_t>(::sysconf(_SC_PHYS_PAGES)) * static_cast<std::uint64_t>(::sysconf(_SC_PAGESIZE));
  return make_error("model database " + db.dir() + " needs " + mb(footprint.total_bytes()) + " (" +
                    std::to_string(footprint.templates) + " templates, " + mb(footprint.template_bytes) +
                    ", the largest " + mb(footprint.largest_template_bytes) + "; SVM " + mb(footprint.svm_bytes) +
                    "), more than runtime.model_memory_mb: " + std::to_string(config.runtime.model_memory_mb) + " in " +
                    config.source + ": raise it (this machine has " + mb(ram) +
                    " of RAM) or delete parts ('cellsight parts delete NAME')");
}

Expected<LoadedModels> load_models(const Config& config, const ModelDb& db) {
  const formats::Manifest& m = db.manifest();
  if (const std::string stale = db.svm_stale_reason(); !stale.empty()) {
    return make_error("model database " + db.dir() + ": " + stale);
  }
  if (Status fits = check_model_budget(config, db, model_footprint(db)); !fits) return fits.error();
  LoadedModels out;
  auto svm = load_svm(db);
  if (!svm) return svm.error();
  out.svm = std::move(*svm);
  for (const formats::PartEntry& p : m.parts) out.class_names.push_back(p.name);
  out.templates = open_templates(config, db);
  return out;
}

namespace {

// The production recogniser: everything sized here, recognise() allocates nothing.
class ModelRecogniser final : public runtime::Recogniser {
 public:
  ModelRecogniser(const Config& config, const algo::Plane& support, LoadedModels models, RecogniserMode mode)
      : preparer_(config, support, scan_builder_params_max_points(config)),
        models_(std::move(models)),
        cascade_(mode_params(config, mode, models_.class_names.size()), perfect_match_params(config),
                 grid_spec(config)),
        mode_(mode) {}

  algo::Decision recognise(std::span<const algo::ScanPoint> points,
                           std::chrono::steady_clock::time_point deadline) override {
    using Clock = std::chrono::steady_clock;
    const auto ms_since = [](Clock::time_point t) {
      return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
    };
    const Clock::time_point t0 = Clock::now();
    algo::Decision d;
    const PrepareReport r = preparer_.prepare(points);
    d.features_ms = ms_since(t0);
    if (r.status != PrepareStatus::kOk) {
      d.source = r.status == PrepareStatus::kNoPart || r.status == PrepareStatus::kEmpty
                     ? algo::DecisionSource::kNoPart
                     : algo::DecisionSource::kBadScan;
      d.total_ms = ms_since(t0);
      return d;
    }
    const Clock::time_point t1 = Clock::now();
    const std::span<const algo::ClassProbability> probabilities = models_.svm.predict(preparer_.features());
    const double svm_ms = ms_since(t1);
    if (Clock::now() >= deadline) {
      d.source = algo::DecisionSource::kTimeout;
    } else if (mode_ == RecogniserMode::kSvmOnly) {
      if (!probabilities.empty()) {
        d.source = algo::DecisionSource::kSvm;
        d.class_index = probabilities[0].class_index;
        d.part_id = models_.svm.classes()[static_cast<std::size_t>(d.class_index)].id;
        d.probability = probabilities[0].probability;
        if (probabilities.size() > 1) d.second_class_index = probabilities[1].class_index;
      }
    } else {
      d = cascade_.decide(probabilities, models_.templates.models, preparer_.part_points(), deadline, t0);
      if (d.class_index < 0 && r.edge_pieces > 0 && Clock::now() < deadline) d = second_look(points, d, deadline, t0);
    }
    d.features_ms = std::chrono::duration<double, std::milli>(t1 - t0).count();
    d.svm_ms = svm_ms;
    d.total_ms = ms_since(t0);
    return d;
  }

  std::string_view class_name(int class_index) const override {
    if (class_index < 0 || static_cast<std::size_t>(class_index) >= models_.class_names.size()) return {};
    return models_.class_names[static_cast<std::size_t>(class_index)];
  }

 private:
  // A large piece at the field's end was dropped as a neighbour's part and no candidate passed. A glare band near the
  // part's end cuts off a strip that looks just like that (issue 10), so the scan is decided once more with the
  // piece kept; its answer counts only when a candidate passes. A neighbour's part kept adds material no template
  // has (the two-way check rejects it), so this never turns a neighbour into an id. Allocation-free like the first.
  // It shares the first look's verification budget (`began`): at least its first candidate is verified.
  algo::Decision second_look(std::span<const algo::ScanPoint> points, const algo::Decision& first,
                             std::chrono::steady_clock::time_point deadline,
                             std::chrono::steady_clock::time_point began) {
    if (preparer_.prepare(points, true).status != PrepareStatus::kOk) return first;
    const std::span<const algo::ClassProbability> probabilities = models_.svm.predict(preparer_.features());
    const algo::Decision d =
        cascade_.decide(probabilities, models_.templates.models, preparer_.part_points(), deadline, began);
    return d.class_index >= 0 ? d : first;
  }

  static std::size_t scan_builder_params_max_points(const Config& config) {
    return scan_builder_params(config).max_points;
  }
  // --pm-only: the SVM never decides alone and Perfect Match tries every class.
  static algo::CascadeParams mode_params(const Config& config, RecogniserMode mode, std::size_t classes) {
    algo::CascadeParams p = cascade_params(config);
    if (mode == RecogniserMode::kPmOnly) {
      constexpr double kNoBudgetMs = 1e9;  // debugging: every class, whatever it costs
      p.accept_p1 = 2.0;
      p.pm_candidates = static_cast<int>(std::max<std::size_t>(1, classes));
      p.stop_ratio = 1e-12;  // every candidate the SVM gives any probability
      p.verify_budget_ms = kNoBudgetMs;
      p.search_budget_ms = kNoBudgetMs;
    }
    return p;
  }

  ScanPreparer preparer_;
  LoadedModels models_;
  algo::Cascade cascade_;
  RecogniserMode mode_;
};

}  // namespace

Expected<algo::Plane> load_support_plane(const std::string& calibration_path) {
  auto record = formats::load_calibration(calibration_path);
  if (!record)
    return make_error(record.error().message + "\n(run scripts/calibrate.sh, or cellsight calibrate, first)");
  if (!record->has_support) {
    return make_error(calibration_path +
                      ": no support section: scan the empty carrier and run 'cellsight calibrate support' first");
  }
  return record->support;
}

Expected<std::unique_ptr<runtime::Recogniser>> make_recogniser(const Config& config, const std::string& models_dir,
                                                               const std::string& calibration_path,
                                                               RecogniserMode mode) {
  auto record = formats::load_calibration(calibration_path);
  if (!record)
    return make_error(record.error().message + "\n(run scripts/calibrate.sh, or cellsight calibrate, first)");
  if (!record->has_support) {
    return make_error(calibration_path + ": no support section: run 'cellsight calibrate support' first");
  }
  auto db = ModelDb::open(models_dir, grid_spec(config), false);
  if (!db) return db.error();
  auto models = load_models(config, *db);
  if (!models) return models.error();
  for (const std::string& p : models->templates.problems) CS_LOG_ERROR("models", "%s", p.c_str());
  return std::unique_ptr<runtime::Recogniser>(
      std::make_unique<ModelRecogniser>(config, record->support, std::move(*models), mode));
}

}  // namespace cellsight::app
