// `cellsight teach`: store scans of a part type and build its template.
#include "cli/teach_mode.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>

#include "algo/part_isolation.hpp"
#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "base/atomic_file.hpp"
#include "base/crc32.hpp"
#include "base/local_time.hpp"
#include "cli/cli.hpp"
#include "cli/mode_args.hpp"
#include "cli/perturb_mode.hpp"
#include "cli/train_mode.hpp"
#include "drivers/log.hpp"
#include "formats/calibration_file.hpp"
#include "formats/input_file.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "formats/template_file.hpp"

namespace cellsight::cli {
namespace {

constexpr std::int64_t kMaxPlcId = 65535;
constexpr int kMaxTeachCount = 10000;

struct TaughtScan {
  std::vector<algo::ScanPoint> points;
  std::string source;
  std::string stored;  // the file's bytes (formats/scan_file), once encode_for_storage has run
};

int fail(int code, const std::string& message) {
  std::fprintf(stderr, "cellsight: %s\n", message.c_str());
  return code;
}

std::string scan_file_name(const std::string& part, std::size_t index) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%05zu", index);
  return "scans/" + part + "/" + buf + std::string(app::kTaughtScanExtension);
}

// Acquires `count` passes of `part` on the simulated cell, seeds first_seed.., on all cores (each perturbed when
// `perturb` is given).
Expected<std::vector<TaughtScan>> acquire_sim_scans(const app::Config& config, const std::string& part, int count,
                                                    std::uint64_t first_seed, const std::string& calibration_path,
                                                    const app::PassPerturbation* perturb) {
  std::vector<TaughtScan> scans(static_cast<std::size_t>(count));
  auto ok = app::acquire_sim_passes(
      config, part, count, first_seed, calibration_path, "scanned",
      [&](int index, std::uint64_t seed, std::vector<algo::ScanPoint>&& points) -> Status {
        scans[static_cast<std::size_t>(index)] = {std::move(points), "sim seed " + std::to_string(seed), {}};
        return {};
      },
      perturb);
  if (!ok) return ok.error();
  return scans;
}

Expected<std::vector<TaughtScan>> import_scans(const std::vector<std::string>& files) {
  std::vector<TaughtScan> scans;
  for (const std::string& f : files) {
    auto points = formats::load_ply_file(f);
    if (!points) return points.error();
    scans.push_back({std::move(*points), std::filesystem::absolute(f).lexically_normal().string(), {}});
  }
  return scans;
}

// The cascade's view of a template being built (class 0: teach checks one part against itself).
algo::TemplateModel view_of(const formats::TemplateModel& model) {
  algo::TemplateModel view;
  view.class_index = 0;
  view.map = model.map.view();
  view.centroid_m = model.centroid_m;
  view.centroid_z_m = model.centroid_z_m;
  view.surface_cells = model.surface_cells;
  return view;
}

struct TemplateChoice {
  std::size_t index = 0;
  formats::TemplateModel model;
};

// Consensus template (issue 10: "built from the taught scans, not taken blindly from one"): the chosen scan keeps
// every point; where it has no solid material (its cells closed and then opened by 3 x 3, so the few points a glare
// band leaves do not count) and no margin cell of it (its own edges do not grow), the cell takes the other scans'
// points when at least half of the others have material in it. Each other scan is moved onto the chosen one
// by its Perfect Match / outline pose and levelled in depth as the two-way check does. Material that only a few
// scans show (a stray edge, a neighbour's part, a chain that swung in) stays out; glare, dropouts and the laser's
// shadows of that one pass are filled.
constexpr std::size_t kMinConsensusScans = 4;
struct Consensus {
  std::vector<algo::ScanPoint> points;
  std::size_t added_points = 0;
  std::size_t added_cells = 0;
};
Consensus consensus_points(const app::Config& config, app::ScanPreparer& preparer, algo::Cascade& cascade,
                           const std::vector<TaughtScan>& scans, const TemplateChoice& chosen) {
  const algo::GridSpec g = app::grid_spec(config);
  const auto nx = static_cast<std::size_t>(g.nx), ny = static_cast<std::size_t>(g.ny);
  const double inv = 1.0 / g.resolution_m;
  auto cell_of = [&](double x, double y, std::size_t& out) {
    const double fx = (x - g.origin_m.x()) * inv, fy = (y - g.origin_m.y()) * inv;
    if (!(fx >= 0.0 && fy >= 0.0 && fx < static_cast<double>(nx) && fy < static_cast<double>(ny))) return false;
    out = static_cast<std::size_t>(fy) * nx + static_cast<std::size_t>(fx);
    return true;
  };
  Consensus out;
  (void)preparer.prepare(scans[chosen.index].points);
  out.points.assign(preparer.part_points().begin(), preparer.part_points().end());
  // The chosen scan's solid cells (own 3: its occupancy closed, then opened, by 3 x 3) and the ring one cell around
  // them (own 1): the ring is not filled from the others at first, so the outline does not grow by their sub-cell
  // offsets.
  std::vector<std::uint8_t> occupied(nx * ny, 0);
  for (const algo::ScanPoint& p : out.points) {
    std::size_t c = 0;
    if (cell_of(p.x, p.y, c)) occupied[c] = 1;
  }
  const algo::CellBox raster{0, g.nx - 1, 0, g.ny - 1};
  std::vector<std::uint8_t> solid(nx * ny, 0), ring(nx * ny, 0), tmp(nx * ny, 0);
  algo::square_morphology(occupied, solid, tmp, g.nx, raster, 1, true);
  algo::square_morphology(solid, solid, tmp, g.nx, raster, 1, false);
  algo::square_morphology(solid, solid, tmp, g.nx, raster, 1, false);
  algo::square_morphology(solid, solid, tmp, g.nx, raster, 1, true);
  algo::square_morphology(solid, ring, tmp, g.nx, raster, 1, true);
  std::vector<std::uint8_t> own(nx * ny, 0);
  for (std::size_t c = 0; c < own.size(); ++c) own[c] = solid[c] != 0 ? 3 : ring[c];
  const algo::TemplateModel view = view_of(chosen.model);
  const Eigen::Vector2d c = chosen.model.centroid_m;
  std::vector<std::vector<algo::ScanPoint>> moved;
  std::vector<std::uint16_t> votes(nx * ny, 0);
  std::vector<std::uint32_t> last(nx * ny, UINT32_MAX);  // count each scan once per cell
  for (std::size_t j = 0; j < scans.size(); ++j) {
    if (j == chosen.index) continue;
    (void)preparer.prepare(scans[j].points);
    const algo::MatchReport r = cascade.evaluate_own(view, preparer.part_points());
    if (!std::isfinite(r.pm.error)) continue;
    // p_template = c + R(-theta)(p - c - t) (DESIGN.md's pose inverted); z less the check's depth plane.
    const double ct = std::cos(r.check_pose.theta_rad), st = std::sin(r.check_pose.theta_rad);
    std::vector<algo::ScanPoint> pts;
    pts.reserve(preparer.part_points().size());
    for (algo::ScanPoint p : preparer.part_points()) {
      const double dx = p.x - c.x() - r.check_pose.x_m, dy = p.y - c.y() - r.check_pose.y_m;
      const double x = c.x() + ct * dx + st * dy, y = c.y() - st * dx + ct * dy;
      const double dz = r.depth_offset_m + r.depth_slope_x * (x - c.x()) + r.depth_slope_y * (y - c.y());
      p.x = static_cast<float>(x);
      p.y = static_cast<float>(y);
      p.z = static_cast<float>(p.z - dz);
      std::size_t cell = 0;
      if (cell_of(x, y, cell) && last[cell] != j) {
        last[cell] = static_cast<std::uint32_t>(j);
        ++votes[cell];
      }
      pts.push_back(p);
    }
    moved.push_back(std::move(pts));
  }
  const auto quorum = static_cast<std::uint16_t>(std::max<std::size_t>(2, (moved.size() + 1) / 2));
  std::vector<std::uint8_t> counted(nx * ny, 0);  // 1: filled beyond the ring, 2: a seam cell of the ring
  // A ring cell next to a filled cell is the seam between the chosen scan's material and what the others filled
  // (a glare band's edge in the chosen scan): filled as well, or the template keeps a one-cell gap along each edge of
  // the band, which cuts a later scan's lost data into pieces that no longer look like a band.
  const auto beside_filled = [&](std::size_t cell) {
    const std::size_t cx = cell % nx, cy = cell / nx;
    for (std::size_t y = cy > 0 ? cy - 1 : 0; y <= std::min(cy + 1, ny - 1); ++y) {
      for (std::size_t x = cx > 0 ? cx - 1 : 0; x <= std::min(cx + 1, nx - 1); ++x) {
        if (counted[y * nx + x] == 1) return true;
      }
    }
    return false;
  };
  for (const std::uint8_t pass : {std::uint8_t{1}, std::uint8_t{2}}) {
    for (const auto& pts : moved) {
      for (const algo::ScanPoint& p : pts) {
        std::size_t cell = 0;
        if (!cell_of(p.x, p.y, cell) || votes[cell] < quorum) continue;
        const bool take = pass == 1 ? own[cell] == 0 : own[cell] == 1 && counted[cell] != 1 && beside_filled(cell);
        if (!take) continue;
        out.points.push_back(p);
        ++out.added_points;
        if (counted[cell] == 0) {
          counted[cell] = pass;
          ++out.added_cells;
        }
      }
    }
  }
  return out;
}

// Consensus: fills the chosen scan's gaps from the others (consensus_points) and rebuilds its template from the
// merged points. Returns the cells added (0: the template is as it was).
std::size_t complete_from_others(const app::Config& config, app::ScanPreparer& preparer, algo::Cascade& cascade,
                                 const std::vector<TaughtScan>& scans, TemplateChoice& chosen) {
  auto merged = consensus_points(config, preparer, cascade, scans, chosen);
  if (merged.added_points == 0) return 0;
  auto model = formats::build_template(merged.points, app::grid_spec(config));
  if (!model) return 0;
  std::printf(
      "template: completed from the other scans where at least half of them agree and it has none "
      "(%zu cells, %.0f mm2: glare, dropouts, shadows of that pass)\n",
      merged.added_cells,
      static_cast<double>(merged.added_cells) * config.grid.resolution_m * config.grid.resolution_m * 1e6);
  chosen.model = std::move(*model);
  return merged.added_cells;
}

// The template scan: candidates in order of how close their part's point count is to the median of the taught
// scans (a glare band or a cut-off part has fewer points), built and checked against the other scans (Perfect Match
// + the two-way check) until one leaves a median evidence within the cascade's area floor; else the best of the
// tried. Scans that disagree with the chosen one are named (the operator sees it at teach time). Teach time only:
// allocates a full template per try.
Expected<TemplateChoice> choose_template(const app::Config& config, app::ScanPreparer& preparer,
                                         const std::vector<TaughtScan>& scans) {
  constexpr int kMaxTries = 3;
  constexpr double kDisagreeFactor = 4.0;
  std::vector<std::size_t> counts(scans.size());
  for (std::size_t i = 0; i < scans.size(); ++i) {
    (void)preparer.prepare(scans[i].points);
    counts[i] = preparer.part_points().size();
  }
  std::vector<std::size_t> sorted = counts;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
  const auto median_count = static_cast<double>(sorted[sorted.size() / 2]);
  std::vector<std::size_t> order(scans.size());
  for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
    return std::abs(static_cast<double>(counts[a]) - median_count) <
           std::abs(static_cast<double>(counts[b]) - median_count);
  });
  const algo::CascadeParams cp = app::cascade_params(config);
  algo::Cascade cascade(cp, app::perfect_match_params(config), app::grid_spec(config));
  std::optional<TemplateChoice> best;
  double best_median = std::numeric_limits<double>::infinity();
  std::vector<double> best_evidence;
  std::string first_error;
  for (int t = 0; t < std::min<int>(kMaxTries, static_cast<int>(order.size())); ++t) {
    const std::size_t i = order[static_cast<std::size_t>(t)];
    (void)preparer.prepare(scans[i].points);
    auto model = formats::build_template(preparer.part_points(), app::grid_spec(config));
    if (!model) {
      if (first_error.empty()) first_error = scans[i].source + ": " + model.error().message;
      continue;
    }
    const algo::TemplateModel view = view_of(*model);
    std::vector<double> evidence(scans.size(), 0.0);
    std::vector<double> others;
    for (std::size_t j = 0; j < scans.size(); ++j) {
      if (j == i) continue;
      (void)preparer.prepare(scans[j].points);
      evidence[j] = cascade.evaluate_own(view, preparer.part_points()).evidence_m2;
      others.push_back(evidence[j]);
    }
    double median = 0.0;
    if (!others.empty()) {
      std::nth_element(others.begin(), others.begin() + static_cast<std::ptrdiff_t>(others.size() / 2), others.end());
      median = others[others.size() / 2];
    }
    if (median < best_median) {
      best_median = median;
      best_evidence = evidence;
      best = TemplateChoice{i, std::move(*model)};
    }
    if (median <= cp.area_floor_m2) break;
  }
  if (!best) return make_error(first_error.empty() ? std::string("no scan") : first_error);
  std::printf("template: %s (median evidence of the other %zu scans against it %.0f mm2)\n",
              scans[best->index].source.c_str(), scans.size() - 1, best_median * 1e6);
  if (scans.size() >= kMinConsensusScans && complete_from_others(config, preparer, cascade, scans, *best) > 0) {
    // Judge every scan against the completed template.
    const algo::TemplateModel view = view_of(best->model);
    std::vector<double> others;
    for (std::size_t j = 0; j < scans.size(); ++j) {
      (void)preparer.prepare(scans[j].points);
      best_evidence[j] = cascade.evaluate_own(view, preparer.part_points()).evidence_m2;
      if (j != best->index) others.push_back(best_evidence[j]);
    }
    std::nth_element(others.begin(), others.begin() + static_cast<std::ptrdiff_t>(others.size() / 2), others.end());
    best_median = others[others.size() / 2];
  }
  const double disagree = std::max(kDisagreeFactor * best_median, cp.area_floor_m2);
  for (std::size_t j = 0; j < scans.size(); ++j) {
    if (j != best->index && best_evidence[j] > disagree) {
      std::printf(
          "warning: %s disagrees with the other taught scans (%.0f mm2 of evidence against the template, "
          "typical %.0f mm2): glare, a stray part or the wrong part? It is stored; training does not let it "
          "widen the acceptance thresholds\n",
          scans[j].source.c_str(), best_evidence[j] * 1e6, best_median * 1e6);
    }
  }
  return std::move(*best);
}

