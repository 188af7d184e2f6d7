// The labelled scan sets of `cellsight eval`: DIR/truth.csv (the true pose of each scan relative to its part's
// template) and, with --sim, the set generated on the simulated cell.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "algo/perfect_match.hpp"
#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/scan_acquisition.hpp"
#include "base/result.hpp"

namespace cellsight::cli {

// A scan's true pose relative to its template (DESIGN.md "Pose"); z, rx, ry NaN when truth.csv has only x, y, theta.
using TruthPose = algo::FullPose;

// DIR/truth.csv: file,x_m,y_m,theta_deg[,z_m,rx_deg,ry_deg] (file relative to DIR); '#' comments and a header line
// allowed. No file: an empty map.
[[nodiscard]] Expected<std::map<std::string, TruthPose>> read_truth(const std::string& dir);

// eval --sim: K simulated passes of each listed part (seeds S..S+K-1) written as DIR/<part>/sSEED.ply with
// DIR/truth.csv; passes of taught parts get their pose relative to the template (whose seed the manifest records).
// With `perturb` every pass is perturbed before it is written (the truth stays the simulator's).
[[nodiscard]] Status generate_sim_scans(const app::Config& config, const app::ModelDb& db,
                                        const std::vector<std::string>& parts, int count, std::uint64_t first_seed,
                                        const std::string& calibration_path, const std::string& dir,
                                        const app::PassPerturbation* perturb);

}  // namespace cellsight::cli
