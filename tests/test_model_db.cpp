// The model database as the operator uses it, through the executable: teach (simulated and PLY import), parts,
// train, classify, eval; and bad input (clear error, exit code 2, nothing in the database overwritten).
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <catch2/catch.hpp>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "algo/cascade.hpp"
#include "app/config.hpp"
#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "base/crc32.hpp"
#include "drivers/sim/rig.hpp"
#include "formats/calibration_file.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "formats/template_file.hpp"
#include "sim_test_util.hpp"
#include "tests/scratch_dir.hpp"
#include "tests/small_cell.hpp"

namespace fs = std::filesystem;
using namespace cellsight;

using test::read_all;
using test::Run;
using test::SmallCell;

TEST_CASE("teach then train then classify a small database through the executable", "[cycle]") {
  const SmallCell cell = SmallCell::named("cycle");
  // Given three parts taught on the simulated cell, two of which differ by one hole only.
  for (const char* part : {"plate_4h", "plate_5h", "bracket_l"}) {
    const Run r = cell.run(std::string("teach --sim --part ") + part + " --count 6");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  Run list = cell.run("parts list");
  INFO(list.output);
  REQUIRE(list.exit_code == 0);
  CHECK(list.output.find("plate_5h") != std::string::npos);
  CHECK(list.output.find("stale") != std::string::npos);

  // A stale model is refused with what to run.
  const fs::path probe = cell.dir / "probe.ply";
  {
    const Run scan = cell.run("scan --sim --part plate_5h --seed 901 --calibration " +
                              (cell.dir / "calibration.yaml").string() + " --out " + probe.string());
    INFO(scan.output);
    REQUIRE(scan.exit_code == 0);
  }
  Run stale = cell.run("classify " + probe.string());
  CHECK(stale.exit_code == 2);
  CHECK(stale.output.find("cellsight train") != std::string::npos);

  // When trained.
  const Run train = cell.run("train --report " + (cell.dir / "report").string());
  INFO(train.output);
  REQUIRE(train.exit_code == 0);
  CHECK(fs::exists(cell.dir / "report" / "summary.txt"));
  auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(db.ok());
  CHECK(db->svm_stale_reason().empty());
  for (const auto& p : db->manifest().parts) CHECK(p.thresholds.learnt);

  // Then a new pass of a taught part (a seed never taught) is recognised, as JSON lines of DESIGN.md.
  const Run classify = cell.run("classify --json " + probe.string());
  INFO(classify.output);
  REQUIRE(classify.exit_code == 0);
  CHECK(classify.output.find("\"class\": \"plate_5h\"") != std::string::npos);
  CHECK(classify.output.find("\"pose\": {\"x\": ") != std::string::npos);
  // The full pose (issue 13): the keys of version 1 first, then z, rx_deg, ry_deg, and a sigma of each.
  CHECK(classify.output.find("\"theta_deg\": ") < classify.output.find("\"z\": "));
  CHECK(classify.output.find("\"rx_deg\": ") != std::string::npos);
  CHECK(classify.output.find("\"ry_deg\": ") != std::string::npos);
  CHECK(classify.output.find("\"sigma\": {\"x\": ") != std::string::npos);

  // A part never taught comes out unknown, never as a taught id.
  const fs::path stranger = cell.dir / "stranger.ply";
  REQUIRE(cell.run("scan --sim --part channel_u --seed 5 --calibration " + (cell.dir / "calibration.yaml").string() +
                   " --out " + stranger.string())
              .exit_code == 0);
  const Run unknown = cell.run("classify --json " + stranger.string());
  INFO(unknown.output);
  CHECK(unknown.output.find("\"class\": null") != std::string::npos);
  CHECK(unknown.output.find("\"pose\": null, \"sigma\": null") != std::string::npos);
  // Each verified candidate's size and edges, signed, added after the fields of issue 10's first version (none
  // renamed): millimetres, null where not measured.
  CHECK(unknown.output.find("\"edge_dev_mm\": ") < unknown.output.find("\"size_off_mm\": ["));
  CHECK(unknown.output.find("\"edge_off_mm\": {\"left\": ") != std::string::npos);
  CHECK(unknown.output.find("\"bottom\": ") < unknown.output.find("\"top\": "));

  // Limits learnt by a cellsight of another learn version (recorded in the manifest) are stale: classify refuses
  // until train learns them again (an older build's limits gave a newer one a wrong id on a 5 mm taller twin).
  {
    auto older = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
    REQUIRE(older.ok());
    CHECK(older->manifest().learn_version == algo::kLearnVersion);
    older->manifest().learn_version = 0;
    REQUIRE(static_cast<bool>(older->save()));
  }
  const Run old_limits = cell.run("classify " + probe.string());
  INFO(old_limits.output);
  CHECK(old_limits.exit_code == 2);
  CHECK(old_limits.output.find("learn version 0") != std::string::npos);
  CHECK(old_limits.output.find("cellsight train") != std::string::npos);
  REQUIRE(cell.run("train").exit_code == 0);
  CHECK(cell.run("classify " + probe.string()).exit_code == 0);

  // eval --sim: new passes (seeds never taught) of a taught and an untaught part, written as PLY files with the
  // truth of the taught one relative to its template, then evaluated from the files.
  const fs::path eval_dir = cell.dir / "eval";
  const Run eval = cell.run("eval --sim --count 2 --parts plate_5h,channel_u --scans " + eval_dir.string());
  INFO(eval.output);
  REQUIRE(eval.exit_code == 0);
  CHECK(fs::exists(eval_dir / "plate_5h" / "s100001.ply"));
  CHECK(fs::exists(eval_dir / "channel_u" / "s100002.ply"));
  const std::string truth_csv = read_all(eval_dir / "truth.csv");
  CHECK(truth_csv.rfind("file,x_m,y_m,theta_deg,z_m,rx_deg,ry_deg\nplate_5h/s100001.ply,", 0) == 0);
  CHECK(std::count(truth_csv.begin(), truth_csv.end(), '\n') == 3);  // header + the taught part's two passes
  CHECK(eval.output.find("(2 of taught parts, 2 of parts not taught)") != std::string::npos);
  CHECK(eval.output.find("not taught   2 of 2 came out unknown") != std::string::npos);
  CHECK(eval.output.find("wrong ids    0") != std::string::npos);
  // Poses against the composed truth: within two cells of this test's coarse 4.4 mm grid.
  const auto at = eval.output.find("pose xy");
  REQUIRE(at != std::string::npos);
  double mean_mm = -1, p95_mm = -1, max_mm = -1;
  REQUIRE(std::sscanf(eval.output.c_str() + at, "pose xy mean %lf p95 %lf max %lf", &mean_mm, &p95_mm, &max_mm) == 3);
  CHECK(max_mm >= 0.0);
  CHECK(max_mm <= 8.8);
  // Per axis: error and how often the truth lay within 1 and 2 sigma (the truth has all six axes).
  for (const char* axis : {"pose x ", "pose y ", "pose z ", "pose rx ", "pose ry ", "pose theta "}) {
    const auto line = eval.output.find(std::string(axis) + "  ");
    CHECK(line != std::string::npos);
  }
  CHECK(eval.output.find("within 1 sigma") != std::string::npos);
  // An existing non-empty folder is never overwritten.
  CHECK(cell.run("eval --sim --count 1 --parts plate_5h --scans " + eval_dir.string()).exit_code == 2);

  // A corrupt template disables its part only: the others keep working.
  const std::string manifest_before = read_all(cell.models + "/manifest.yaml");
  {
    std::fstream f(cell.models + "/templates/bracket_l.dmap", std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(100000);
    f.put('\x5a');
  }
  const Run damaged = cell.run("classify --json " + probe.string());
  INFO(damaged.output);
  CHECK(damaged.exit_code == 0);
  CHECK(damaged.output.find("bracket_l") != std::string::npos);  // reported
  CHECK(damaged.output.find("\"class\": \"plate_5h\"") != std::string::npos);

  // Bad input to train: a part with fewer scans than folds -> clear error, the database untouched.
  const Run few = cell.run("teach --sim --part tray --count 2");
  REQUIRE(few.exit_code == 0);
  const std::string manifest_taught = read_all(cell.models + "/manifest.yaml");
  const Run refused = cell.run("train");
  CHECK(refused.exit_code == 2);
  CHECK(refused.output.find("tray") != std::string::npos);
  CHECK(read_all(cell.models + "/manifest.yaml") == manifest_taught);
  CHECK(manifest_taught != manifest_before);

  // Deleting a part makes the model stale again.
  const Run del = cell.run("parts delete tray");
  CHECK(del.exit_code == 0);
  CHECK_FALSE(fs::exists(cell.models + "/scans/tray"));
}

// The operator's path for parts that exist only as scans (PLY files in DESIGN.md's carrier frame, carrier included,
// as `cellsight scan` writes them): carrier plane from an empty-carrier PLY, teach from PLY files under names the
// simulator's catalogue does not know, train, classify. Nothing here may look anything up in the catalogue.
TEST_CASE("parts taught from PLY files under their own names are recognised, nothing taken from the catalogue") {
  const SmallCell cell = SmallCell::named("ply");
  const std::string calibration = (cell.dir / "calibration.yaml").string();
  const auto scan = [&](const std::string& what, const fs::path& out) {
    const Run r = cell.run("scan --sim " + what + " --calibration " + calibration + " --out " + out.string());
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  };
  const fs::path empty = cell.dir / "empty.ply";
  scan("--empty", empty);
  {
    const Run r = cell.run("calibrate support --scan " + empty.string() + " --calibration " + calibration);
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  // The customer's names for two catalogue shapes.
  const std::vector<std::pair<std::string, std::string>> parts = {{"door_inner_7731", "plate_5h"},
                                                                  {"hinge_bracket_L2", "bracket_l"}};
  for (std::size_t k = 0; k < parts.size(); ++k) {
    std::string files;
    for (int seed = 1; seed <= 6; ++seed) {
      const fs::path f = cell.dir / (parts[k].first + "_" + std::to_string(seed) + ".ply");
      scan("--part " + parts[k].second + " --seed " + std::to_string(seed), f);
      files += " " + f.string();
    }
    const Run r = cell.run("teach --part " + parts[k].first + " --id " + std::to_string(40 + k) + files);
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  const Run train = cell.run("train --calibration " + calibration);
  INFO(train.output);
  REQUIRE(train.exit_code == 0);
  const fs::path probe = cell.dir / "probe.ply";
  scan("--part bracket_l --seed 77", probe);
  const Run classify = cell.run("classify --json --calibration " + calibration + " " + probe.string());
  INFO(classify.output);
  REQUIRE(classify.exit_code == 0);
  CHECK(classify.output.find("\"class\": \"hinge_bracket_L2\", \"id\": 41") != std::string::npos);
}

TEST_CASE("teach refuses bad scans and keeps the database as it was") {
  const SmallCell cell = SmallCell::named("bad");
  const fs::path empty = cell.dir / "empty.ply";
  std::ofstream(empty, std::ios::binary) << formats::write_ply_binary({});
  Run r = cell.run("teach --part empty_part --id 7 " + empty.string());
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("no point") != std::string::npos);
  CHECK_FALSE(fs::exists(cell.models + "/manifest.yaml"));

  // A part scanned far outside the grid (shifted 2 m): refused, nothing stored.
  std::vector<algo::ScanPoint> shifted;
  for (int i = 0; i < 4000; ++i) {
    shifted.push_back(
        {2.0F + 0.001F * static_cast<float>(i % 200), 0.3F + 0.001F * static_cast<float>(i / 200), 0.1F, 0, 0});
  }
  const fs::path outside = cell.dir / "outside.ply";
  std::ofstream(outside, std::ios::binary) << formats::write_ply_binary(shifted);
  r = cell.run("teach --part far_away " + outside.string());
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("does not fit the grid") != std::string::npos);
  CHECK_FALSE(fs::exists(cell.models + "/manifest.yaml"));

  // Not a PLY at all.
  const fs::path junk = cell.dir / "junk.ply";
  std::ofstream(junk) << "solid cube\n";
  r = cell.run("teach --part junk " + junk.string());
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("junk.ply") != std::string::npos);

  // Bad names and ids.
  CHECK(cell.run("teach --part 'a/b' --sim --count 1").exit_code == 2);
  CHECK(cell.run("teach --part ok --id 70000 --sim --count 1").exit_code == 2);
  // A missing database is a clear error naming what to run.
  r = cell.run("parts list");
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("cellsight teach") != std::string::npos);
}

