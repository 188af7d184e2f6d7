// Configuration and part-catalogue reading: shipped files, every class of bad input, one clear line per error.
#include <algorithm>
#include <catch2/catch.hpp>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>
#include <string_view>

#include "app/catalogue.hpp"
#include "app/config.hpp"
#include "app/sim_setup.hpp"
#include "cli/sim_mode.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {

const std::string kShippedConfig = CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml";
const std::string kShippedCatalogue = CELLSIGHT_SOURCE_DIR "/config/parts.yaml";

// A YAML file in a fresh temporary folder.
std::string write_temp(const std::string& name, const std::string& text) {
  const fs::path dir = test::numbered_scratch_dir("config");
  const std::string path = (dir / name).string();
  std::ofstream(path) << text;
  return path;
}

std::string load_error(const std::string& yaml) {
  auto cfg = app::load_config(write_temp("c.yaml", yaml));
  REQUIRE_FALSE(cfg.ok());
  return cfg.error().message;
}

}  // namespace

TEST_CASE(
    "Given the shipped config file, when it is loaded, then it is valid and states exactly the built-in defaults") {
  auto cfg = app::load_config(kShippedConfig);
  INFO((cfg.ok() ? std::string() : cfg.error().message));
  REQUIRE(cfg.ok());
  const app::Config d = app::default_config();
  const auto& k = cfg->rig.camera.intrinsics;
  const auto& dk = d.rig.camera.intrinsics;
  CHECK(k.width_px == dk.width_px);
  CHECK(k.height_px == dk.height_px);
  CHECK(k.fx_px == dk.fx_px);
  CHECK(k.fy_px == dk.fy_px);
  CHECK(k.cx_px == dk.cx_px);
  CHECK(k.cy_px == dk.cy_px);
  CHECK(k.k1 == dk.k1);
  CHECK(k.k2 == dk.k2);
  CHECK(k.p1 == dk.p1);
  CHECK(k.p2 == dk.p2);
  CHECK(k.k3 == dk.k3);
  CHECK(cfg->rig.camera.distance_m == d.rig.camera.distance_m);
  CHECK(cfg->rig.camera.triangulation_angle_deg == d.rig.camera.triangulation_angle_deg);
  CHECK(cfg->rig.camera.aim_world_m == d.rig.camera.aim_world_m);
  CHECK(cfg->rig.laser.normal_world == d.rig.laser.normal_world);
  CHECK(cfg->rig.laser.emitter_world_m == d.rig.laser.emitter_world_m);
  CHECK(cfg->rig.laser.sheet_sigma_mm == d.rig.laser.sheet_sigma_mm);
  CHECK(cfg->rig.conveyor.speed_m_per_s == d.rig.conveyor.speed_m_per_s);
  CHECK(cfg->rig.conveyor.counts_per_mm == d.rig.conveyor.counts_per_mm);
  CHECK(cfg->rig.conveyor.trigger_every_counts == d.rig.conveyor.trigger_every_counts);
  CHECK(cfg->rig.carrier.length_m == d.rig.carrier.length_m);
  CHECK(cfg->rig.carrier.hook_height_m == d.rig.carrier.hook_height_m);
  CHECK(cfg->rig.carrier.part_plane_z_m == d.rig.carrier.part_plane_z_m);
  CHECK(cfg->rig.sensor.gain_dn_per_us == d.rig.sensor.gain_dn_per_us);
  CHECK(cfg->rig.sensor.ambient_light_dn == d.rig.sensor.ambient_light_dn);
  CHECK(cfg->rig.sensor.speckle_contrast == d.rig.sensor.speckle_contrast);
  CHECK(cfg->rig.sensor.noise == d.rig.sensor.noise);
  CHECK(cfg->sim.pose_xy_range_m == d.sim.pose_xy_range_m);
  CHECK(cfg->sim.pose_theta_range_deg == d.sim.pose_theta_range_deg);
  CHECK(cfg->sim.swing_range_deg == d.sim.swing_range_deg);
  CHECK(cfg->sim.tilt_range_deg == d.sim.tilt_range_deg);
  CHECK(cfg->sim.pose_z_range_m == d.sim.pose_z_range_m);
  REQUIRE(cfg->sim.coatings.size() == d.sim.coatings.size());
  for (std::size_t i = 0; i < d.sim.coatings.size(); ++i) {
    CHECK(cfg->sim.coatings[i].name == d.sim.coatings[i].name);
    CHECK(cfg->sim.coatings[i].material.diffuse == d.sim.coatings[i].material.diffuse);
    CHECK(cfg->sim.coatings[i].material.specular == d.sim.coatings[i].material.specular);
  }
  CHECK(cfg->grid.nx == 296);
  CHECK(cfg->grid.ny == 500);
  CHECK(cfg->grid.nz == 182);
  CHECK(cfg->grid.resolution_m == d.grid.resolution_m);
  CHECK(cfg->camera.exposure_us == d.camera.exposure_us);
  CHECK(cfg->modbus.port == d.modbus.port);
  CHECK(cfg->pm.lc_m == d.pm.lc_m);
  CHECK(cfg->pm.fit_lc_m == d.pm.fit_lc_m);
  CHECK(cfg->pm.eta_plus == d.pm.eta_plus);
  CHECK(cfg->pm.eta_minus == d.pm.eta_minus);
  CHECK(cfg->pm.step_initial_m == d.pm.step_initial_m);
  CHECK(cfg->pm.step_min_m == d.pm.step_min_m);
  CHECK(cfg->pm.step_max_m == d.pm.step_max_m);
  CHECK(cfg->pm.step_initial_rad == d.pm.step_initial_rad);
  CHECK(cfg->pm.step_min_rad == d.pm.step_min_rad);
  CHECK(cfg->pm.step_max_rad == d.pm.step_max_rad);
  CHECK(cfg->pm.max_iterations == d.pm.max_iterations);
  CHECK(cfg->pm.max_points == d.pm.max_points);
  CHECK(cfg->pm.informative_fraction == d.pm.informative_fraction);
  CHECK(cfg->pm.coarse_points == d.pm.coarse_points);
  CHECK(cfg->pm.coarse_iterations == d.pm.coarse_iterations);
  CHECK(cfg->pm.level_passes == d.pm.level_passes);
  CHECK(cfg->pm.level_clip_m == d.pm.level_clip_m);
  CHECK(cfg->cascade.accept_p1 == d.cascade.accept_p1);
  CHECK(cfg->cascade.accept_p2_max == d.cascade.accept_p2_max);
  CHECK(cfg->cascade.pm_candidates == d.cascade.pm_candidates);
  CHECK(cfg->cascade.verify_budget_ms == d.cascade.verify_budget_ms);
  CHECK(cfg->cascade.search_budget_ms == d.cascade.search_budget_ms);
  CHECK(cfg->cascade.stop_ratio == d.cascade.stop_ratio);
  CHECK(cfg->cascade.margin_ratio == d.cascade.margin_ratio);
  CHECK(cfg->cascade.margin_floor_m2 == d.cascade.margin_floor_m2);
  CHECK(cfg->cascade.near_fail_factor == d.cascade.near_fail_factor);
  CHECK(cfg->cascade.weak_evidence_weight == d.cascade.weak_evidence_weight);
  CHECK(cfg->cascade.band_elongation == d.cascade.band_elongation);
  CHECK(cfg->cascade.band_contact_max == d.cascade.band_contact_max);
  CHECK(cfg->cascade.band_max_width_m == d.cascade.band_max_width_m);
  CHECK(cfg->cascade.verify_all_lost_m2 == d.cascade.verify_all_lost_m2);
  CHECK(cfg->cascade.size_factor == d.cascade.size_factor);
  CHECK(cfg->cascade.size_floor_m == d.cascade.size_floor_m);
  CHECK(cfg->cascade.size_floor_x_m == d.cascade.size_floor_x_m);
  CHECK(cfg->cascade.edge_floor_m == d.cascade.edge_floor_m);
  CHECK(cfg->cascade.edge_floor_x_m == d.cascade.edge_floor_x_m);
  CHECK(cfg->cascade.robust_k == d.cascade.robust_k);
  CHECK(cfg->cascade.full_pose == d.cascade.full_pose);
  CHECK(cfg->cascade.max_sigma_m == Approx(d.cascade.max_sigma_m));
  CHECK(cfg->cascade.max_sigma_rad == Approx(d.cascade.max_sigma_rad));
  for (std::size_t a = 0; a < algo::kPoseAxes; ++a) {
    CHECK(cfg->cascade.pose_sigma_scale[a] == d.cascade.pose_sigma_scale[a]);
    CHECK(cfg->cascade.pose_sigma_floor[a] == Approx(d.cascade.pose_sigma_floor[a]));
  }
  CHECK(cfg->cascade.blob_window_m == d.cascade.blob_window_m);
  CHECK(cfg->cascade.depth_tolerance_m == d.cascade.depth_tolerance_m);
  CHECK(cfg->cascade.refine_iterations == d.cascade.refine_iterations);
  CHECK(cfg->cascade.level_depth == d.cascade.level_depth);
  CHECK(cfg->cascade.per_cell_depth == d.cascade.per_cell_depth);
  CHECK(cfg->cascade.fine_window_m == d.cascade.fine_window_m);
  CHECK(cfg->cascade.fine_depth_tolerance_m == d.cascade.fine_depth_tolerance_m);
  CHECK(cfg->cascade.error_factor == d.cascade.error_factor);
  CHECK(cfg->cascade.error_floor == d.cascade.error_floor);
  CHECK(cfg->cascade.area_factor == d.cascade.area_factor);
  CHECK(cfg->cascade.area_floor_m2 == d.cascade.area_floor_m2);
  CHECK(cfg->cascade.share_factor == d.cascade.share_factor);
  CHECK(cfg->cascade.share_floor == d.cascade.share_floor);
  CHECK(cfg->svm.sa_start_temperature == d.svm.sa_start_temperature);
  CHECK(cfg->svm.augment_per_scan == d.svm.augment_per_scan);
  CHECK(cfg->svm.augment_search_per_scan == d.svm.augment_search_per_scan);
  CHECK(cfg->runtime.deadline_ms == d.runtime.deadline_ms);
  CHECK(cfg->catalogue_path == fs::path(kShippedCatalogue).lexically_normal().string());
}

