// `cellsight calibrate support`: the carrier plane from an empty-carrier scan, stored beside the sensor calibration.
#include <unistd.h>

#include <catch2/catch.hpp>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include "app/config.hpp"
#include "cli/calibrate_mode.hpp"
#include "cli/scan_mode.hpp"
#include "formats/calibration_file.hpp"
#include "formats/ply.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {
std::string read_all(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}
}  // namespace

TEST_CASE(
    "Given a calibrated simulated cell, when the support is calibrated from an empty-carrier scan, then the "
    "carrier plane is stored and a scan that is no empty carrier is refused without touching the file") {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  const fs::path dir = test::scratch_dir("support");
  const std::string file = (dir / "calibration.yaml").string();
  for (const char* step : {"camera", "laser", "conveyor"}) {
    REQUIRE(cli::run_calibrate({step, "--sim", "--out", (dir / step).string(), "--calibration", file}, *cfg, stdout,
                               stderr) == 0);
  }
  REQUIRE(cli::run_calibrate_support({"--sim", "--calibration", file}, *cfg) == 0);
  auto record = formats::load_calibration(file);
  REQUIRE(record.ok());
  REQUIRE(record->has_support);
  REQUIRE(record->has_camera);  // the other sections are kept
  // The simulated carrier's bars lie in z = carrier.plane_z_m.
  CHECK(record->support.normal.z() > 0.99999);
  CHECK(std::abs(record->support.offset_m - cfg->rig.carrier.plane_z_m) < 0.3e-3);
  CHECK(record->support_rms_mm < 0.5);

  // A cloud that is no plane, and a broken PLY: refused, file unchanged.
  const std::string before = read_all(file);
  std::mt19937 rng(4);
  std::uniform_real_distribution<float> u(0.0F, 0.6F);
  std::vector<algo::ScanPoint> cloud;
  for (int i = 0; i < 5000; ++i) cloud.push_back({u(rng), u(rng), u(rng), 0, 0});
  std::ofstream(dir / "cloud.ply", std::ios::binary) << formats::write_ply_binary(cloud);
  CHECK(cli::run_calibrate_support({"--scan", (dir / "cloud.ply").string(), "--calibration", file}, *cfg) == 2);
  std::ofstream(dir / "broken.ply") << "ply\nformat ascii 1.0\nelement vertex 3\n";
  CHECK(cli::run_calibrate_support({"--scan", (dir / "broken.ply").string(), "--calibration", file}, *cfg) == 2);
  CHECK(cli::run_calibrate_support({"--calibration", file}, *cfg) == 2);  // neither --scan nor --sim
  CHECK(read_all(file) == before);
  fs::remove_all(dir);
}