namespace {

// Part "plate" (PLC id 3) with `scan_count` scan records whose checksums are 0x1234abcd, 0x1234abce, ...
formats::PartEntry plate_entry(int scan_count) {
  formats::PartEntry p;
  p.name = "plate";
  p.id = 3;
  p.template_file = "templates/plate.dmap";
  for (int i = 1; i <= scan_count; ++i) {
    char path[32];
    std::snprintf(path, sizeof path, "scans/plate/%05d.ply", i);
    p.scans.push_back({path, 0x1234abccU + static_cast<std::uint32_t>(i), "test"});
  }
  return p;
}

}  // namespace

TEST_CASE("a manifest that was edited or damaged is refused") {
  const SmallCell cell = SmallCell::named("manifest");
  app::ModelDb db = *app::ModelDb::open(cell.models, app::grid_spec(cell.config), true);
  db.manifest().parts.push_back(plate_entry(1));
  REQUIRE(db.save().ok());
  auto reopened = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(reopened.ok());
  CHECK(reopened->manifest().parts.at(0).scans.at(0).crc32 == 0x1234abcdU);
  CHECK(reopened->manifest().parts.at(0).id == 3);

  std::string text = read_all(cell.models + "/manifest.yaml");
  text.replace(text.find("id: 3"), 5, "id: 4");
  std::ofstream(cell.models + "/manifest.yaml", std::ios::binary) << text;
  auto edited = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE_FALSE(edited.ok());
  CHECK(edited.error().message.find("checksum") != std::string::npos);

  // Another grid: refused, both named.
  REQUIRE(db.save().ok());
  algo::GridSpec other = app::grid_spec(cell.config);
  other.nx += 1;
  auto wrong = app::ModelDb::open(cell.models, other, false);
  REQUIRE_FALSE(wrong.ok());
  CHECK(wrong.error().message.find("149x250x91") != std::string::npos);
}

