// Configuration and part-catalogue reading: shipped files, every class of bad input, one clear line per error.
#include <catch2/catch.hpp>
#include <chrono>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>

#include "app/catalogue.hpp"
#include "app/config.hpp"
#include "app/sim_mode.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {

const std::string kShippedConfig = CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml";
const std::string kShippedCatalogue = CELLSIGHT_SOURCE_DIR "/config/parts.yaml";

// A YAML file in a fresh temporary folder.
std::string write_temp(const std::string& name, const std::string& text) {
  static int counter = 0;
  const fs::path dir = fs::temp_directory_path() / ("cellsight-test-config-" + std::to_string(::getpid()) + "-" + std::to_string(counter++));
  fs::create_directories(dir);
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

TEST_CASE("Given the shipped config file, when it is loaded, then it is valid and states exactly the built-in defaults") {
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
  CHECK(cfg->cascade.robust_k == d.cascade.robust_k);
  CHECK(cfg->cascade.blob_window_m == d.cascade.blob_window_m);
  CHECK(cfg->cascade.depth_tolerance_m == d.cascade.depth_tolerance_m);
  CHECK(cfg->cascade.refine_iterations == d.cascade.refine_iterations);
  CHECK(cfg->cascade.level_depth == d.cascade.level_depth);
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

TEST_CASE("Given a value out of range, when the config is loaded, then one line names file, line, column, key, "
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
  CHECK(message.find("grid.nx: '29.5' is not valid, expected a whole number from 8 to 4096 cells") != std::string::npos);
  CHECK(message.find("rig.laser.normal: is not valid, expected [x, y, z]") != std::string::npos);
  CHECK(std::count(message.begin(), message.end(), '\n') == 4);
}

TEST_CASE("Given inconsistent limits, when the config is loaded, then the relation is named") {
  CHECK(load_error("camera:\n  exposure_min_us: 500\n  exposure_max_us: 100\n").find("must not exceed camera.exposure_max_us") !=
        std::string::npos);
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

TEST_CASE("Given every catalogue part at the extremes of the random pose, when placed on the carrier, then it lies "
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
            .find("parts[0].features[0].type: 'dimple' is not valid, expected one of: hole | slot") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700}\n  - {name: a, width_mm: 400, height_mm: 700}\n")
            .find("parts[1].name: 'a' appears twice") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, features: [{type: hole, x_mm: 300, diameter_mm: 10}]}\n")
            .find("feature 0: centre outside the part") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, height_mm: 700}\n").find(":2:5: parts[0].width_mm: missing") != std::string::npos);
  CHECK(load("parts: []\n").find("the catalogue is empty") != std::string::npos);
  CHECK(load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, colour: red}\n").find("parts[0].colour: unknown key") !=
        std::string::npos);
}

TEST_CASE("Given pose texts, when parsed, then metres and degrees are read and malformed ones refused") {
  auto pose = app::parse_pose("0.01,-0.02,3");
  REQUIRE(pose.ok());
  CHECK(pose->x_m == 0.01);
  CHECK(pose->y_m == -0.02);
  CHECK(pose->theta_rad == Approx(3 * std::numbers::pi / 180.0));
  CHECK(pose->swing_rad == 0.0);
  CHECK_FALSE(app::parse_pose("1,2").ok());
  CHECK_FALSE(app::parse_pose("a,b,c").ok());
  CHECK_FALSE(app::parse_pose("0.01,0.02,3,4,5").ok());
  CHECK_FALSE(app::parse_pose("0.5,0,0").ok());  // 0.5 m is not a pose error, it is a typo for mm
  CHECK(app::parse_pose("0.01,,3").error().message.find("'' is not a number") != std::string::npos);
}

TEST_CASE("Given a folder as the config file, when it is loaded, then it is refused as not a regular file, "
          "not thrown") {
  const std::string dir = fs::path(write_temp("c.yaml", "")).parent_path().string();
  auto cfg = app::load_config(dir);
  REQUIRE_FALSE(cfg.ok());
  CHECK(cfg.error().message == dir + ": is a directory, not a configuration file");
}

TEST_CASE("Given a key written twice in one mapping, when the config is loaded, then it is refused with file, line and "
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

TEST_CASE("Given a Modbus bind address that is not a dotted IPv4 address, when the config is loaded, then it is "
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

TEST_CASE("Given a file of many mistakes, when the config is loaded, then the first 20 are printed and the rest "
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

TEST_CASE("Given a short config of aliases of aliases, when the config is loaded, then it is refused at once instead "
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