TEST_CASE(
    "Given a value out of range, when the config is loaded, then one line names file, line, column, key, "
    "value and the range with its unit") {
  const std::string message = load_error("rig:\n  camera:\n    fx_px: -3\n");
  CHECK(message.find("c.yaml:3:12: rig.camera.fx_px: '-3' is not valid, expected a number from 50 to 50000 px") !=
        std::string::npos);
  CHECK(message.find('\n') == std::string::npos);
}

TEST_CASE("Given a misspelt key, when the config is loaded, then it is refused naming the key and its line") {
  const std::string message = load_error("conveyor:\n  speed_m_per_s: 0.01\n  sped_m_per_s: 0.02\n");
  CHECK(message.find(":3:3: conveyor.sped_m_per_s: unknown key") != std::string::npos);
}

TEST_CASE("Given wrong types and bad choices, when the config is loaded, then each is reported on its own line") {
  const std::string message = load_error(
      "camera:\n  backend: usb\n  exposure_us: [1, 2]\nsim:\n  sensor:\n    noise: maybe\ngrid:\n  nx: 29.5\n"
      "rig:\n  laser:\n    normal: [1, 0]\n");
  CHECK(message.find("camera.backend: 'usb' is not valid, expected one of: sim | v4l2") != std::string::npos);
  CHECK(message.find("camera.exposure_us: a list is not valid") != std::string::npos);
  CHECK(message.find("sim.sensor.noise: 'maybe' is not valid, expected true or false") != std::string::npos);
  CHECK(message.find("grid.nx: '29.5' is not valid, expected a whole number from 8 to 4096 cells") !=
        std::string::npos);
  CHECK(message.find("rig.laser.normal: is not valid, expected [x, y, z]") != std::string::npos);
  CHECK(std::count(message.begin(), message.end(), '\n') == 4);
}