TEST_CASE(
    "Given a manifest whose texts hold quotes and backslashes, when it is saved and read back, then every "
    "text is the same (fuzz_manifest finding)") {
  // Found by tests/fuzz/fuzz_manifest: parts_fingerprint was written between quotes without escaping, so a manifest
  // that read fine (a quote in a plain scalar, checksum right) was saved as one that no longer parsed.
  formats::Manifest m;
  formats::PartEntry p;
  p.name = "plate";
  p.id = 3;
  p.template_file = "templates/plate.dmap";
  p.taught_at = "a \"quoted\" time";
  p.scans.push_back({"scans/plate/00001.ply", 0x1234abcdU, "C:\\scans\\\"odd\".ply"});
  m.parts.push_back(p);
  m.svm.present = true;
  m.svm.file = "svm.bin";
  m.svm.trained_at = "then";
  m.svm.parts_fingerprint = "deadbeef\"-2\\";
  m.svm.hyper = "rbf \"C\"=1";
  const auto back = formats::parse_manifest("manifest.yaml", formats::manifest_text(m));
  INFO(formats::manifest_text(m));
  REQUIRE(back.ok());
  CHECK(back->svm.parts_fingerprint == m.svm.parts_fingerprint);
  CHECK(back->svm.hyper == m.svm.hyper);
  CHECK(back->parts.at(0).taught_at == p.taught_at);
  CHECK(back->parts.at(0).scans.at(0).source == p.scans.at(0).source);
}

