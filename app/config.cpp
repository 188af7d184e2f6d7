// Reads config/cellsight.yaml into Config, validating every value (ranges carry their units).
#include "app/config.hpp"

#include <arpa/inet.h>
#include <unistd.h>

#include <array>
#include <filesystem>
#include <numbers>

#include "formats/yaml_reader.hpp"

namespace cellsight::app {
namespace {

namespace fs = std::filesystem;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

void read_rig(formats::YamlSection s, sim::RigParams& rig) {
  formats::YamlSection cam = s.section("camera");
  auto& k = rig.camera.intrinsics;
  cam.integer("width_px", k.width_px, 64, 8192, "px");
  cam.integer("height_px", k.height_px, 64, 8192, "px");
  cam.number("fx_px", k.fx_px, 50.0, 50000.0, "px");
  cam.number("fy_px", k.fy_px, 50.0, 50000.0, "px");
  cam.number("cx_px", k.cx_px, 0.0, 8192.0, "px");
  cam.number("cy_px", k.cy_px, 0.0, 8192.0, "px");
  cam.number("k1", k.k1, -2.0, 2.0, "");
  cam.number("k2", k.k2, -5.0, 5.0, "");
  cam.number("p1", k.p1, -0.1, 0.1, "");
  cam.number("p2", k.p2, -0.1, 0.1, "");
  cam.number("k3", k.k3, -10.0, 10.0, "");
  cam.number("distance_m", rig.camera.distance_m, 0.3, 10.0, "m");
  cam.number("triangulation_angle_deg", rig.camera.triangulation_angle_deg, 5.0, 80.0, "deg");
  cam.vec3("aim_m", rig.camera.aim_world_m, -5.0, 5.0, "m");
  cam.number("roll_deg", rig.camera.roll_deg, -45.0, 45.0, "deg");
  cam.finish();

  formats::YamlSection laser = s.section("laser");
  laser.vec3("normal", rig.laser.normal_world, -1.0, 1.0, "");
  if (rig.laser.normal_world.norm() < 0.5) laser.error("normal", "must be a direction (length near 1)");
  laser.number("offset_m", rig.laser.offset_m, -1.0, 1.0, "m");
  laser.vec3("emitter_m", rig.laser.emitter_world_m, -5.0, 5.0, "m");
  laser.number("sheet_sigma_mm", rig.laser.sheet_sigma_mm, 0.01, 5.0, "mm");
  laser.finish();
  s.finish();
}

void read_conveyor(formats::YamlSection s, sim::ConveyorParams& c) {
  s.number("speed_m_per_s", c.speed_m_per_s, 0.001, 1.0, "m/s");
  s.number("counts_per_mm", c.counts_per_mm, 0.1, 1000.0, "counts/mm");
  s.integer("trigger_every_counts", c.trigger_every_counts, 1, 100000, "counts");
  s.finish();
}

void read_carrier(formats::YamlSection s, sim::CarrierParams& c) {
  s.number("length_m", c.length_m, 0.1, 3.0, "m");
  s.number("height_m", c.height_m, 0.1, 3.0, "m");
  s.number("start_offset_m", c.start_offset_m, -3.0, 3.0, "m");
  s.number("plane_z_m", c.plane_z_m, -1.0, 1.0, "m");
  s.number("bar_width_m", c.bar_width_m, 0.005, 0.2, "m");
  s.number("hanger_spacing_m", c.hanger_spacing_m, 0.0, 3.0, "m");
  s.number("hook_height_m", c.hook_height_m, 0.1, 3.0, "m");
  s.number("part_plane_z_m", c.part_plane_z_m, -1.0, 1.0, "m");
  s.number("reflectivity", c.reflectivity, 0.0, 2.0, "");
  s.finish();
}

void read_sim(formats::YamlSection s, Config& cfg) {
  auto& p = cfg.sim;
  s.text("catalogue", cfg.catalogue_path);
  s.number("pose_xy_range_m", p.pose_xy_range_m, 0.0, 0.3, "m");
  s.number("pose_theta_range_deg", p.pose_theta_range_deg, 0.0, 45.0, "deg");
  s.number("swing_range_deg", p.swing_range_deg, 0.0, 20.0, "deg");
  s.number("tilt_range_deg", p.tilt_range_deg, 0.0, 20.0, "deg");
  s.number("pose_z_range_m", p.pose_z_range_m, 0.0, 0.1, "m");
  s.number("reflectivity_jitter", p.reflectivity_jitter, 0.0, 0.9, "");
  s.number("split_probability", p.split_probability, 0.0, 1.0, "");
  std::int64_t seed = static_cast<std::int64_t>(p.camera_noise_seed);
  s.integer("camera_noise_seed", seed, 0, INT64_MAX, "");
  p.camera_noise_seed = static_cast<std::uint64_t>(seed);
  formats::YamlSection sensor = s.section("sensor");
  auto& n = cfg.rig.sensor;
  sensor.number("gain_dn_per_us", n.gain_dn_per_us, 0.0, 100.0, "DN/us");
  sensor.number("optics_sigma_px", n.optics_sigma_px, 0.3, 10.0, "px");
  sensor.number("bloom_per_log", n.bloom_per_log, 0.0, 5.0, "");
  sensor.number("ambient_dn", n.ambient_dn, 0.0, 200.0, "DN");
  sensor.number("ambient_gradient_dn", n.ambient_gradient_dn, 0.0, 100.0, "DN");
  sensor.number("ambient_light_dn", n.ambient_light_dn, 0.0, 255.0, "DN");
  sensor.number("reference_exposure_us", n.reference_exposure_us, 1.0, 1e6, "us");
  sensor.number("speckle_contrast", n.speckle_contrast, 0.0, 1.0, "");
  sensor.number("halo_fraction", n.halo_fraction, 0.0, 0.5, "");
  sensor.number("read_noise_dn", n.read_noise_dn, 0.0, 50.0, "DN");
  sensor.number("shot_noise_dn_per_dn", n.shot_noise_dn_per_dn, 0.0, 10.0, "DN");
  sensor.number("hot_pixel_fraction", n.hot_pixel_fraction, 0.0, 0.01, "");
  sensor.number("spikes_per_frame", n.spikes_per_frame, 0.0, 100.0, "");
  sensor.number("ghost_probability", n.ghost_probability, 0.0, 1.0, "");
  sensor.boolean("noise", n.noise);
  sensor.finish();
  if (s.has("coatings")) p.coatings.clear();
  for (formats::YamlSection c : s.list("coatings")) {
    sim::Coating coating;
    c.require("name");
    c.text("name", coating.name);
    c.number("diffuse", coating.material.diffuse, 0.0, 2.0, "");
    c.number("specular", coating.material.specular, 0.0, 10.0, "");
    c.number("lobe_deg", coating.material.lobe_deg, 0.5, 90.0, "deg");
    c.number("weight", coating.weight, 0.0, 1000.0, "");
    c.finish();
    p.coatings.push_back(coating);
  }
  s.finish();
}

void read_grid_section(formats::YamlSection g, Config& cfg) {
  g.vec3("origin_m", cfg.grid.origin_m, -5.0, 5.0, "m");
  g.integer("nx", cfg.grid.nx, 8, 4096, "cells");
  g.integer("ny", cfg.grid.ny, 8, 4096, "cells");
  g.integer("nz", cfg.grid.nz, 8, 4096, "cells");
  g.number("resolution_m", cfg.grid.resolution_m, 0.0002, 0.05, "m");
  g.finish();
}

void read_camera_section(formats::YamlSection c, Config& cfg) {
  c.choice("backend", cfg.camera.backend, {"sim", "v4l2"});
  c.text("device", cfg.camera.device);
  c.integer("buffers", cfg.camera.buffers, 4, 32, "buffers");
  c.integer("timeout_ms", cfg.camera.timeout_ms, 10, 60000, "ms");
  c.number("exposure_us", cfg.camera.exposure_us, 1.0, 1e6, "us");
  c.number("exposure_min_us", cfg.camera.exposure_min_us, 1.0, 1e6, "us");
  c.number("exposure_max_us", cfg.camera.exposure_max_us, 1.0, 1e6, "us");
  c.boolean("external_trigger", cfg.camera.external_trigger);
  c.integer("trigger_control_id", cfg.camera.trigger_control_id, 0, 0xFFFFFFFFLL, "");
  c.integer("trigger_control_value", cfg.camera.trigger_control_value, -1000000, 1000000, "");
  if (cfg.camera.exposure_min_us > cfg.camera.exposure_max_us)
    c.error("exposure_min_us", "must not exceed camera.exposure_max_us");
  c.finish();
}

void read_exposure_section(formats::YamlSection e, Config& cfg) {
  e.number("width_min_px", cfg.exposure.width_min_px, 0.5, 100.0, "px");
  e.number("width_max_px", cfg.exposure.width_max_px, 0.5, 100.0, "px");
  if (cfg.exposure.width_min_px >= cfg.exposure.width_max_px)
    e.error("width_min_px", "must be below exposure.width_max_px");
  e.number("max_step_ratio", cfg.exposure.max_step_ratio, 1.01, 10.0, "");
  e.finish();
}

void read_gpio_section(formats::YamlSection g, Config& cfg) {
  g.choice("backend", cfg.gpio.backend, {"sim", "gpiod"});
  g.text("chip", cfg.gpio.chip);
  g.integer("laser_line", cfg.gpio.laser_line, 0, 1023, "");
  g.integer("trigger_line", cfg.gpio.trigger_line, 0, 1023, "");
  g.integer("part_present_line", cfg.gpio.part_present_line, 0, 1023, "");
  g.integer("encoder_a_line", cfg.gpio.encoder_a_line, 0, 1023, "");
  g.integer("encoder_b_line", cfg.gpio.encoder_b_line, 0, 1023, "");
  g.boolean("part_present_active_low", cfg.gpio.part_present_active_low);
  g.boolean("laser_active_low", cfg.gpio.laser_active_low);
  g.boolean("trigger_active_low", cfg.gpio.trigger_active_low);
  g.boolean("encoder_reverse", cfg.gpio.encoder_reverse);
  g.integer("trigger_pulse_us", cfg.gpio.trigger_pulse_us, 1, 100000, "us");
  g.integer("debounce_us", cfg.gpio.debounce_us, 0, 1000000, "us");
  g.finish();
}

// A listening address: a dotted IPv4 address, checked here so that a bad one names file and key, not fail at `run`.
void read_ipv4(formats::YamlSection& section, const char* key, std::string& value, const char* examples) {
  section.text(key, value);
  in_addr parsed{};
  if (::inet_pton(AF_INET, value.c_str(), &parsed) != 1) {
    section.error(key, "'" + value + "' is not valid, expected a dotted IPv4 address such as " + examples +
                           " (host names are not accepted)");
  }
}

void read_modbus_section(formats::YamlSection m, Config& cfg) {
  // libmodbus listens on a numeric IPv4 address only: a host name or a bad address would fail at `run` time.
  read_ipv4(m, "bind_address", cfg.modbus.bind_address, "0.0.0.0 (every interface) or 192.168.0.10");
  m.integer("port", cfg.modbus.port, 1, 65535, "");
  m.integer("max_clients", cfg.modbus.max_clients, 1, 64, "clients");
  m.integer("byte_timeout_ms", cfg.modbus.byte_timeout_ms, 1, 10000, "ms");
  m.integer("plc_heartbeat_timeout_ms", cfg.modbus.plc_heartbeat_timeout_ms, 0, 600000, "ms");
  m.integer("result_queue_depth", cfg.modbus.result_queue_depth, 1, 256, "results");
  m.finish();
}

void read_support_section(formats::YamlSection s, Config& cfg) {
  s.number("distance_threshold_mm", cfg.support.distance_threshold_mm, 0.1, 100.0, "mm");
  s.finish();
}

void read_svm_section(formats::YamlSection s, Config& cfg) {
  s.number("sa_start_temperature", cfg.svm.sa_start_temperature, 1e-6, 1e6, "");
  s.number("sa_cooling_ratio", cfg.svm.sa_cooling_ratio, 0.5, 0.9999, "");
  s.integer("sa_iterations", cfg.svm.sa_iterations, 1, 100000, "");
  s.integer("folds", cfg.svm.folds, 2, 50, "");
  s.number("train_fraction", cfg.svm.train_fraction, 0.1, 0.95, "");
  s.choice("kernel", cfg.svm.kernel, {"rbf", "poly"});
  s.integer("threads", cfg.svm.threads, 0, 256, "threads");
  s.integer("seed", cfg.svm.seed, 0, INT64_MAX, "");
  s.integer("augment_per_scan", cfg.svm.augment_per_scan, 0, 100, "");
  s.integer("augment_search_per_scan", cfg.svm.augment_search_per_scan, 0, 100, "");
  s.integer("search_classes", cfg.svm.search_classes, 0, 100000, "classes");
  s.finish();
}

void read_perfect_match_section(formats::YamlSection s, Config& cfg) {
  s.number("lc_m", cfg.pm.lc_m, 1e-4, 10.0, "m");
  s.number("fit_lc_m", cfg.pm.fit_lc_m, 0.0, 10.0, "m");
  s.number("eta_plus", cfg.pm.eta_plus, 1.0, 5.0, "");
  s.number("eta_minus", cfg.pm.eta_minus, 0.01, 1.0, "");
  s.number("step_initial_m", cfg.pm.step_initial_m, 1e-9, 1.0, "m");
  s.number("step_min_m", cfg.pm.step_min_m, 1e-9, 1.0, "m");
  s.number("step_max_m", cfg.pm.step_max_m, 1e-9, 1.0, "m");
  s.number("step_initial_rad", cfg.pm.step_initial_rad, 1e-9, 1.0, "rad");
  s.number("step_min_rad", cfg.pm.step_min_rad, 1e-9, 1.0, "rad");
  s.number("step_max_rad", cfg.pm.step_max_rad, 1e-9, 1.0, "rad");
  s.integer("max_iterations", cfg.pm.max_iterations, 1, 100000, "");
  s.integer("max_points", cfg.pm.max_points, 10, 1000000, "points");
  s.number("informative_fraction", cfg.pm.informative_fraction, 0.0, 1.0, "");
  s.integer("coarse_points", cfg.pm.coarse_points, 0, 1000000, "points");
  s.integer("coarse_iterations", cfg.pm.coarse_iterations, 0, 100000, "");
  s.integer("level_passes", cfg.pm.level_passes, 0, 10, "");
  s.number("level_clip_m", cfg.pm.level_clip_m, 1e-4, 0.1, "m");
  s.finish();
  if (cfg.pm.step_min_m > cfg.pm.step_initial_m || cfg.pm.step_initial_m > cfg.pm.step_max_m) {
    s.error("step_initial_m", "must lie between perfect_match.step_min_m and perfect_match.step_max_m");
  }
  if (cfg.pm.step_min_rad > cfg.pm.step_initial_rad || cfg.pm.step_initial_rad > cfg.pm.step_max_rad) {
    s.error("step_initial_rad", "must lie between perfect_match.step_min_rad and perfect_match.step_max_rad");
  }
}

void read_cascade_section(formats::YamlSection s, Config& cfg) {
  s.number("accept_p1", cfg.cascade.accept_p1, 0.0, 1.0, "");
  s.number("accept_p2_max", cfg.cascade.accept_p2_max, 0.0, 1.0, "");
  s.integer("pm_candidates", cfg.cascade.pm_candidates, 1, 64, "classes");
  s.number("verify_budget_ms", cfg.cascade.verify_budget_ms, 1.0, 3000.0, "ms");
  s.number("search_budget_ms", cfg.cascade.search_budget_ms, 1.0, 3000.0, "ms");
  s.number("stop_ratio", cfg.cascade.stop_ratio, 0.0, 1.0, "");
  s.number("margin_ratio", cfg.cascade.margin_ratio, 0.0, 1.0, "");
  s.number("margin_floor_m2", cfg.cascade.margin_floor_m2, 0.0, 1.0, "m^2");
  s.number("near_fail_factor", cfg.cascade.near_fail_factor, 1.0, 100.0, "");
  s.number("blob_window_m", cfg.cascade.blob_window_m, 0.0, 0.05, "m");
  s.number("depth_tolerance_m", cfg.cascade.depth_tolerance_m, 1e-4, 0.1, "m");
  s.boolean("per_cell_depth", cfg.cascade.per_cell_depth);
  s.number("fine_window_m", cfg.cascade.fine_window_m, 0.0, 0.05, "m");
  s.number("fine_depth_tolerance_m", cfg.cascade.fine_depth_tolerance_m, 1e-4, 0.1, "m");
  s.integer("refine_iterations", cfg.cascade.refine_iterations, 0, 1000, "");
  s.boolean("level_depth", cfg.cascade.level_depth);
  s.number("error_factor", cfg.cascade.error_factor, 1.0, 100.0, "");
  s.number("error_floor", cfg.cascade.error_floor, 0.0, 1.0, "");
  s.number("error_margin_floor", cfg.cascade.error_margin_floor, 0.0, 1.0, "");
  s.number("area_factor", cfg.cascade.area_factor, 1.0, 100.0, "");
  s.number("area_floor_m2", cfg.cascade.area_floor_m2, 0.0, 1.0, "m^2");
  s.number("share_factor", cfg.cascade.share_factor, 1.0, 100.0, "");
  s.number("share_floor", cfg.cascade.share_floor, 0.0, 1.0, "");
  s.number("hole_pattern_floor_m2", cfg.cascade.hole_pattern_floor_m2, 0.0, 1.0, "m^2");
  s.number("hole_match_radius_m", cfg.cascade.hole_match_radius_m, 0.0, 0.05, "m");
  s.number("weak_evidence_weight", cfg.cascade.weak_evidence_weight, 0.0, 1.0, "");
  s.number("band_elongation", cfg.cascade.band_elongation, 1.0, 1000.0, "");
  s.number("band_contact_max", cfg.cascade.band_contact_max, 0.0, 1.0, "");
  s.number("band_max_width_m", cfg.cascade.band_max_width_m, 0.0, 1.0, "m");
  s.number("verify_all_lost_m2", cfg.cascade.verify_all_lost_m2, 0.0, 1.0, "m^2");
  s.number("size_factor", cfg.cascade.size_factor, 1.0, 100.0, "");
  s.number("size_floor_m", cfg.cascade.size_floor_m, 0.0, 1.0, "m");
  s.number("size_floor_x_m", cfg.cascade.size_floor_x_m, 0.0, 1.0, "m");
  s.number("edge_floor_m", cfg.cascade.edge_floor_m, 0.0, 1.0, "m");
  s.number("edge_floor_x_m", cfg.cascade.edge_floor_x_m, 0.0, 1.0, "m");
  s.number("robust_k", cfg.cascade.robust_k, 1.0, 100.0, "");
  s.boolean("full_pose", cfg.cascade.full_pose);
  double max_sigma_mm = cfg.cascade.max_sigma_m * 1e3;
  double max_sigma_deg = cfg.cascade.max_sigma_rad * kRadToDeg;
  s.number("pose_max_sigma_mm", max_sigma_mm, 0.0, 100.0, "mm");
  s.number("pose_max_sigma_deg", max_sigma_deg, 0.0, 45.0, "deg");
  cfg.cascade.max_sigma_m = max_sigma_mm * 1e-3;
  cfg.cascade.max_sigma_rad = max_sigma_deg / kRadToDeg;
  if (s.has("pose_sigma_scale")) {
    formats::YamlSection scale = s.section("pose_sigma_scale");
    constexpr std::array<const char*, algo::kPoseAxes> kAxes = {"x", "y", "z", "rx", "ry", "rz"};
    for (std::size_t a = 0; a < algo::kPoseAxes; ++a) {
      scale.number(kAxes[a], cfg.cascade.pose_sigma_scale[a], 0.01, 1000.0, "");
    }
    scale.finish();
  }
  if (s.has("pose_sigma_floor")) {
    // Millimetres and degrees in the file, metres and radians inside.
    formats::YamlSection floor = s.section("pose_sigma_floor");
    constexpr std::array<const char*, algo::kPoseAxes> kAxes = {"x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"};
    for (std::size_t a = 0; a < algo::kPoseAxes; ++a) {
      const bool angle = a >= 3;
      double v = cfg.cascade.pose_sigma_floor[a] * (angle ? kRadToDeg : 1e3);
      floor.number(kAxes[a], v, 0.0, 10.0, angle ? "deg" : "mm");
      cfg.cascade.pose_sigma_floor[a] = angle ? v / kRadToDeg : v * 1e-3;
    }
    floor.finish();
  }
  s.finish();
}

void read_runtime_section(formats::YamlSection s, Config& cfg) {
  s.integer("deadline_ms", cfg.runtime.deadline_ms, 10, 60000, "ms");
  s.boolean("lock_memory", cfg.runtime.lock_memory);
  s.integer("realtime_priority", cfg.runtime.realtime_priority, 0, 99, "");
  s.text("models_dir", cfg.runtime.models_dir);
  s.integer("model_memory_mb", cfg.runtime.model_memory_mb, 1, 1 << 20, "MB");
  s.finish();
}

void read_hmi_section(formats::YamlSection s, Config& cfg) {
  s.boolean("enabled", cfg.hmi.enabled);
  // civetweb listens on a numeric address too.
  read_ipv4(s, "bind_address", cfg.hmi.bind_address,
            "127.0.0.1 (this machine only), 0.0.0.0 (every interface) or 192.168.0.10");
  s.integer("port", cfg.hmi.port, 1, 65535, "");
  s.text("users_file", cfg.hmi.users_file);
  s.integer("max_clients", cfg.hmi.max_clients, 2, 256, "clients");
  s.integer("session_idle_minutes", cfg.hmi.session_idle_minutes, 1, 7 * 24 * 60, "min");
  s.integer("max_sessions", cfg.hmi.max_sessions, 1, 1000, "sessions");
  s.integer("max_failed_logins", cfg.hmi.max_failed_logins, 1, 1000, "logins");
  s.integer("lockout_s", cfg.hmi.lockout_s, 1, 86400, "s");
  s.integer("max_request_bytes", cfg.hmi.max_request_bytes, 1024, 64 << 20, "bytes");
  s.integer("history", cfg.hmi.history, 1, 100000, "results");
  s.boolean("review_unknown", cfg.hmi.review_unknown);
  s.integer("review_keep", cfg.hmi.review_keep, 1, 10000, "scans");
  s.integer("keep_slots", cfg.hmi.keep_slots, 1, 16, "scans");
  s.finish();
}

// The sections after the rig and the simulator, in the order of the shipped file.
void read_rest(formats::YamlSection& root, Config& cfg) {
  read_grid_section(root.section("grid"), cfg);
  read_camera_section(root.section("camera"), cfg);
  read_exposure_section(root.section("exposure"), cfg);
  read_gpio_section(root.section("gpio"), cfg);
  read_modbus_section(root.section("modbus"), cfg);
  read_support_section(root.section("support"), cfg);
  read_svm_section(root.section("svm"), cfg);
  read_perfect_match_section(root.section("perfect_match"), cfg);
  read_cascade_section(root.section("cascade"), cfg);
  read_runtime_section(root.section("runtime"), cfg);
  read_hmi_section(root.section("hmi"), cfg);
}

}  // namespace

Config default_config() {
  Config cfg;
  cfg.source = "(built-in defaults)";
  cfg.sim.coatings = sim::default_coatings();
  return cfg;
}

namespace {

// Validates a parsed document into a Config; every problem one line naming `path`.
Expected<Config> config_from_yaml(const YAML::Node& doc, const std::string& path) {
  Config cfg = default_config();
  cfg.source = path;
  formats::YamlErrors errors(path);
  formats::YamlSection root(doc, "", &errors);
  int version = 1;
  root.integer("format_version", version, 1, 1, "");
  root.choice("log_level", cfg.log_level, {"debug", "info", "warn", "error", "off"});
  read_rig(root.section("rig"), cfg.rig);
  read_conveyor(root.section("conveyor"), cfg.rig.conveyor);
  read_carrier(root.section("carrier"), cfg.rig.carrier);
  read_sim(root.section("sim"), cfg);
  read_rest(root, cfg);
  root.finish();
  if (!errors.empty()) return make_error(errors.joined());
  const fs::path catalogue(cfg.catalogue_path);
  if (catalogue.is_relative())
    cfg.catalogue_path = (fs::path(path).parent_path() / catalogue).lexically_normal().string();
  const fs::path users(cfg.hmi.users_file);
  if (users.is_relative()) cfg.hmi.users_file = (fs::path(path).parent_path() / users).lexically_normal().string();
  return cfg;
}

}  // namespace

Expected<Config> load_config(const std::string& path) {
  auto doc = formats::load_yaml_file(path);
  if (!doc) return doc.error();
  return config_from_yaml(*doc, path);
}

Expected<Config> parse_config(const std::string& text, const std::string& path) {
  auto doc = formats::parse_yaml_text(text, path);
  if (!doc) return doc.error();
  return config_from_yaml(*doc, path);
}

Expected<Config> find_and_load_config(const std::string& explicit_path) {
  if (!explicit_path.empty()) return load_config(explicit_path);
  std::vector<std::string> candidates;
  if (const char* env = std::getenv("CELLSIGHT_CONFIG"); env != nullptr && env[0] != '\0') return load_config(env);
  candidates.emplace_back("config/cellsight.yaml");
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    candidates.push_back((exe.parent_path().parent_path() / "config/cellsight.yaml").string());
    candidates.push_back((exe.parent_path().parent_path() / "share/cellsight/config/cellsight.yaml").string());
  }
  candidates.emplace_back("/etc/cellsight/cellsight.yaml");
  for (const auto& c : candidates) {
    if (fs::exists(c, ec)) return load_config(c);
  }
  std::string where;
  for (const auto& c : candidates) where += (where.empty() ? "" : ", ") + c;
  return make_error("no configuration found (looked at " + where + "); pass --config FILE or set CELLSIGHT_CONFIG");
}

std::string default_calibration_path(const Config& config) {
  std::error_code ec;
  if (!config.source.empty() && config.source.front() != '(' && fs::is_regular_file(config.source, ec)) {
    return (fs::path(config.source).parent_path() / "calibration.yaml").lexically_normal().string();
  }
  return "config/calibration.yaml";
}

}  // namespace cellsight::app