TEST_CASE("Given inconsistent limits, when the config is loaded, then the relation is named") {
  CHECK(load_error("camera:\n  exposure_min_us: 500\n  exposure_max_us: 100\n")
            .find("must not exceed camera.exposure_max_us") != std::string::npos);
  CHECK(load_error("exposure:\n  width_min_px: 6\n  width_max_px: 3\n").find("must be below exposure.width_max_px") !=
        std::string::npos);
  CHECK(load_error("perfect_match:\n  step_min_m: 0.01\n  step_initial_m: 0.001\n")
            .find("perfect_match.step_initial_m: must lie between perfect_match.step_min_m and "
                  "perfect_match.step_max_m") != std::string::npos);
}

TEST_CASE("Given broken YAML or a missing file, when the config is loaded, then the error says where") {
  const std::string message = load_error("rig:\n  camera: [1, 2\n");
  CHECK(message.find("c.yaml:") != std::string::npos);
  CHECK(message.find("YAML syntax error") != std::string::npos);
  auto missing = app::load_config("/nonexistent/cellsight.yaml");
  REQUIRE_FALSE(missing.ok());
  CHECK(missing.error().message == "/nonexistent/cellsight.yaml: cannot open: No such file or directory");
}

TEST_CASE("Given a partial config, when it is loaded, then missing keys keep their defaults") {
  auto cfg = app::load_config(write_temp("c.yaml", "conveyor:\n  speed_m_per_s: 0.02\n"));
  REQUIRE(cfg.ok());
  CHECK(cfg->rig.conveyor.speed_m_per_s == 0.02);
  CHECK(cfg->rig.conveyor.counts_per_mm == app::default_config().rig.conveyor.counts_per_mm);
}

TEST_CASE("Given the shipped catalogue, when it is loaded, then it has at least 12 parts in the thesis size range") {
  auto parts = app::load_catalogue(kShippedCatalogue);
  INFO((parts.ok() ? std::string() : parts.error().message));
  REQUIRE(parts.ok());
  CHECK(parts->size() >= 12);
  for (const auto& p : *parts) {
    INFO(p.name);
    CHECK(p.width_mm >= 400);
    CHECK(p.width_mm <= 600);
    CHECK(p.height_mm >= 650);
    CHECK(p.height_mm <= 800);
    CHECK(sim::validate_part(p).empty());
    CHECK(sim::build_part(p).size() >= 1);
  }
}

TEST_CASE(
    "Given every catalogue part at the extremes of the random pose, when placed on the carrier, then it lies "
    "inside the occupancy grid") {
  auto cfg = app::load_config(kShippedConfig);
  REQUIRE(cfg.ok());
  auto cell = app::make_sim_cell(*cfg);
  REQUIRE(cell.ok());
  const auto fits = app::check_catalogue_fits_grid(*cfg, cell->catalogue());
  INFO((fits.ok() ? std::string() : fits.error().message));
  CHECK(fits.ok());
}