// The words of `teach`: --part, and either --sim --count K or scan files. An error is a usage error.
struct TeachArgs {
  ModeArgs args;
  std::string part;
  bool sim = false;
  std::int64_t count = 0;
};

Expected<TeachArgs> parse_teach_args(const std::vector<std::string>& words) {
  TeachArgs t;
  std::string error;
  if (!parse_mode_args(words, {"--part", "--id", "--count", "--seed", "--calibration", "--perturb"}, {"--sim"}, t.args,
                       error)) {
    return make_error("teach: " + error);
  }
  const std::string* part = t.args.value("--part");
  if (part == nullptr) return make_error("teach needs --part NAME");
  if (!formats::valid_part_name(*part))
    return make_error("teach: part name '" + *part + "': use 1..64 letters, digits, '_' or '-'");
  t.part = *part;
  t.sim = t.args.has("--sim");
  if (t.sim == !t.args.positional.empty()) {
    return make_error("teach needs either --sim --count K or scan files (SCAN.ply ...), not both");
  }
  if (t.sim) {
    const std::string* c = t.args.value("--count");
    if (c == nullptr || !parse_whole(*c, 1, kMaxTeachCount, t.count)) {
      return make_error("teach --sim needs --count K (1.." + std::to_string(kMaxTeachCount) + ")");
    }
  } else if (t.args.value("--count") != nullptr || t.args.value("--seed") != nullptr ||
             t.args.value("--perturb") != nullptr) {
    return make_error("teach: --count, --seed and --perturb apply to --sim only");
  }
  return t;
}