TEST_CASE("limits learnt before a gate existed read as not learnt, so the database asks for training", "[model_db]") {
  formats::Manifest m;
  formats::PartEntry p;
  p.name = "plate";
  p.id = 3;
  p.template_file = "templates/plate.dmap";
  p.scans.push_back({"scans/plate/00001.ply", 0x1234abcdU, "sim seed 1"});
  p.thresholds = {true, 0.01, 0.002, 0.003, 0.1, 0.05, 0.0004, 0.001, -0.002, 0.01};
  m.parts.push_back(p);
  const std::string text = formats::manifest_text(m);
  const auto back = formats::parse_manifest("manifest.yaml", text);
  REQUIRE(back.ok());
  CHECK(back->parts.at(0).thresholds.learnt);
  CHECK(back->parts.at(0).thresholds.max_hole_pattern_m2 == Approx(0.0004));
  // The manifest of an older version: the text from `key` up to (not including) the first of `until` left out, the
  // checksum made again.
  auto older = [&](const char* key, const char* until) {
    std::string old = text.substr(0, text.find("checksum_crc32"));
    const std::size_t at = old.find(key);
    REQUIRE(at != std::string::npos);
    old.erase(at, old.find_first_of(until, at + 2) - at);
    char line[40];
    std::snprintf(line, sizeof line, "checksum_crc32: \"%08x\"\n", base::crc32(old));
    return old + line;
  };
  // The same limits without the hole pattern's (a database trained before it, issue 11) or without an edge's (before
  // issue 10's edges): read, but not learnt.
  for (const char* key : {", max_hole_pattern_m2: ", ", edge_centre_left_m: ", ", max_edge_dev_top_m: "}) {
    const std::string old = older(key, ",}");
    INFO(old);
    const auto before = formats::parse_manifest("manifest.yaml", old);
    REQUIRE(before.ok());
    CHECK_FALSE(before->parts.at(0).thresholds.learnt);
  }
  // The centres' gains in the depth slope came later and are optional: without them the limits are learnt, and the
  // centres stand alone (gain 0).
  {
    const std::string old = older(", size_gain_x_m: ", "}");
    REQUIRE(old.find("gain") == std::string::npos);
    const auto before = formats::parse_manifest("manifest.yaml", old);
    REQUIRE(before.ok());
    CHECK(before->parts.at(0).thresholds.learnt);
    CHECK(before->parts.at(0).thresholds.size_gain_x_m == 0.0);
    CHECK(before->parts.at(0).thresholds.edge_gain_m == std::array<double, 4>{});
  }
  // So are the bands about the edges' medians beside a line: without them, no band (limit 0).
  {
    const std::string old = older(", edge_median_left_m: ", "}");
    REQUIRE(old.find("median") == std::string::npos);
    const auto before = formats::parse_manifest("manifest.yaml", old);
    REQUIRE(before.ok());
    CHECK(before->parts.at(0).thresholds.learnt);
    CHECK(before->parts.at(0).thresholds.max_edge_dev_median_m == std::array<double, 4>{});
  }
  // The learn version is written and read back; a manifest written before it was recorded reads as version 0 (so
  // the database is stale until `train`: the cycle test).
  {
    formats::Manifest v = m;
    v.learn_version = 5;
    const auto round = formats::parse_manifest("manifest.yaml", formats::manifest_text(v));
    REQUIRE(round.ok());
    CHECK(round->learn_version == 5);
    const std::string old = older("learn_version: ", "\n");
    REQUIRE(old.find("learn_version") == std::string::npos);
    const auto before = formats::parse_manifest("manifest.yaml", old);
    REQUIRE(before.ok());
    CHECK(before->learn_version == 0);
  }
}

TEST_CASE("a part's limits go from the manifest to the cascade and back field by field", "[model_db]") {
  // Every field a different value, so that two swapped fields show.
  const formats::PartThresholds p{true,
                                  1e-3,
                                  2e-4,
                                  3e-4,
                                  4e-3,
                                  5e-3,
                                  6e-4,
                                  7e-3,
                                  -8e-3,
                                  9e-3,
                                  1.1e-2,
                                  1.2e-2,
                                  {1.3e-3, -1.4e-3, 1.5e-3, -1.6e-3},
                                  {1.7e-3, 1.8e-3, 1.9e-3, 2.1e-3},
                                  -2.2e-2,
                                  2.3e-2,
                                  {2.4e-2, -2.5e-2, 2.6e-2, -2.7e-2},
                                  {2.8e-3, -2.9e-3, 3.1e-3, -3.2e-3},
                                  {3.3e-3, 3.4e-3, 3.5e-3, 3.6e-3}};
  const algo::TemplateThresholds t = app::template_thresholds(p);
  CHECK(t.max_error == p.max_error);
  CHECK(t.max_missing_area_m2 == p.max_missing_area_m2);
  CHECK(t.max_extra_area_m2 == p.max_extra_area_m2);
  CHECK(t.max_uncovered == p.max_uncovered);
  CHECK(t.max_outliers == p.max_outliers);
  CHECK(t.max_hole_pattern_m2 == p.max_hole_pattern_m2);
  CHECK(t.size_centre_x_m == p.size_centre_x_m);
  CHECK(t.size_centre_y_m == p.size_centre_y_m);
  CHECK(t.max_size_dev_x_m == p.max_size_dev_x_m);
  CHECK(t.max_size_dev_y_m == p.max_size_dev_y_m);
  CHECK(t.max_size_dev_m == p.max_size_dev_m);
  CHECK(t.edge_centre_m == p.edge_centre_m);
  CHECK(t.max_edge_dev_m == p.max_edge_dev_m);
  CHECK(t.size_gain_x_m == p.size_gain_x_m);
  CHECK(t.size_gain_y_m == p.size_gain_y_m);
  CHECK(t.edge_gain_m == p.edge_gain_m);
  CHECK(t.edge_median_m == p.edge_median_m);
  CHECK(t.max_edge_dev_median_m == p.max_edge_dev_median_m);
  // ... and back: the manifest writes the same limits (every field is in its text).
  auto text_of = [](const formats::PartThresholds& limits) {
    formats::Manifest m;
    formats::PartEntry e;
    e.name = "plate";
    e.id = 1;
    e.template_file = "templates/plate.dmap";
    e.thresholds = limits;
    m.parts.push_back(e);
    return formats::manifest_text(m);
  };
  CHECK(text_of(app::part_thresholds(t, true)) == text_of(p));
}

TEST_CASE("a part taught with few scans lowers the folds, too few for any test is refused with the count needed",
          "[cycle]") {
  const SmallCell cell = SmallCell::named("few");  // 3-fold CV configured
  REQUIRE(cell.run("teach --sim --part plate_4h --count 3").exit_code == 0);
  REQUIRE(cell.run("teach --sim --part bracket_l --count 2").exit_code == 0);
  // Given 2 scans of bracket_l (one to train, one to test): no cross-validation is possible.
  const Run refused = cell.run("train");
  INFO(refused.output);
  CHECK(refused.exit_code == 2);
  CHECK(refused.output.find("'bracket_l' has 2 scans") != std::string::npos);
  CHECK(refused.output.find("at least 3") != std::string::npos);
  // Given 3 each (two to train): 2-fold instead of 3, said so, and a model that classifies.
  REQUIRE(cell.run("teach --sim --part bracket_l --count 1 --seed 3").exit_code == 0);
  const Run trained = cell.run("train");
  INFO(trained.output);
  REQUIRE(trained.exit_code == 0);
  CHECK(trained.output.find("2-fold cross-validation instead of 3") != std::string::npos);
  CHECK(cell.run("parts list").output.find("stale") == std::string::npos);
}