TEST_CASE("Given catalogue mistakes, when the catalogue is loaded, then each is named with its line") {
  auto load = [](const std::string& yaml) {
    auto parts = app::load_catalogue(write_temp("parts.yaml", yaml));
    REQUIRE_FALSE(parts.ok());
    return parts.error().message;
  };
  CHECK(load("format_version: 1\nparts:\n  - {name: a, width_mm: 400, height_mm: 700, features: [{type: dimple}]}\n")
            .find("parts[0].features[0].type: 'dimple' is not valid, expected one of: hole | slot") !=
        std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700}\n  - {name: a, width_mm: 400, height_mm: 700}\n")
            .find("parts[1].name: 'a' appears twice") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, features: [{type: hole, x_mm: 300, diameter_mm: "
             "10}]}\n")
            .find("feature 0: centre outside the part") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, height_mm: 700}\n").find(":2:5: parts[0].width_mm: missing") != std::string::npos);
  CHECK(load("parts: []\n").find("the catalogue is empty") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, colour: red}\n")
            .find("parts[0].colour: unknown key") != std::string::npos);
}

TEST_CASE("Given pose texts, when parsed, then metres and degrees are read and malformed ones refused") {
  auto pose = cli::parse_pose("0.01,-0.02,3");
  REQUIRE(pose.ok());
  CHECK(pose->x_m == 0.01);
  CHECK(pose->y_m == -0.02);
  CHECK(pose->theta_rad == Approx(3 * std::numbers::pi / 180.0));
  CHECK(pose->swing_rad == 0.0);
  CHECK(pose->tilt_rad == 0.0);
  CHECK(pose->z_m == 0.0);
  auto full = cli::parse_pose("0.01,0.02,3,2.5,-1.5,0.004");  // swing, tilt in degrees, z in metres
  REQUIRE(full.ok());
  CHECK(full->swing_rad == Approx(2.5 * std::numbers::pi / 180.0));
  CHECK(full->tilt_rad == Approx(-1.5 * std::numbers::pi / 180.0));
  CHECK(full->z_m == 0.004);
  CHECK_FALSE(cli::parse_pose("1,2").ok());
  CHECK_FALSE(cli::parse_pose("a,b,c").ok());
  CHECK_FALSE(cli::parse_pose("0.01,0.02,3,4,5,0.001,7").ok());
  CHECK_FALSE(cli::parse_pose("0.01,0.02,3,4,50").ok());  // a tilt of 50 deg is no hanging part
  CHECK_FALSE(cli::parse_pose("0.01,0.02,3,4,5,0.5").ok());
  CHECK_FALSE(cli::parse_pose("0.5,0,0").ok());  // 0.5 m is not a pose error, it is a typo for mm
  CHECK(cli::parse_pose("0.01,,3").error().message.find("'' is not a number") != std::string::npos);
}

TEST_CASE(
    "Given a folder as the config file, when it is loaded, then it is refused as not a regular file, "
    "not thrown") {
  const std::string dir = fs::path(write_temp("c.yaml", "")).parent_path().string();
  auto cfg = app::load_config(dir);
  REQUIRE_FALSE(cfg.ok());
  CHECK(cfg.error().message == dir + ": is a directory, not a configuration file");
}

TEST_CASE(
    "Given a key written twice in one mapping, when the config is loaded, then it is refused with file, line and "
    "key (yaml-cpp would keep the first value silently)") {
  const std::string message = load_error("conveyor:\n  speed_m_per_s: 0.01\n  speed_m_per_s: 0.02\n");
  CHECK(message.find("c.yaml:3:3: conveyor.speed_m_per_s: given twice (first at line 2); keep one") !=
        std::string::npos);
  CHECK(message.find('\n') == std::string::npos);
  // At the top level and inside a list element too.
  CHECK(load_error("grid:\n  nx: 100\ngrid:\n  ny: 100\n").find("c.yaml:3:1: grid: given twice (first at line 1)") !=
        std::string::npos);
  CHECK(load_error("sim:\n  coatings:\n    - name: a\n      name: b\n")
            .find("c.yaml:4:7: sim.coatings[0].name: given twice (first at line 3)") != std::string::npos);
  // Two different keys that are lists are unknown keys, not one key twice.
  CHECK(load_error("? [a]\n: 1\n? [b]\n: 2\n").find("given twice") == std::string::npos);
}

TEST_CASE(
    "Given a Modbus bind address that is not a dotted IPv4 address, when the config is loaded, then it is "
    "refused with file, line, key and reason") {
  CHECK(load_error("modbus:\n  bind_address: 999.1.1.1\n")
            .find("c.yaml:2:17: modbus.bind_address: '999.1.1.1' is not valid, expected a dotted IPv4 address such as "
                  "0.0.0.0 (every interface) or 192.168.0.10 (host names are not accepted)") != std::string::npos);
  CHECK(load_error("modbus:\n  bind_address: plc.local\n").find("modbus.bind_address: 'plc.local' is not valid") !=
        std::string::npos);
  for (const char* good : {"0.0.0.0", "127.0.0.1", "192.168.10.2"}) {
    auto cfg = app::load_config(write_temp("c.yaml", std::string("modbus:\n  bind_address: ") + good + "\n"));
    INFO(good << ": " << (cfg.ok() ? std::string() : cfg.error().message));
    REQUIRE(cfg.ok());
    CHECK(cfg->modbus.bind_address == good);
  }
}

