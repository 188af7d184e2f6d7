// The Parts and Debug pages' API (issue 14): the model database read in place (app/'s ModelDb, as `parts list` reads
// it), the templates as pictures, and the long actions (delete, retrain, debug classify) as child `cellsight`
// commands through the JobRunner. Nothing the browser sends becomes a path: parts are named by validated part names,
// stored scans by review ids or a part's scan number, and the paths are made here.
//   GET  /api/parts                      the parts, their templates' sizes, learnt thresholds, the SVM's state
//   GET  /api/parts/NAME/template.png    the template's depth image (colour = depth, transparent where empty)
//   GET  /api/parts/NAME/points.json     its surface cells, decimated, in mm about the centroid (the 3D view)
//   POST /api/parts/delete {name}        maintenance: job `parts delete NAME`
//   POST /api/retrain {}                 maintenance: job `train --progress --report <models>/reports/train-<time>`
//   GET  /api/job                        the running or last job (JobView)
//   POST /api/job/cancel                 maintenance
//   GET  /api/debug/scans                the stored scans the debug page may classify
//   POST /api/debug {mode, files}        maintenance: job `classify --json [--svm-only|--pm-only] FILES`
// A job route answers 409 while another job runs.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "algo/grid.hpp"
#include "hmi/jobs.hpp"
#include "hmi/routes.hpp"

namespace cellsight::hmi {

struct PartsApiParams {
  std::string models_dir;
  algo::GridSpec grid{};  // the configuration's (app::grid_spec): a template for another grid is refused
  // Called on the job runner's thread after a delete or a training that succeeded, so that the running loop loads
  // the changed database (`run` decides when).
  std::function<void()> models_changed;
};

// Stored scans the debug page may name: "<models>/review/ID/scan.ply" (the review ring) for ID of 1..12 digits.
inline constexpr std::size_t kMaxReviewIdDigits = 12;
inline constexpr std::size_t kMaxDebugFiles = 50;    // scans per debug job
inline constexpr std::size_t kMaxPointsJson = 6000;  // points of /points.json

// The routes; `jobs` is borrowed and outlives the server.
[[nodiscard]] std::vector<Route> parts_routes(JobRunner& jobs, PartsApiParams params);

// "<models>/review/ID/scan.ply" when `ref` is a review id, "" otherwise (exposed for tests).
[[nodiscard]] std::string review_scan_path(const std::string& models_dir, const std::string& ref);

}  // namespace cellsight::hmi