TEST_CASE("scans flagged at training survive a save and must name scans of the part", "[model_db]") {
  const SmallCell cell = SmallCell::named("flagged");
  app::ModelDb db = *app::ModelDb::open(cell.models, app::grid_spec(cell.config), true);
  formats::PartEntry p = plate_entry(2);
  p.flagged = {"scans/plate/00002.ply"};
  db.manifest().parts.push_back(p);
  REQUIRE(db.save().ok());
  auto reopened = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(reopened.ok());
  CHECK(reopened->manifest().parts.at(0).flagged == std::vector<std::string>{"scans/plate/00002.ply"});

  // A flagged name that is not one of the part's scans (saved through the API, so the checksum holds): refused,
  // the key named.
  reopened->manifest().parts.at(0).flagged = {"scans/plate/00003.ply"};
  REQUIRE(reopened->save().ok());
  auto refused = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error().message.find("flagged") != std::string::npos);
}

// Not a test of its own ([.]: ctest runs it by name as the fixture "plc_db", tests/CMakeLists.txt): the small trained
// database that tests/test_run_plc.py runs `cellsight run --sim` with, in the build folder. Three parts, two of them
// differing by one hole; channel_u stays untaught, so the run must report it as unknown.
TEST_CASE("fixture: a small trained database for the PLC integration test", "[.][plc_fixture]") {
  const SmallCell cell(fs::path(CELLSIGHT_BINARY_DIR) / "tests" / "plc_db");
  // The PLC test checks the runtime's path and the recogniser's answers, not this machine's speed: the sanitizer build
  // on a loaded machine took 150-240 ms per pass and ran out of the 200 ms verification budget on taught parts
  // ("not_verified"). 2 s is still well inside the loop's 3 s deadline; the search's budget likewise.
  std::string text = read_all(cell.config_path);
  for (const char* key : {"verify_budget_ms: ", "search_budget_ms: "}) {
    const auto at = text.find(key);
    REQUIRE(at != std::string::npos);
    const auto end = text.find(' ', at + std::strlen(key));
    text.replace(at, end - at, std::string(key) + "2000");
  }
  std::ofstream(cell.config_path) << text;
  int id = 1;
  for (const char* part : {"plate_4h", "plate_5h", "bracket_l"}) {
    const Run r = cell.run(std::string("teach --sim --part ") + part + " --id " + std::to_string(id++) + " --count 8");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  const Run train = cell.run("train");
  INFO(train.output);
  REQUIRE(train.exit_code == 0);
  auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(db.ok());
  CHECK(db->svm_stale_reason().empty());
}

TEST_CASE(
    "opening the database to write removes the temporary files an interrupted write left, only those, and "
    "says so",
    "[model_db]") {
  const SmallCell cell = SmallCell::named("orphans");
  const fs::path models(cell.models);
  fs::create_directories(models / "templates");
  fs::create_directories(models / "scans" / "plate");
  const auto touch = [](const fs::path& p) { std::ofstream(p, std::ios::binary) << std::string(4096, 'x'); };
  // Given what a teach killed while writing left (names as mkstemp makes them) ...
  const std::vector<fs::path> orphans = {models / "templates" / "plate.dmap.tmp-Ab3xYz",
                                         models / "scans" / "plate" / "00001.ply.tmp-q1W2e3",
                                         models / "manifest.yaml.tmp-0aZ9kk"};
  for (const fs::path& p : orphans) touch(p);
  // ... and files that are not ours or not of that pattern.
  const std::vector<fs::path> others = {models / "templates" / "plate.dmap.bak",        models / "notes.tmp-1",
                                        models / "templates" / "plate.dmap.tmp-abc12",  models / "plate.tmp-abcdefg",
                                        models / "templates" / "plate.dmap.tmp-ab_12c", models / ".tmp-abcdef"};
  for (const fs::path& p : others) touch(p);
  fs::create_directories(models / "kept.tmp-abcdef");  // a folder of that name is not a file write_file_atomic made

  // A reading mode leaves them (another process may be writing) ...
  REQUIRE(app::ModelDb::open(cell.models, app::grid_spec(cell.config), true).ok());
  for (const fs::path& p : orphans) CHECK(fs::exists(p));

  // ... teach removes them when it opens the database, whatever happens next (here: a scan that is no scan).
  const Run r = cell.run("teach --part plate /dev/zero");
  INFO(r.output);
  CHECK(r.exit_code == 2);
  for (const fs::path& p : orphans) {
    CHECK_FALSE(fs::exists(p));
    CHECK(r.output.find("removed " + p.string() + ": the temporary file of a write that was interrupted") !=
          std::string::npos);
  }
  for (const fs::path& p : others) CHECK(fs::exists(p));
  CHECK(fs::is_directory(models / "kept.tmp-abcdef"));
  fs::remove_all(cell.dir);
}

TEST_CASE("parts list checks every template and the SVM as loading them does, marks a damaged one and exits 2",
          "[model_db]") {
  const SmallCell cell = SmallCell::named("damaged");
  const algo::GridSpec grid = app::grid_spec(cell.config);
  app::ModelDb db = *app::ModelDb::open(cell.models, grid, true);
  fs::create_directories(fs::path(cell.models) / "templates");
  // Given two parts with real templates of a small plate (the SmallCell grid starts at the carrier origin) ...
  std::vector<algo::ScanPoint> plate;
  for (int i = 0; i < 60; ++i) {
    for (int j = 0; j < 60; ++j) plate.push_back({0.25F + 0.002F * i, 0.45F + 0.002F * j, 0.1F, 0, 0});
  }
  auto model = formats::build_template(plate, grid);
  REQUIRE(model.ok());
  for (const std::string name : {"good", "bad"}) {
    formats::PartEntry p;
    p.name = name;
    p.id = name == "good" ? 1 : 2;
    p.template_file = "templates/" + name + ".dmap";
    p.thresholds.learnt = true;
    REQUIRE(
        formats::write_template(db.path_of(p.template_file), *model, {name, static_cast<std::uint32_t>(p.id), 0}).ok());
    db.manifest().parts.push_back(p);
  }
  // ... a trained SVM on them whose file does not match its checksum ...
  db.manifest().svm.present = true;
  db.manifest().svm.file = "svm-test.model";
  db.manifest().svm.crc32 = base::crc32("the model as it was written");
  db.manifest().svm.trained_at = "2026-12-01 12:00:00";
  db.manifest().svm.parts_fingerprint = db.parts_fingerprint();
  std::ofstream(db.path_of("svm-test.model"), std::ios::binary) << "a model changed after training";
  REQUIRE(db.save().ok());
  // ... and one byte of bad's body changed (its header still reads well, so `parts show` alone cannot tell).
  {
    std::fstream f(db.path_of("templates/bad.dmap"), std::ios::in | std::ios::out | std::ios::binary);
    f.seekg(-100, std::ios::end);
    const char c = static_cast<char>(f.get());
    f.seekp(-100, std::ios::end);
    f.put(static_cast<char>(c ^ 0x5a));
  }

  const Run r = cell.run("parts list");
  INFO(r.output);
  CHECK(r.exit_code == 2);
  const auto line_after = [&](const std::string& start) {
    const auto at = r.output.find('\n', r.output.find(start));
    return r.output.substr(at + 1, r.output.find('\n', at + 1) - at - 1);
  };
  CHECK(line_after("good ").find("DAMAGED") == std::string::npos);
  CHECK(line_after("bad ").rfind("  DAMAGED template templates/bad.dmap: ", 0) == 0);
  CHECK(line_after("bad ").find("classify disables this part") != std::string::npos);
  CHECK(r.output.find("SVM: DAMAGED: " + db.path_of("svm-test.model") + ": checksum differs from the manifest") !=
        std::string::npos);
  CHECK(r.output.find("parts list: 2 damaged files") != std::string::npos);
  fs::remove_all(cell.dir);
}

TEST_CASE(
    "a teach and a train killed between their files and the manifest leave the database as it was, the next "
    "writer removes what they wrote",
    "[model_db][crash]") {
  const SmallCell cell = SmallCell::named("killed");
  const fs::path models(cell.models);
  for (const char* part : {"plate_4h", "bracket_l"}) {
    const Run r = cell.run(std::string("teach --sim --part ") + part + " --count 5");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  const Run trained = cell.run("train");
  INFO(trained.output);
  REQUIRE(trained.exit_code == 0);
  const fs::path probe = cell.dir / "probe.ply";
  REQUIRE(cell.run("scan --sim --part plate_4h --seed 901 --calibration " + (cell.dir / "calibration.yaml").string() +
                   " --out " + probe.string())
              .exit_code == 0);
  const std::string classify =
      "classify --calibration " + (cell.dir / "calibration.yaml").string() + " " + probe.string();
  REQUIRE(cell.run(classify).exit_code == 0);
  const std::string manifest_before = read_all(models / "manifest.yaml");
  const auto files = [&] {
    std::set<std::string> out;
    for (const auto& e : fs::recursive_directory_iterator(models)) {
      if (e.is_regular_file()) out.insert(e.path().lexically_relative(models).generic_string());
    }
    return out;
  };
  const std::set<std::string> files_before = files();
  const auto killed = [](const Run& r) { return r.exit_code == -1 || r.exit_code == 128 + SIGKILL; };
  const std::string kill_at_manifest = "CELLSIGHT_FAULT_KILL_BEFORE_RENAME=manifest.yaml";
  // The database is the one before: same manifest, the old parts and model classify as before.
  const auto as_before = [&] {
    CHECK(read_all(models / "manifest.yaml") == manifest_before);
    const Run after = cell.run(classify);
    INFO(after.output);
    CHECK(after.exit_code == 0);
    CHECK(after.output.find("plate_4h") != std::string::npos);
  };

  // When a teach of a new part dies after its template and scans are in place, before the manifest names them ...
  const Run teach = cell.run("teach --sim --part plate_5h --count 5", kill_at_manifest);
  INFO(teach.output);
  CHECK(killed(teach));
  CHECK(fs::exists(models / "templates" / "plate_5h.dmap"));
  as_before();
  // ... and a training dies the same way, its new model written (it removed the teach's orphans first) ...
  const Run train = cell.run("train", kill_at_manifest);
  INFO(train.output);
  CHECK(killed(train));
  CHECK(train.output.find("plate_5h.dmap: not in the manifest") != std::string::npos);
  CHECK(train.output.find("plate_5h/00001.cscan: not in the manifest") != std::string::npos);
  CHECK_FALSE(fs::exists(models / "templates" / "plate_5h.dmap"));
  as_before();
  std::size_t extra_models = 0;
  for (const std::string& f : files()) extra_models += f.starts_with("svm-") && files_before.count(f) == 0 ? 1 : 0;
  CHECK(extra_models == 1);

  // ... then the next teach removes the training's orphans (the model, the manifest's temporary file), says so, and
  // leaves exactly the files its manifest names.
  const Run again = cell.run("teach --sim --part plate_5h --count 5");
  INFO(again.output);
  REQUIRE(again.exit_code == 0);
  CHECK(again.output.find(".model: not in the manifest") != std::string::npos);
  CHECK(again.output.find("manifest.yaml.tmp-") != std::string::npos);
  auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(db.ok());
  std::set<std::string> named = {"manifest.yaml", db->manifest().svm.file};
  for (const formats::PartEntry& p : db->manifest().parts) {
    named.insert(p.template_file);
    for (const formats::ScanEntry& sc : p.scans) named.insert(sc.file);
  }
  CHECK(files() == named);
  CHECK(cell.run("parts list").exit_code == 0);
  fs::remove_all(cell.dir);
}

TEST_CASE(
    "parts rebuild: an old-format template is refused naming the command, rebuild gives teach's template back "
    "and asks for train",
    "[model_db]") {
  const SmallCell cell = SmallCell::named("rebuild");
  const std::string calibration = (cell.dir / "calibration.yaml").string();
  for (const char* part : {"plate_4h", "bracket_l", "tray"}) {
    const Run r = cell.run(std::string("teach --sim --part ") + part + " --count 4");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  REQUIRE(cell.run("train").exit_code == 0);
  const fs::path probe = cell.dir / "probe.ply";
  REQUIRE(cell.run("scan --sim --part plate_4h --seed 901 --calibration " + calibration + " --out " + probe.string())
              .exit_code == 0);
  const std::string template_path = cell.models + "/templates/plate_4h.dmap";
  const std::string taught = read_all(template_path);
  REQUIRE(taught.size() > formats::kTemplateHeaderBytes);
  CHECK(taught.size() < 4'000'000);  // a sparse map, not the full grid

  // Given plate_4h's template made a version 1 file (the full-grid format of earlier builds: its version field sits
  // where version 2 has it, and is checked before anything else is read)
  {
    std::string old = taught;
    old[8] = 1;
    std::ofstream(template_path, std::ios::binary | std::ios::trunc) << old;
  }
  // Then parts list and classify refuse it, name the command that regenerates it, and keep the other part
  const Run list = cell.run("parts list");
  INFO(list.output);
  CHECK(list.exit_code == 2);
  CHECK(list.output.find("template format version 1") != std::string::npos);
  CHECK(list.output.find("cellsight parts rebuild") != std::string::npos);
  const Run old_classify = cell.run("classify --json " + probe.string());
  INFO(old_classify.output);
  CHECK(old_classify.output.find("parts rebuild") != std::string::npos);
  CHECK(old_classify.output.find("\"class\": null") != std::string::npos);  // unknown: never a guess
  CHECK(old_classify.output.find("\"rejected_by\": \"no_template\"") != std::string::npos);

  // When it is rebuilt (an unknown name is refused first, nothing written)
  const Run unknown = cell.run("parts rebuild nope --calibration " + calibration);
  CHECK(unknown.exit_code == 2);
  CHECK(unknown.output.find("no part 'nope'") != std::string::npos);
  const Run rebuilt = cell.run("parts rebuild plate_4h --calibration " + calibration);
  INFO(rebuilt.output);
  REQUIRE(rebuilt.exit_code == 0);
  CHECK(rebuilt.output.find("run 'cellsight train'") != std::string::npos);

  // Then the template is teach's, byte for byte behind the header (whose creation time differs) ...
  const std::string again = read_all(template_path);
  REQUIRE(again.size() == taught.size());
  CHECK(again.compare(formats::kTemplateHeaderBytes, std::string::npos, taught, formats::kTemplateHeaderBytes,
                      std::string::npos) == 0);
  // ... its part's thresholds are to be learnt again (the other part's stay), so classify asks for train ...
  auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(db.ok());
  CHECK_FALSE(db->find("plate_4h")->thresholds.learnt);
  CHECK(db->find("bracket_l")->thresholds.learnt);
  const Run stale = cell.run("classify " + probe.string());
  CHECK(stale.exit_code == 2);
  CHECK(stale.output.find("cellsight train") != std::string::npos);
  // ... and after training the part is recognised again
  REQUIRE(cell.run("train").exit_code == 0);
  const Run classify = cell.run("classify --json " + probe.string());
  INFO(classify.output);
  CHECK(classify.exit_code == 0);
  CHECK(classify.output.find("\"class\": \"plate_4h\"") != std::string::npos);

  // A budget the database does not fit (issue 11): parts list says so, classify and run refuse at start-up with
  // exit 2, naming the need and the budget, instead of running a loop that pages templates in.
  std::string text = read_all(cell.config_path);
  const std::string key = "model_memory_mb: 1200";
  REQUIRE(text.find(key) != std::string::npos);
  text.replace(text.find(key), key.size(), "model_memory_mb: 1");
  const std::string tight = (cell.dir / "tight.yaml").string();
  std::ofstream(tight) << text;
  const auto with_tight = [&](const std::string& args) { return cell.run_with_config(tight, args); };
  const auto footprint = app::model_footprint(*app::ModelDb::open(cell.models, app::grid_spec(cell.config), false));
  REQUIRE(footprint.total_bytes() > 1'000'000);
  const Run over_list = with_tight("parts list");
  INFO(over_list.output);
  CHECK(over_list.output.find("OVER BUDGET") != std::string::npos);
  for (const std::string& args :
       {"classify " + probe.string(), std::string("run --sim --parts 1 --calibration ") + calibration}) {
    const Run refused = with_tight(args);
    INFO(args << "\n" << refused.output);
    CHECK(refused.exit_code == 2);
    CHECK(refused.output.find("needs") != std::string::npos);
    CHECK(refused.output.find("more than runtime.model_memory_mb: 1 in " + tight) != std::string::npos);
  }
  fs::remove_all(cell.dir);
}

namespace {

// The relative paths of the regular files below `dir`, sorted.
std::vector<std::string> files_below(const fs::path& dir) {
  std::vector<std::string> out;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (e.is_regular_file()) out.push_back(e.path().lexically_relative(dir).generic_string());
  }
  std::sort(out.begin(), out.end());
  return out;
}

// Rewrites every taught scan of the database at `models` as a binary PLY (scans/PART/NNNNN.ply), the way teach
// stored them before issue 11, the manifest's names and checksums with them.
void make_legacy_ply_database(const SmallCell& cell) {
  auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
  REQUIRE(db.ok());
  for (formats::PartEntry& p : db->manifest().parts) {
    for (formats::ScanEntry& s : p.scans) {
      auto points = formats::parse_scan_file(read_all(db->path_of(s.file)));
      REQUIRE(points.ok());
      const std::string ply_file = fs::path(s.file).replace_extension(".ply").generic_string();
      const std::string bytes = formats::write_ply_binary(*points);
      std::ofstream(db->path_of(ply_file), std::ios::binary) << bytes;
      fs::remove(db->path_of(s.file));
      if (p.template_scan == s.file) p.template_scan = ply_file;
      s.file = ply_file;
      s.crc32 = base::crc32(bytes);
    }
  }
  REQUIRE(db->save().ok());
}

}  // namespace

TEST_CASE(
    "taught scans are stored compactly and recognised, parts export gives PLY files another cell can teach, a "
    "database of PLY scans still trains",
    "[model_db][scan_file]") {
  const SmallCell cell = SmallCell::named("compact");
  const fs::path models(cell.models);
  const std::string calibration = (cell.dir / "calibration.yaml").string();
  // Given two parts taught on the simulated cell
  for (const char* part : {"plate_4h", "bracket_l"}) {
    const Run r = cell.run(std::string("teach --sim --part ") + part + " --count 5");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
  }
  // Then their scans are compact files, each file's CRC-32 in the manifest, and no PLY among them
  {
    auto db = app::ModelDb::open(cell.models, app::grid_spec(cell.config), false);
    REQUIRE(db.ok());
    std::size_t scans = 0;
    for (const formats::PartEntry& p : db->manifest().parts) {
      for (const formats::ScanEntry& s : p.scans) {
        CHECK(s.file.ends_with(".cscan"));
        const std::string bytes = read_all(models / s.file);
        CHECK(formats::is_scan_file(bytes));
        CHECK(base::crc32(bytes) == s.crc32);
        CHECK(bytes.size() < 400'000);  // a 1.8 MB binary PLY
        ++scans;
      }
    }
    CHECK(scans == 10);
  }
  // ... the model trains on them and recognises a new pass
  const fs::path probe = cell.dir / "probe.ply";
  REQUIRE(cell.run("scan --sim --part plate_4h --seed 901 --calibration " + calibration + " --out " + probe.string())
              .exit_code == 0);
  const auto recognised = [&] {
    const Run classify = cell.run("classify --json " + probe.string());
    INFO(classify.output);
    CHECK(classify.exit_code == 0);
    CHECK(classify.output.find("\"class\": \"plate_4h\"") != std::string::npos);
  };
  {
    const Run train = cell.run("train");
    INFO(train.output);
    REQUIRE(train.exit_code == 0);
  }
  recognised();

  // When a part is exported (into a folder whose parent does not exist yet)
  const fs::path exported = cell.dir / "outgoing" / "plate_4h";
  const Run e = cell.run("parts export plate_4h --out " + exported.string());
  INFO(e.output);
  REQUIRE(e.exit_code == 0);
  // Then it holds one binary PLY per taught scan, named after the stored file, with all its points
  const std::vector<std::string> names = {"00001.ply", "00002.ply", "00003.ply", "00004.ply", "00005.ply"};
  CHECK(files_below(exported) == names);
  for (const std::string& n : names) {
    const std::string ply = read_all(exported / n);
    auto points = formats::parse_ply(ply);
    REQUIRE(points.ok());
    auto stored =
        formats::parse_scan_file(read_all(models / "scans" / "plate_4h" / fs::path(n).replace_extension(".cscan")));
    REQUIRE(stored.ok());
    CHECK(points->size() == stored->size());
    CHECK(ply.find("format binary_little_endian") != std::string::npos);
  }
  // ... a second export into it, an unknown part and a missing --out are refused with exit 2
  const Run again = cell.run("parts export plate_4h --out " + exported.string());
  CHECK(again.exit_code == 2);
  CHECK(again.output.find("not an empty folder") != std::string::npos);
  CHECK(cell.run("parts export nope --out " + (cell.dir / "nope").string()).exit_code == 2);
  CHECK(cell.run("parts export plate_4h").exit_code == 2);
  CHECK(cell.run("parts show plate_4h --out " + (cell.dir / "x").string()).exit_code == 2);
  // ... and another cell's database is taught from the exported files through the PLY path
  {
    std::string files;
    for (const std::string& n : names) files += " " + (exported / n).string();
    const Run r =
        cell.run("--models " + (cell.dir / "elsewhere").string() + " teach --part plate_copy --id 77" + files);
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    CHECK(files_below(cell.dir / "elsewhere" / "scans" / "plate_copy").size() == names.size());
  }

  // Given the database as teach stored it before issue 11: every scan a binary PLY
  make_legacy_ply_database(cell);
  // Then it trains and recognises as before ...
  {
    const Run train = cell.run("train");
    INFO(train.output);
    REQUIRE(train.exit_code == 0);
    CHECK(train.output.find("not in the manifest") == std::string::npos);
  }
  recognised();
  // ... and a part taught into it is stored compactly beside the old PLY scans, which stay (and export as before)
  const Run more = cell.run("teach --sim --part channel_u --count 4");
  INFO(more.output);
  REQUIRE(more.exit_code == 0);
  CHECK(more.output.find("not in the manifest") == std::string::npos);
  CHECK(fs::exists(models / "scans" / "plate_4h" / "00001.ply"));
  CHECK(fs::exists(models / "scans" / "channel_u" / "00001.cscan"));
  CHECK(cell.run("parts export bracket_l --out " + (cell.dir / "old").string() + "/").exit_code == 0);
  CHECK(files_below(cell.dir / "old") == names);
  fs::remove_all(cell.dir);
}