TEST_CASE(
    "Given a file of many mistakes, when the config is loaded, then the first 20 are printed and the rest "
    "counted") {
  std::string yaml;
  for (int i = 0; i < 1000; ++i) yaml += "unknown_" + std::to_string(i) + ": 1\n";
  const std::string message = load_error(yaml);
  CHECK(std::count(message.begin(), message.end(), '\n') == 20);
  CHECK(message.find(":1:1: unknown_0: unknown key") != std::string::npos);
  CHECK(message.find(":20:1: unknown_19: unknown key") != std::string::npos);
  CHECK(message.find("unknown_20:") == std::string::npos);
  CHECK(message.substr(message.rfind('\n') + 1) == "... and 980 more");
}

TEST_CASE(
    "Given a short config of aliases of aliases, when the config is loaded, then it is refused at once instead "
    "of walking the expansion (found writing fuzz_config)") {
  // Found writing tests/fuzz/fuzz_config: the repeated-key check walked every alias as a copy, so 500 bytes of
  // references (six levels of ten here: 10^6 values) took seconds, nine levels hours.
  std::string yaml = "a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n";
  for (int level = 1; level < 6; ++level) {
    const std::string name = "a" + std::to_string(level);
    yaml += name + ": &" + name + " [";
    for (int k = 0; k < 10; ++k) yaml += (k == 0 ? "*a" : ", *a") + std::to_string(level - 1);
    yaml += "]\n";
  }
  const auto start = std::chrono::steady_clock::now();
  const std::string message = load_error(yaml);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  CHECK(message.find("c.yaml:1:1: (top level): the document holds more than 100000 values once its aliases are "
                     "expanded (aliases of aliases?); refused") != std::string::npos);
  CHECK(seconds < 2.0);  // the capped walk: ~0.1 s under the sanitizers
}