// The part's PLC id: --id (unique in the database, and the part's own if it exists), its existing id, or one more
// than the largest so far.
Expected<std::int64_t> plc_id_for(const ModeArgs& args, const app::ModelDb& db, const std::string& part,
                                  const formats::PartEntry* existing) {
  std::int64_t id = 0;
  if (const std::string* v = args.value("--id")) {
    if (!parse_whole(*v, 1, kMaxPlcId, id)) return make_error("teach: --id '" + *v + "': expected 1..65535");
    if (existing != nullptr && existing->id != id) {
      return make_error("teach: part '" + part + "' already has PLC id " + std::to_string(existing->id) +
                        "; delete it first to change its id");
    }
    for (const formats::PartEntry& p : db.manifest().parts) {
      if (p.name != part && p.id == id) {
        return make_error("teach: PLC id " + std::to_string(id) + " belongs to part '" + p.name + "'");
      }
    }
    return id;
  }
  if (existing != nullptr) return static_cast<std::int64_t>(existing->id);
  for (const formats::PartEntry& p : db.manifest().parts) id = std::max<std::int64_t>(id, p.id);
  return id + 1;
}

// The scans to teach: simulated passes (seeds after the ones already taught, unless --seed) or the files given.
Expected<std::vector<TaughtScan>> gather_scans(const TeachArgs& t, const app::Config& config, std::int64_t id,
                                               std::size_t already, const std::string& calibration_path,
                                               const app::PassPerturbation* perturb) {
  if (!t.sim) return import_scans(t.args.positional);
  std::uint64_t first_seed = already + 1;
  if (const std::string* s = t.args.value("--seed")) {
    std::int64_t v = 0;
    if (!parse_whole(*s, 0, INT64_MAX, v)) return make_error("--seed '" + *s + "': expected a number");
    first_seed = static_cast<std::uint64_t>(v);
  }
  std::printf("teaching %s (PLC id %lld): %lld simulated passes, seeds %llu..%s%s\n", t.part.c_str(),
              static_cast<long long>(id), static_cast<long long>(t.count), static_cast<unsigned long long>(first_seed),
              perturb != nullptr ? ", perturbed: " : "", perturb != nullptr ? perturb->spec.text.c_str() : "");
  return acquire_sim_scans(config, t.part, static_cast<int>(t.count), first_seed, calibration_path, perturb);
}

