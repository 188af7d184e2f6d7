// `cellsight teach --part NAME [--id N] (--sim --count K [--seed S] | SCAN.ply...)`: stores scans of a part type and
// builds its template; and the template builder `parts rebuild` shares with it.
#pragma once

#include <string>
#include <vector>

#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "formats/template_file.hpp"

namespace cellsight::cli {

[[nodiscard]] int run_teach(const std::vector<std::string>& args, const app::Config& config,
                            const std::string& models_dir);

// A part's template built again from its stored scans as teach builds one: from the scan the manifest names as its
// template scan (so poses keep their reference), completed from all its other stored scans where at least half of
// them agree (consensus; from 4 scans on). For templates of an older format, or after the builder changed.
[[nodiscard]] Expected<formats::TemplateModel> rebuild_template(const app::Config& config, app::ScanPreparer& preparer,
                                                                const app::ModelDb& db, const formats::PartEntry& part);

}  // namespace cellsight::cli
