// `cellsight train [--report DIR] [--compare] [--progress]`: features of every taught scan, simulated-annealing feature
// selection with k-fold CV, the probability SVM, acceptance thresholds per template; written atomically into the
// model database.
#pragma once

#include <atomic>
#include <string>
#include <vector>

#include "algo/cascade.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"
#include "algo/training.hpp"
#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/train_progress.hpp"

namespace cellsight::cli {

// Reads a taught scan: checksum against the manifest, then the PLY parser.
[[nodiscard]] Expected<std::vector<algo::ScanPoint>> load_taught_scan(const app::ModelDb& db,
                                                                      const formats::ScanEntry& scan);

struct TaughtData {
  algo::Dataset data;
  std::vector<std::vector<algo::MatchReport>> own_matches;  // per class: its scans against its own template
};

// Features of every taught scan, one class per part in manifest order (class index = position). Runs on
// `threads` threads; any bad scan (checksum, empty, no part, outside the grid) stops it with an error naming
// the file.
// With `templates`, every scan is also matched against its own template (for the acceptance thresholds). With
// `progress`, each scan done is reported to it.
[[nodiscard]] Expected<TaughtData> build_dataset(const app::Config& config, const app::ModelDb& db,
                                                 const algo::Plane& support, int threads, const std::atomic<bool>* stop,
                                                 const app::LoadedTemplates* templates,
                                                 app::ProgressLines* progress = nullptr);

[[nodiscard]] int run_train(const std::vector<std::string>& args, const app::Config& config,
                            const std::string& models_dir);

}  // namespace cellsight::cli
