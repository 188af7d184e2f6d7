// The cellsight configuration (config/cellsight.yaml): every setting with its built-in default.
#pragma once

#include <Eigen/Core>
#include <string>

#include "algo/cascade.hpp"
#include "algo/perfect_match.hpp"
#include "algo/result.hpp"
#include "drivers/sim/rig.hpp"
#include "drivers/sim/sim_cell.hpp"
#include "hmi/hmi_params.hpp"

namespace cellsight::app {

struct GridConfig {
  Eigen::Vector3d origin_m{0.0, 0.0, 0.0};  // carrier-frame corner of cell (0, 0, 0)
  int nx = 296, ny = 500, nz = 182;         // thesis 6.3: 0.65 x 1.10 x 0.40 m
  double resolution_m = 0.0022;
};

struct CameraConfig {
  std::string backend = "sim";  // sim | v4l2
  std::string device = "/dev/video0";
  int buffers = 4;
  int timeout_ms = 1000;
  double exposure_us = 1500.0;  // start value; the exposure loop moves it inside the limits
  double exposure_min_us = 20.0;
  double exposure_max_us = 20000.0;
  bool external_trigger = false;        // v4l2: the camera waits for the trigger line (driver-private control)
  std::int64_t trigger_control_id = 0;  // 0: the first control whose name contains "trigger"
  int trigger_control_value = 1;        // value of that control that selects external trigger
};

struct ExposureConfig {
  double width_min_px = 3.0;  // stripe-width band the loop keeps (thesis 6.2)
  double width_max_px = 6.0;
  double max_step_ratio = 1.5;
};

struct GpioConfig {
  std::string backend = "sim";  // sim | gpiod
  std::string chip = "gpiochip0";
  int laser_line = 17, trigger_line = 27, part_present_line = 22, encoder_a_line = 23, encoder_b_line = 24;
  bool part_present_active_low = false;
  bool laser_active_low = false;
  bool trigger_active_low = false;
  bool encoder_reverse = false;  // counts must grow while the conveyor runs forward
  int trigger_pulse_us = 100;
  int debounce_us = 2000;
};

struct ModbusConfig {
  std::string bind_address = "127.0.0.1";
  int port = 1502;
  int max_clients = 4;
  int byte_timeout_ms = 50;
  int plc_heartbeat_timeout_ms = 0;  // 0: the PLC heartbeat is not checked
  int result_queue_depth = 8;
};

struct SupportConfig {
  double distance_threshold_mm = 6.0;  // points this close to the fitted carrier plane are carrier
};

struct SvmConfig {
  double sa_start_temperature = 200.0;  // thesis 6.4.2
  double sa_cooling_ratio = 0.95;
  int sa_iterations = 200;
  int folds = 5;
  double train_fraction = 0.7;  // of each part's scans; the rest is the held-back test (thesis: 35 / 15 of 50)
  std::string kernel = "rbf";   // rbf | poly (thesis eq. 6.2 / 6.4)
  int threads = 0;              // cross-validation threads; 0 = all cores
  std::int64_t seed = 1;
  // Synthetic variants of every taught scan (algo/augment: re-posed, thinned, dropouts, noise), 0 = off; the
  // annealing scores its candidates on at most augment_search_per_scan of them, the final SVM learns from all.
  int augment_per_scan = 8;
  int augment_search_per_scan = 1;
  // With more parts than this the feature search scores on this many of them (the nearest centroids, algo
  // TrainParams::search_classes); 0 = all parts.
  int search_classes = 40;
};

// The recognition parameters are the algorithms' own structs, so their defaults (documented and measured there)
// have one source; config/cellsight.yaml exposes the keys a maintenance engineer may need to tune.
using PerfectMatchConfig = algo::PerfectMatchParams;  // algo/perfect_match.hpp
using CascadeConfig = algo::CascadeParams;            // algo/cascade.hpp
using HmiConfig = hmi::HmiParams;                     // hmi/hmi_params.hpp

struct RuntimeConfig {
  int deadline_ms = 3000;  // support removal .. registers written, hard
  bool lock_memory = false;
  int realtime_priority = 0;  // SCHED_FIFO priority of the acquisition thread; 0 = normal scheduling
  std::string models_dir = "models";
  // Memory the loaded model database may take (templates read whole, the SVM): run and classify refuse a database
  // that needs more, at start-up, naming both (issue 11: fixed memory, never a slow loop).
  int model_memory_mb = 1200;
};

struct Config {
  std::string source;  // the file it came from, or "(built-in defaults)"
  std::string log_level = "info";
  sim::RigParams rig = sim::default_rig_params();
  sim::SimParams sim;
  std::string catalogue_path = "parts.yaml";  // relative paths are relative to the config file's folder
  GridConfig grid;
  CameraConfig camera;
  ExposureConfig exposure;
  GpioConfig gpio;
  ModbusConfig modbus;
  SupportConfig support;
  SvmConfig svm;
  PerfectMatchConfig pm;
  CascadeConfig cascade;
  RuntimeConfig runtime;
  HmiConfig hmi;
};

[[nodiscard]] Config default_config();
// Reads and validates a config file; the Error lists every problem, one line each.
[[nodiscard]] Expected<Config> load_config(const std::string& path);
// load_config on the file's text already in memory (`path` names it in messages and anchors relative paths).
[[nodiscard]] Expected<Config> parse_config(const std::string& text, const std::string& path);
// Finds the config: explicit path, $CELLSIGHT_CONFIG, ./config/cellsight.yaml, <exe>/../config, /etc/cellsight.
[[nodiscard]] Expected<Config> find_and_load_config(const std::string& explicit_path);
// calibration.yaml beside the configuration file (config/calibration.yaml with the built-in defaults).
[[nodiscard]] std::string default_calibration_path(const Config& config);

}  // namespace cellsight::app