namespace {

// The range of every numeric key (app/config.cpp), as documented by its error message: "from LO to HI UNIT".
enum class KeyKind { kNumber, kInteger, kVec3 };
enum class Reach { kBoth, kLowOnly, kHighOnly };  // which bounds other keys' relations let a value reach
struct RangedKey {
  const char* path;  // dotted; "[0]" is the first element of a list of mappings (given a name)
  KeyKind kind;
  const char* lo;
  const char* hi;
  const char* unit;
  const char* siblings = "";  // other keys of the same mapping, so that a bound does not break a relation
  Reach reach = Reach::kBoth;
};
constexpr KeyKind kNumber = KeyKind::kNumber, kInteger = KeyKind::kInteger, kVec3 = KeyKind::kVec3;
constexpr Reach kLowOnly = Reach::kLowOnly, kHighOnly = Reach::kHighOnly;

const RangedKey kRangedKeys[] = {
    {"format_version", kInteger, "1", "1", ""},
    {"rig.camera.width_px", kInteger, "64", "8192", "px"},
    {"rig.camera.height_px", kInteger, "64", "8192", "px"},
    {"rig.camera.fx_px", kNumber, "50", "50000", "px"},
    {"rig.camera.fy_px", kNumber, "50", "50000", "px"},
    {"rig.camera.cx_px", kNumber, "0", "8192", "px"},
    {"rig.camera.cy_px", kNumber, "0", "8192", "px"},
    {"rig.camera.k1", kNumber, "-2", "2", ""},
    {"rig.camera.k2", kNumber, "-5", "5", ""},
    {"rig.camera.p1", kNumber, "-0.1", "0.1", ""},
    {"rig.camera.p2", kNumber, "-0.1", "0.1", ""},
    {"rig.camera.k3", kNumber, "-10", "10", ""},
    {"rig.camera.distance_m", kNumber, "0.3", "10", "m"},
    {"rig.camera.triangulation_angle_deg", kNumber, "5", "80", "deg"},
    {"rig.camera.aim_m", kVec3, "-5", "5", "m"},
    {"rig.camera.roll_deg", kNumber, "-45", "45", "deg"},
    {"rig.laser.normal", kVec3, "-1", "1", ""},
    {"rig.laser.offset_m", kNumber, "-1", "1", "m"},
    {"rig.laser.emitter_m", kVec3, "-5", "5", "m"},
    {"rig.laser.sheet_sigma_mm", kNumber, "0.01", "5", "mm"},
    {"conveyor.speed_m_per_s", kNumber, "0.001", "1", "m/s"},
    {"conveyor.counts_per_mm", kNumber, "0.1", "1000", "counts/mm"},
    {"conveyor.trigger_every_counts", kInteger, "1", "100000", "counts"},
    {"carrier.length_m", kNumber, "0.1", "3", "m"},
    {"carrier.height_m", kNumber, "0.1", "3", "m"},
    {"carrier.start_offset_m", kNumber, "-3", "3", "m"},
    {"carrier.plane_z_m", kNumber, "-1", "1", "m"},
    {"carrier.bar_width_m", kNumber, "0.005", "0.2", "m"},
    {"carrier.hanger_spacing_m", kNumber, "0", "3", "m"},
    {"carrier.hook_height_m", kNumber, "0.1", "3", "m"},
    {"carrier.part_plane_z_m", kNumber, "-1", "1", "m"},
    {"carrier.reflectivity", kNumber, "0", "2", ""},
    {"sim.pose_xy_range_m", kNumber, "0", "0.3", "m"},
    {"sim.pose_theta_range_deg", kNumber, "0", "45", "deg"},
    {"sim.swing_range_deg", kNumber, "0", "20", "deg"},
    {"sim.tilt_range_deg", kNumber, "0", "20", "deg"},
    {"sim.pose_z_range_m", kNumber, "0", "0.1", "m"},
    {"sim.reflectivity_jitter", kNumber, "0", "0.9", ""},
    {"sim.split_probability", kNumber, "0", "1", ""},
    {"sim.camera_noise_seed", kInteger, "0", "9223372036854775807", ""},
    {"sim.sensor.gain_dn_per_us", kNumber, "0", "100", "DN/us"},
    {"sim.sensor.optics_sigma_px", kNumber, "0.3", "10", "px"},
    {"sim.sensor.bloom_per_log", kNumber, "0", "5", ""},
    {"sim.sensor.ambient_dn", kNumber, "0", "200", "DN"},
    {"sim.sensor.ambient_gradient_dn", kNumber, "0", "100", "DN"},
    {"sim.sensor.ambient_light_dn", kNumber, "0", "255", "DN"},
    {"sim.sensor.reference_exposure_us", kNumber, "1", "1e6", "us"},
    {"sim.sensor.speckle_contrast", kNumber, "0", "1", ""},
    {"sim.sensor.halo_fraction", kNumber, "0", "0.5", ""},
    {"sim.sensor.read_noise_dn", kNumber, "0", "50", "DN"},
    {"sim.sensor.shot_noise_dn_per_dn", kNumber, "0", "10", "DN"},
    {"sim.sensor.hot_pixel_fraction", kNumber, "0", "0.01", ""},
    {"sim.sensor.spikes_per_frame", kNumber, "0", "100", ""},
    {"sim.sensor.ghost_probability", kNumber, "0", "1", ""},
    {"sim.coatings[0].diffuse", kNumber, "0", "2", ""},
    {"sim.coatings[0].specular", kNumber, "0", "10", ""},
    {"sim.coatings[0].lobe_deg", kNumber, "0.5", "90", "deg"},
    {"sim.coatings[0].weight", kNumber, "0", "1000", ""},
    {"grid.origin_m", kVec3, "-5", "5", "m"},
    {"grid.nx", kInteger, "8", "4096", "cells"},
    {"grid.ny", kInteger, "8", "4096", "cells"},
    {"grid.nz", kInteger, "8", "4096", "cells"},
    {"grid.resolution_m", kNumber, "0.0002", "0.05", "m"},
    {"camera.buffers", kInteger, "4", "32", "buffers"},
    {"camera.timeout_ms", kInteger, "10", "60000", "ms"},
    {"camera.exposure_us", kNumber, "1", "1e6", "us"},
    {"camera.exposure_min_us", kNumber, "1", "1e6", "us", "exposure_max_us: 1e6"},
    {"camera.exposure_max_us", kNumber, "1", "1e6", "us", "exposure_min_us: 1"},
    {"camera.trigger_control_id", kInteger, "0", "4294967295", ""},
    {"camera.trigger_control_value", kInteger, "-1000000", "1000000", ""},
    {"exposure.width_min_px", kNumber, "0.5", "100", "px", "width_max_px: 100", kLowOnly},
    {"exposure.width_max_px", kNumber, "0.5", "100", "px", "width_min_px: 0.5", kHighOnly},
    {"exposure.max_step_ratio", kNumber, "1.01", "10", ""},
    {"gpio.laser_line", kInteger, "0", "1023", ""},
    {"gpio.trigger_line", kInteger, "0", "1023", ""},
    {"gpio.part_present_line", kInteger, "0", "1023", ""},
    {"gpio.encoder_a_line", kInteger, "0", "1023", ""},
    {"gpio.encoder_b_line", kInteger, "0", "1023", ""},
    {"gpio.trigger_pulse_us", kInteger, "1", "100000", "us"},
    {"gpio.debounce_us", kInteger, "0", "1000000", "us"},
    {"modbus.port", kInteger, "1", "65535", ""},
    {"modbus.max_clients", kInteger, "1", "64", "clients"},
    {"modbus.byte_timeout_ms", kInteger, "1", "10000", "ms"},
    {"modbus.plc_heartbeat_timeout_ms", kInteger, "0", "600000", "ms"},
    {"modbus.result_queue_depth", kInteger, "1", "256", "results"},
    {"support.distance_threshold_mm", kNumber, "0.1", "100", "mm"},
    {"svm.sa_start_temperature", kNumber, "1e-6", "1e6", ""},
    {"svm.sa_cooling_ratio", kNumber, "0.5", "0.9999", ""},
    {"svm.sa_iterations", kInteger, "1", "100000", ""},
    {"svm.folds", kInteger, "2", "50", ""},
    {"svm.train_fraction", kNumber, "0.1", "0.95", ""},
    {"svm.threads", kInteger, "0", "256", "threads"},
    {"svm.seed", kInteger, "0", "9223372036854775807", ""},
    {"svm.augment_per_scan", kInteger, "0", "100", ""},
    {"svm.augment_search_per_scan", kInteger, "0", "100", ""},
    {"perfect_match.lc_m", kNumber, "1e-4", "10", "m"},
    {"perfect_match.fit_lc_m", kNumber, "0", "10", "m"},
    {"perfect_match.eta_plus", kNumber, "1", "5", ""},
    {"perfect_match.eta_minus", kNumber, "0.01", "1", ""},
    {"perfect_match.step_initial_m", kNumber, "1e-9", "1", "m", "step_min_m: 1e-9\nstep_max_m: 1"},
    {"perfect_match.step_min_m", kNumber, "1e-9", "1", "m", "step_initial_m: 1\nstep_max_m: 1"},
    {"perfect_match.step_max_m", kNumber, "1e-9", "1", "m", "step_min_m: 1e-9\nstep_initial_m: 1e-9"},
    {"perfect_match.step_initial_rad", kNumber, "1e-9", "1", "rad", "step_min_rad: 1e-9\nstep_max_rad: 1"},
    {"perfect_match.step_min_rad", kNumber, "1e-9", "1", "rad", "step_initial_rad: 1\nstep_max_rad: 1"},
    {"perfect_match.step_max_rad", kNumber, "1e-9", "1", "rad", "step_min_rad: 1e-9\nstep_initial_rad: 1e-9"},
    {"perfect_match.max_iterations", kInteger, "1", "100000", ""},
    {"perfect_match.max_points", kInteger, "10", "1000000", "points"},
    {"perfect_match.informative_fraction", kNumber, "0", "1", ""},
    {"perfect_match.coarse_points", kInteger, "0", "1000000", "points"},
    {"perfect_match.coarse_iterations", kInteger, "0", "100000", ""},
    {"perfect_match.level_passes", kInteger, "0", "10", ""},
    {"perfect_match.level_clip_m", kNumber, "1e-4", "0.1", "m"},
    {"cascade.accept_p1", kNumber, "0", "1", ""},
    {"cascade.accept_p2_max", kNumber, "0", "1", ""},
    {"cascade.pm_candidates", kInteger, "1", "64", "classes"},
    {"cascade.verify_budget_ms", kNumber, "1", "3000", "ms"},
    {"cascade.search_budget_ms", kNumber, "1", "3000", "ms"},
    {"cascade.stop_ratio", kNumber, "0", "1", ""},
    {"cascade.margin_ratio", kNumber, "0", "1", ""},
    {"cascade.margin_floor_m2", kNumber, "0", "1", "m^2"},
    {"cascade.near_fail_factor", kNumber, "1", "100", ""},
    {"cascade.blob_window_m", kNumber, "0", "0.05", "m"},
    {"cascade.depth_tolerance_m", kNumber, "1e-4", "0.1", "m"},
    {"cascade.fine_window_m", kNumber, "0", "0.05", "m"},
    {"cascade.fine_depth_tolerance_m", kNumber, "1e-4", "0.1", "m"},
    {"cascade.refine_iterations", kInteger, "0", "1000", ""},
    {"cascade.error_factor", kNumber, "1", "100", ""},
    {"cascade.error_floor", kNumber, "0", "1", ""},
    {"cascade.error_margin_floor", kNumber, "0", "1", ""},
    {"cascade.area_factor", kNumber, "1", "100", ""},
    {"cascade.area_floor_m2", kNumber, "0", "1", "m^2"},
    {"cascade.share_factor", kNumber, "1", "100", ""},
    {"cascade.share_floor", kNumber, "0", "1", ""},
    {"cascade.weak_evidence_weight", kNumber, "0", "1", ""},
    {"cascade.band_elongation", kNumber, "1", "1000", ""},
    {"cascade.band_contact_max", kNumber, "0", "1", ""},
    {"cascade.band_max_width_m", kNumber, "0", "1", "m"},
    {"cascade.verify_all_lost_m2", kNumber, "0", "1", "m^2"},
    {"cascade.size_factor", kNumber, "1", "100", ""},
    {"cascade.size_floor_m", kNumber, "0", "1", "m"},
    {"cascade.size_floor_x_m", kNumber, "0", "1", "m"},
    {"cascade.edge_floor_m", kNumber, "0", "1", "m"},
    {"cascade.edge_floor_x_m", kNumber, "0", "1", "m"},
    {"cascade.robust_k", kNumber, "1", "100", ""},
    {"cascade.pose_max_sigma_mm", kNumber, "0", "100", "mm"},
    {"cascade.pose_max_sigma_deg", kNumber, "0", "45", "deg"},
    {"cascade.pose_sigma_scale.x", kNumber, "0.01", "1000", ""},
    {"cascade.pose_sigma_scale.rz", kNumber, "0.01", "1000", ""},
    {"cascade.pose_sigma_floor.z_mm", kNumber, "0", "10", "mm"},
    {"cascade.pose_sigma_floor.ry_deg", kNumber, "0", "10", "deg"},
    {"runtime.deadline_ms", kInteger, "10", "60000", "ms"},
    {"runtime.realtime_priority", kInteger, "0", "99", ""},
};

// A config file setting `key.path` to `value` (the x of a vector), and where the value stands (line, column).
struct KeyFile {
  std::string text;
  int line = 0, column = 0;
};
KeyFile key_file(const RangedKey& key, const std::string& value) {
  KeyFile f;
  std::string path = key.path, indent;
  for (std::size_t dot = path.find('.'); dot != std::string::npos; dot = path.find('.')) {
    std::string section = path.substr(0, dot);
    path.erase(0, dot + 1);
    if (section.ends_with("[0]")) {
      f.text += indent + section.substr(0, section.size() - 3) + ":\n" + indent + "  - name: a\n";
      indent += "    ";
    } else {
      f.text += indent + section + ":\n";
      indent += "  ";
    }
  }
  for (std::string_view rest = key.siblings; !rest.empty();) {
    const std::size_t end = std::min(rest.find('\n'), rest.size());
    f.text += indent + std::string(rest.substr(0, end)) + "\n";
    rest.remove_prefix(std::min(end + 1, rest.size()));
  }
  f.line = static_cast<int>(std::count(f.text.begin(), f.text.end(), '\n')) + 1;
  f.column = static_cast<int>(indent.size() + path.size() + 2) + 1;
  f.text += indent + path + ": " + (key.kind == kVec3 ? "[" + value + ", 0, 0]" : value) + "\n";
  return f;
}

std::string exact_text(double v) {
  char text[40];
  std::snprintf(text, sizeof text, "%.17g", v);
  return text;
}

// The values just outside and exactly at each bound, as written in the file.
struct Probe {
  std::string outside_lo, at_lo, at_hi, outside_hi, range;
};
Probe probe(const RangedKey& key) {
  Probe p;
  std::ostringstream range;
  if (key.kind == kInteger) {
    const std::int64_t lo = std::stoll(key.lo), hi = std::stoll(key.hi);
    p = {std::to_string(lo - 1), key.lo, key.hi,
         hi == std::numeric_limits<std::int64_t>::max() ? "9223372036854775808" : std::to_string(hi + 1), ""};
    range << "expected a whole number from " << lo << " to " << hi;
  } else {
    // One part in a million beyond the bound (1e-12 beyond a bound of 0): nearer than any bound is meant.
    const double lo = std::stod(key.lo), hi = std::stod(key.hi);
    auto beyond = [](double bound, double direction) {
      return bound + direction * (bound == 0.0 ? 1e-12 : 1e-6 * std::abs(bound));
    };
    p = {exact_text(beyond(lo, -1.0)), exact_text(lo), exact_text(hi), exact_text(beyond(hi, +1.0)), ""};
    range << "expected a number from " << lo << " to " << hi;
  }
  if (key.unit[0] != '\0') range << " " << key.unit;
  p.range = range.str();
  return p;
}

}  // namespace