// A new part: its entry and its template, built from the taught scan that agrees best with the others (issue 10:
// the first one may carry a glare band or a stray edge); poses are reported relative to it and `parts show` names
// it. Returns an exit code (kExitOk: go on); the template file is added to `written`.
int start_new_part(const app::Config& config, app::ModelDb& db, app::ScanPreparer& preparer,
                   const std::vector<TaughtScan>& scans, const std::string& part, std::int64_t id,
                   formats::PartEntry& entry, std::size_t& template_index, std::vector<std::string>& written) {
  entry.name = part;
  entry.id = static_cast<int>(id);
  entry.template_file = "templates/" + part + ".dmap";
  entry.taught_at = base::local_time_text();
  auto choice = choose_template(config, preparer, scans);
  if (!choice) return fail(kExitUsage, "teach: template of " + part + ": " + choice.error().message);
  template_index = choice->index;
  std::error_code ec;
  std::filesystem::create_directories(db.path_of("templates"), ec);
  formats::TemplateIdentity identity;
  identity.part_name = part;
  identity.plc_id = static_cast<std::uint32_t>(id);
  if (auto ok = formats::write_template(db.path_of(entry.template_file), choice->model, identity); !ok) {
    return fail(kExitFailure, "teach: " + ok.error().message);
  }
  written.push_back(entry.template_file);
  return kExitOk;
}

