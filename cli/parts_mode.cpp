// `cellsight parts`: list (every file checked as loading checks it, template sizes), show, delete, rebuild, export.
#include "cli/parts_mode.hpp"

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <filesystem>

#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "base/atomic_file.hpp"
#include "cli/cli.hpp"
#include "cli/mode_args.hpp"
#include "cli/teach_mode.hpp"
#include "cli/train_mode.hpp"
#include "formats/ply.hpp"
#include "formats/template_file.hpp"

namespace cellsight::cli {
namespace {

constexpr double kBytesPerMb = 1e6;

int fail(int code, const std::string& message) {
  std::fprintf(stderr, "cellsight: %s\n", message.c_str());
  return code;
}

constexpr const char* kListHeader = "%-24s %6s %6s %7s  %-5s %8s  %s\n";

void print_part(const app::ModelDb& db, const formats::PartEntry& p, bool detail) {
  auto info = formats::read_template_info(db.path_of(p.template_file));
  char size[16] = "-";
  if (info) std::snprintf(size, sizeof size, "%.1f MB", static_cast<double>(info->file_bytes) / kBytesPerMb);
  std::printf("%-24s %6d %6zu %7zu  %-5s %8s  %s\n", p.name.c_str(), p.id, p.scans.size(), p.flagged.size(),
              p.thresholds.learnt ? "yes" : "no", size, p.taught_at.c_str());
  if (!detail) return;
  if (info) {
    std::printf(
        "  template     %s (%.1f MB, %llu occupied cells, %llu of %llu bricks, centroid x %.1f mm y %.1f mm)\n",
        p.template_file.c_str(), static_cast<double>(info->file_bytes) / kBytesPerMb,
        static_cast<unsigned long long>(info->occupied_cells), static_cast<unsigned long long>(info->stored_bricks),
        static_cast<unsigned long long>(info->brick_count), info->centroid_m.x() * 1e3, info->centroid_m.y() * 1e3);
  } else {
    std::printf("  template     %s: %s\n", p.template_file.c_str(), info.error().message.c_str());
  }
  if (const formats::ScanEntry* t = p.template_scan_entry()) {
    std::printf("  built from   %s (%s): poses are relative to this pass\n", t->file.c_str(), t->source.c_str());
  }
  if (!p.confusable.empty()) {
    std::string list;
    for (const std::string& c : p.confusable) list += (list.empty() ? "" : ", ") + c;
    std::printf("  look-alikes  %s (verified with it)\n", list.c_str());
  }
  if (p.thresholds.learnt) {
    std::printf(
        "  accepts      PM error <= %.3g, missing <= %.0f mm2 (%.2f %% in all), extra <= %.0f mm2 (%.2f %% in all)\n",
        p.thresholds.max_error, p.thresholds.max_missing_area_m2 * 1e6, p.thresholds.max_uncovered * 100.0,
        p.thresholds.max_extra_area_m2 * 1e6, p.thresholds.max_outliers * 100.0);
    std::printf("  hole pattern <= %.0f mm2 of holes where the other surface is solid\n",
                p.thresholds.max_hole_pattern_m2 * 1e6);
    std::printf("  size         width and height within %.1f mm of its own scans'\n",
                p.thresholds.max_size_dev_m * 1e3);
  }
  for (const formats::ScanEntry& s : p.scans) {
    const bool flagged = std::find(p.flagged.begin(), p.flagged.end(), s.file) != p.flagged.end();
    std::printf("  scan         %s  (%s)%s\n", s.file.c_str(), s.source.c_str(),
                flagged ? "  FLAGGED: disagrees with the others, left out of the thresholds" : "");
  }
}

// Every file is checked as loading it checks it (a template's header and body checksums, the SVM's checksum, model
// and classes), so a damaged one shows here and not first in classify.
int list_parts(const app::ModelDb& db, const app::Config& config) {
  int damaged = 0;
  std::printf(kListHeader, "part", "id", "scans", "flagged", "thr", "template", "taught");
  for (const formats::PartEntry& p : db.manifest().parts) {
    print_part(db, p, false);
    if (auto t = formats::TemplateFile::open(db.path_of(p.template_file), app::grid_spec(config)); !t) {
      std::printf("  DAMAGED template %s: %s; classify disables this part\n", p.template_file.c_str(),
                  t.error().message.c_str());
      ++damaged;
    }
  }
  // What run will hold in memory, against the budget it refuses to start beyond.
  const app::ModelFootprint f = app::model_footprint(db);
  const double budget_mb = config.runtime.model_memory_mb;
  const double need_mb = static_cast<double>(f.total_bytes()) / kBytesPerMb;
  std::printf("memory: %.1f MB of runtime.model_memory_mb %.0f MB (%.0f %%): %zu templates %.1f MB, SVM %.1f MB%s\n",
              need_mb, budget_mb, 100.0 * need_mb / budget_mb, f.templates,
              static_cast<double>(f.template_bytes) / kBytesPerMb, static_cast<double>(f.svm_bytes) / kBytesPerMb,
              need_mb > budget_mb ? "; OVER BUDGET: run and classify refuse this database" : "");
  const std::string stale = db.svm_stale_reason();
  if (stale.empty()) {
    std::printf("SVM: trained %s, %.2f %% on %d test scans, %s\n", db.manifest().svm.trained_at.c_str(),
                db.manifest().svm.test_accuracy * 100.0, db.manifest().svm.test_scans, db.manifest().svm.hyper.c_str());
    if (auto svm = app::load_svm(db); !svm) {
      std::printf("SVM: DAMAGED: %s\n", svm.error().message.c_str());
      ++damaged;
    }
  } else {
    std::printf("SVM: stale: %s\n", stale.c_str());
  }
  if (damaged > 0) {
    std::fflush(stdout);  // the listing before the summary line on stderr
    const std::string files = damaged == 1 ? " damaged file" : " damaged files";
    return fail(kExitUsage,
                "parts list: " + std::to_string(damaged) + files + " in " + db.dir() + " (marked DAMAGED above)");
  }
  return kExitOk;
}

// `parts rebuild [NAME...]`: every part's (or the named parts') template built again from its stored scans and
// written atomically. The rebuilt parts' acceptance thresholds were learnt against the old maps, so they are marked
// unlearnt (the manifest is saved after each part) and `train` must run before classify or run accept them again.
int rebuild_parts(app::ModelDb& db, const app::Config& config, const ModeArgs& args) {
  const std::string* calibration_arg = args.value("--calibration");
  const std::string calibration_path = calibration_arg ? *calibration_arg : app::default_calibration_path(config);
  auto support = app::load_support_plane(calibration_path);
  if (!support) return fail(kExitUsage, "parts rebuild: " + support.error().message);
  std::vector<std::string> names(args.positional.begin() + 1, args.positional.end());
  for (const std::string& name : names) {
    if (db.find(name) == nullptr) return fail(kExitUsage, "parts: no part '" + name + "' in " + db.manifest_path());
  }
  if (names.empty()) {
    for (const formats::PartEntry& p : db.manifest().parts) names.push_back(p.name);
  }
  app::ScanPreparer preparer(config, *support, app::scan_builder_params(config).max_points);
  for (const std::string& name : names) {
    formats::PartEntry& p = *db.find(name);
    auto model = rebuild_template(config, preparer, db, p);
    if (!model) return fail(kExitFailure, "parts rebuild: " + name + ": " + model.error().message);
    formats::TemplateIdentity identity;
    identity.part_name = p.name;
    identity.plc_id = static_cast<std::uint32_t>(p.id);
    if (auto ok = formats::write_template(db.path_of(p.template_file), *model, identity); !ok) {
      return fail(kExitFailure, "parts rebuild: " + ok.error().message);
    }
    p.thresholds.learnt = false;
    if (auto ok = db.save(); !ok) return fail(kExitFailure, "parts rebuild: " + ok.error().message);
    auto info = formats::read_template_info(db.path_of(p.template_file));
    std::printf("%s: template %s rebuilt (%.1f MB)\n", name.c_str(), p.template_file.c_str(),
                info ? static_cast<double>(info->file_bytes) / kBytesPerMb : 0.0);
  }
  std::printf("%zu templates rebuilt; their acceptance thresholds must be learnt again: run 'cellsight train'\n",
              names.size());
  return kExitOk;
}

// `parts export NAME --out DIR`: every taught scan of the part as a binary PLY named after the stored file
// (scans/NAME/00001.cscan -> DIR/00001.ply), each checked against its manifest CRC first, so a scan set can leave the
// cell and be taught elsewhere (`teach --part NAME DIR/*.ply`). DIR is filled under a temporary name and renamed into
// place: an existing non-empty DIR is refused and a failure leaves no half-filled one.
int export_part(const app::ModelDb& db, const formats::PartEntry& part, const std::string& out_arg) {
  namespace fs = std::filesystem;
  std::string out = fs::path(out_arg).lexically_normal().string();  // "DIR/" names DIR, not an empty name inside it
  while (out.size() > 1 && out.back() == '/') out.pop_back();
  std::error_code ec;
  const fs::path parent = fs::absolute(out, ec).parent_path();
  if (!ec) fs::create_directories(parent, ec);
  if (ec) return fail(kExitUsage, "parts export: " + out + ": cannot create its parent folder: " + ec.message());
  auto staged = base::StagedDirectory::create(out);
  if (!staged) return fail(kExitUsage, "parts export: " + staged.error().message);
  for (const formats::ScanEntry& s : part.scans) {
    auto points = load_taught_scan(db, s);
    if (!points) return fail(kExitFailure, "parts export: " + points.error().message);
    const std::string name = fs::path(s.file).stem().string() + ".ply";
    if (auto ok = base::write_file_atomic(staged->path() + "/" + name, formats::write_ply_binary(*points)); !ok) {
      return fail(kExitFailure, "parts export: " + ok.error().message);
    }
  }
  if (auto ok = staged->commit(); !ok) return fail(kExitFailure, "parts export: " + ok.error().message);
  std::printf("%s: %zu scans written to %s as binary PLY\n", part.name.c_str(), part.scans.size(), out.c_str());
  return kExitOk;
}

}  // namespace

int run_parts(const std::vector<std::string>& words, const app::Config& config, const std::string& models_dir) {
  constexpr const char* kUsage = "parts needs list, show NAME, delete NAME, rebuild [NAME...] or export NAME --out DIR";
  ModeArgs args;
  std::string error;
  if (!parse_mode_args(words, {"--calibration", "--out"}, {}, args, error)) return fail(kExitUsage, "parts: " + error);
  if (args.positional.empty()) return fail(kExitUsage, kUsage);
  const std::string& action = args.positional.front();
  const bool writes = action == "delete" || action == "rebuild";
  auto db = writes ? app::ModelDb::open_for_writing(models_dir, app::grid_spec(config), false)
                   : app::ModelDb::open(models_dir, app::grid_spec(config), false);
  if (!db) return fail(kExitUsage, db.error().message);
  if (action == "list" && args.positional.size() == 1) return list_parts(*db, config);
  if (action == "rebuild") return rebuild_parts(*db, config, args);
  if (args.value("--out") != nullptr && action != "export") return fail(kExitUsage, "parts: --out is for export");
  if ((action == "show" || action == "delete" || action == "export") && args.positional.size() == 2) {
    const std::string& name = args.positional[1];
    const formats::PartEntry* p = db->find(name);
    if (p == nullptr) return fail(kExitUsage, "parts: no part '" + name + "' in " + db->manifest_path());
    if (action == "show") {
      print_part(*db, *p, true);
      return kExitOk;
    }
    if (action == "export") {
      const std::string* out = args.value("--out");
      if (out == nullptr) return fail(kExitUsage, "parts export needs --out DIR");
      return export_part(*db, *p, *out);
    }
    if (auto ok = db->delete_part(name); !ok) return fail(kExitFailure, "parts delete: " + ok.error().message);
    std::printf("deleted %s; the SVM is now stale: run 'cellsight train'\n", name.c_str());
    return kExitOk;
  }
  return fail(kExitUsage, kUsage);
}

}  // namespace cellsight::cli