TEST_CASE(
    "Given each numeric key just outside its range, when the config is loaded, then it is refused with file, "
    "line, column, key, value and range, at each bound it is accepted") {
  const fs::path dir = test::scratch_dir("config-ranges");
  const std::string file = (dir / "c.yaml").string();
  auto load = [&](const KeyFile& f) {
    std::ofstream(file, std::ios::trunc) << f.text;
    return app::load_config(file);
  };
  for (const RangedKey& key : kRangedKeys) {
    const Probe p = probe(key);
    for (const std::string& value : {p.outside_lo, p.outside_hi}) {
      const KeyFile f = key_file(key, value);
      INFO(f.text);
      auto cfg = load(f);
      CHECK_FALSE(cfg.ok());
      if (cfg.ok()) continue;  // every key is still tried: a table run names all wrong bounds at once
      const std::string where = file + ":" + std::to_string(f.line) + ":" + std::to_string(f.column) + ": " + key.path;
      CHECK(cfg.error().message == (key.kind == kVec3
                                        ? where + ": is not valid, expected [x, y, z] with each " + p.range
                                        : where + ": '" + value + "' is not valid, " + p.range));
    }
    for (const std::string& value : {p.at_lo, p.at_hi}) {
      if ((key.reach == kHighOnly && value == p.at_lo) || (key.reach == kLowOnly && value == p.at_hi)) continue;
      const KeyFile f = key_file(key, value);
      INFO(f.text);
      auto cfg = load(f);
      INFO((cfg.ok() ? std::string() : cfg.error().message));
      CHECK(cfg.ok());
    }
  }
  fs::remove_all(dir);
}