// Encodes every scan as it will be stored and takes the stored points back (coordinates on the 16 um steps): the
// template, the checks and a later `parts rebuild` or `train` then all see the same points. A scan that cannot be
// stored (a coordinate beyond +-34 km) is refused before anything is written.
Status encode_for_storage(std::vector<TaughtScan>& scans) {
  for (TaughtScan& s : scans) {
    auto bytes = formats::write_scan_file(s.points);
    if (!bytes) return make_error(s.source + ": " + bytes.error().message);
    auto points = formats::parse_scan_file(*bytes);
    if (!points) return make_error(s.source + ": " + points.error().message);  // a bug: what was just written
    s.points = std::move(*points);
    s.stored = std::move(*bytes);
  }
  return {};
}

// Writes the scans (formats/scan_file, atomically) and the manifest; on a failure removes every file this teach wrote.
int store_scans(app::ModelDb& db, const std::vector<TaughtScan>& scans, const std::string& part, std::size_t already,
                std::size_t template_index, formats::PartEntry& entry, formats::PartEntry* existing,
                std::vector<std::string>& written) {
  const auto undo = [&] {
    std::error_code ec;
    for (const std::string& f : written) std::filesystem::remove(db.path_of(f), ec);
  };
  std::error_code ec;
  std::filesystem::create_directories(db.path_of("scans/" + part), ec);
  if (ec) return fail(kExitFailure, "teach: cannot create " + db.path_of("scans/" + part) + ": " + ec.message());
  std::size_t index = already;
  for (const TaughtScan& s : scans) {
    std::string file;
    do {
      file = scan_file_name(part, ++index);
    } while (std::filesystem::exists(db.path_of(file)));
    if (auto ok = base::write_file_atomic(db.path_of(file), s.stored); !ok) {
      undo();
      return fail(kExitFailure, "teach: " + ok.error().message);
    }
    written.push_back(file);
    if (static_cast<std::size_t>(&s - scans.data()) == template_index) entry.template_scan = file;
    entry.scans.push_back({file, base::crc32(s.stored), s.source});
  }
  if (existing != nullptr) {
    *existing = entry;
  } else {
    db.manifest().parts.push_back(entry);
  }
  if (auto ok = db.save(); !ok) {
    undo();
    return fail(kExitFailure, "teach: " + ok.error().message + " (nothing was stored)");
  }
  return kExitOk;
}

}  // namespace

