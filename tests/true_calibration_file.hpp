// A calibration.yaml holding the simulator's true sensor and the carrier plane the simulated carrier really has: for
// tests that need calibrated scans but do not test calibration (calibration has its own tests).
#pragma once

#include <Eigen/Core>
#include <catch2/catch.hpp>
#include <string>

#include "app/config.hpp"
#include "drivers/sim/rig.hpp"
#include "formats/calibration_file.hpp"
#include "sim_test_util.hpp"

namespace cellsight::test {

inline void write_true_calibration(const app::Config& config, const std::string& path) {
  const sim::Rig rig = sim::make_rig(config.rig);
  formats::CalibrationRecord record;
  record.has_camera = record.has_laser = record.has_conveyor = record.has_support = true;
  record.sensor = true_calibration(rig);
  record.camera_date = record.laser_date = record.conveyor_date = record.support_date = "2026-12-01 12:00:00";
  record.camera_views = 12;
  record.laser_points = 1000;
  record.support_points = 1000;
  record.support.normal = Eigen::Vector3d::UnitZ();
  record.support.offset_m = config.rig.carrier.plane_z_m;
  REQUIRE(formats::save_calibration(path, record).ok());
}

}  // namespace cellsight::test
