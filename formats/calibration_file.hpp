// config/calibration.yaml: the calibrated sensor (camera, laser plane, conveyor scale), validated on load and saved
// atomically after a dated backup of the previous file.
#pragma once

#include <string>

#include "algo/result.hpp"
#include "algo/sensor_model.hpp"

namespace cellsight::formats {

// What calibration.yaml holds. Each section is written by its own `cellsight calibrate` step and may be absent
// until that step has run; production needs all three (load_sensor_calibration).
struct CalibrationRecord {
  bool has_camera = false, has_laser = false, has_conveyor = false;
  algo::SensorCalibration sensor{};
  // Local time "YYYY-MM-DD HH:MM:SS" each section was calibrated, and what it was calibrated from.
  std::string camera_date, laser_date, conveyor_date;
  int camera_views = 0;
  double reference_rms_px = 0.0;
  int laser_points = 0;
  double conveyor_angle_deg = 0.0;  // travel direction away from the cell x axis
  // The carrier's support plane (thesis 6.4.1.1), carrier frame, from an empty-carrier scan (calibrate support).
  bool has_support = false;
  algo::Plane support{};
  double support_rms_mm = 0.0;
  std::string support_date;
  std::size_t support_points = 0;
};

constexpr int kCalibrationFormatVersion = 1;

// Reads and validates the file: format_version, every number range-checked, the camera rotation orthonormal,
// the laser normal a unit vector, and the checksum of the whole file (a truncated, corrupt or hand-edited file is
// refused). Errors name file, line and key, one per line; nothing is half-used.
[[nodiscard]] Expected<CalibrationRecord> load_calibration(const std::string& path);

// The complete calibration for production: refused unless every section is present.
[[nodiscard]] Expected<algo::SensorCalibration> load_sensor_calibration(const std::string& path);

// The file's text (sections present in `record` only), ending with its checksum line.
[[nodiscard]] std::string calibration_yaml(const CalibrationRecord& record);

// Copies an existing file to PATH.YYYYMMDD-HHMMSS.bak, then writes the new one atomically. Returns the backup's
// path ("" when there was no previous file). On failure the previous file is untouched.
[[nodiscard]] Expected<std::string> save_calibration(const std::string& path, const CalibrationRecord& record);

}  // namespace cellsight::formats