int run_teach(const std::vector<std::string>& words, const app::Config& config, const std::string& models_dir) {
  auto parsed = parse_teach_args(words);
  if (!parsed) return fail(kExitUsage, parsed.error().message);
  const TeachArgs& t = *parsed;
  auto db = app::ModelDb::open_for_writing(models_dir, app::grid_spec(config), true);
  if (!db) return fail(kExitUsage, db.error().message);
  formats::PartEntry* existing = db->find(t.part);
  auto id = plc_id_for(t.args, *db, t.part, existing);
  if (!id) return fail(kExitUsage, id.error().message);
  const std::string* calibration_arg = t.args.value("--calibration");
  const std::string calibration_path = calibration_arg ? *calibration_arg : app::default_calibration_path(config);
  auto support = app::load_support_plane(calibration_path);
  if (!support) return fail(kExitUsage, support.error().message);
  auto perturb = perturbation_option(t.args, config, calibration_path, app::kPerturbTeach);
  if (!perturb) return fail(kExitUsage, "teach: " + perturb.error().message);

  const std::size_t already = existing != nullptr ? existing->scans.size() : 0;
  auto scans = gather_scans(t, config, *id, already, calibration_path, *perturb ? &**perturb : nullptr);
  if (!scans) return fail(kExitUsage, "teach: " + scans.error().message);
  if (Status ok = encode_for_storage(*scans); !ok) {
    return fail(kExitUsage, "teach: " + ok.error().message + "; nothing was stored");
  }

  // Every scan must show a part that fits the grid before anything is written.
  app::ScanPreparer preparer(config, *support, app::scan_builder_params(config).max_points);
  for (const TaughtScan& s : *scans) {
    const app::PrepareReport r = preparer.prepare(s.points);
    if (r.status != app::PrepareStatus::kOk) {
      return fail(kExitUsage, "teach: " + s.source + ": " + std::string(to_string(r.status)) + " (" + r.describe() +
                                  "); nothing was stored");
    }
  }

  std::vector<std::string> written;
  formats::PartEntry entry = existing != nullptr ? *existing : formats::PartEntry{};
  std::size_t template_index = SIZE_MAX;  // of *scans, when this call builds the template
  if (existing == nullptr) {
    const int started = start_new_part(config, *db, preparer, *scans, t.part, *id, entry, template_index, written);
    if (started != kExitOk) return started;
  }
  if (const int stored = store_scans(*db, *scans, t.part, already, template_index, entry, existing, written);
      stored != kExitOk) {
    return stored;
  }
  std::printf("%s: %zu scans stored (%zu in all), template %s; the SVM is now stale: run 'cellsight train'\n",
              t.part.c_str(), scans->size(), entry.scans.size(), entry.template_file.c_str());
  return kExitOk;
}

Expected<formats::TemplateModel> rebuild_template(const app::Config& config, app::ScanPreparer& preparer,
                                                  const app::ModelDb& db, const formats::PartEntry& part) {
  const formats::ScanEntry* base = part.template_scan_entry();
  if (base == nullptr) return make_error("part '" + part.name + "' has no stored scans");
  std::vector<TaughtScan> scans;
  std::size_t index = 0;
  for (const formats::ScanEntry& s : part.scans) {
    auto points = load_taught_scan(db, s);
    if (!points) return points.error();
    if (&s == base) index = scans.size();
    scans.push_back({std::move(*points), db.path_of(s.file), {}});
  }
  const app::PrepareReport r = preparer.prepare(scans[index].points);
  if (r.status != app::PrepareStatus::kOk) {
    return make_error(scans[index].source + ": " + std::string(to_string(r.status)) + " (" + r.describe() + ")");
  }
  auto model = formats::build_template(preparer.part_points(), app::grid_spec(config));
  if (!model) return make_error(scans[index].source + ": " + model.error().message);
  TemplateChoice chosen{index, std::move(*model)};
  if (scans.size() >= kMinConsensusScans) {
    algo::Cascade cascade(app::cascade_params(config), app::perfect_match_params(config), app::grid_spec(config));
    (void)complete_from_others(config, preparer, cascade, scans, chosen);
  }
  return std::move(chosen.model);
}

}  // namespace cellsight::cli
