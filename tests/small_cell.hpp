// A small model database's cell for the tests that drive the executable (teach, train, classify, the screen's jobs):
// the shipped configuration made fast, the simulator's true sensor as calibration, and a way to run `cellsight` on
// it. Shared by test_model_db and test_hmi_parts.
#pragma once

#include <sys/wait.h>

#include <array>
#include <catch2/catch.hpp>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "app/config.hpp"
#include "tests/scratch_dir.hpp"
#include "tests/true_calibration_file.hpp"

namespace cellsight::test {

namespace fs = std::filesystem;

inline const std::string kExe = CELLSIGHT_BINARY_DIR "/app/cellsight";

struct Run {
  int exit_code;
  std::string output;  // stdout and stderr
};

// A shell command's exit code and output (what it wrote to stdout; add 2>&1 for stderr too).
inline Run run_command(const std::string& command) {
  FILE* pipe = ::popen(command.c_str(), "r");
  REQUIRE(pipe != nullptr);
  std::string out;
  std::array<char, 4096> buf{};
  std::size_t n = 0;
  while ((n = std::fread(buf.data(), 1, buf.size(), pipe)) > 0) out.append(buf.data(), n);
  const int status = ::pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

inline std::string read_all(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

// A small cell for fast tests: the shipped config with a 4.4 mm grid (same extent) and frame spacing, 3-fold CV and a
// short annealing run; the simulator's true sensor as calibration.yaml (calibration has its own tests) with the carrier
// plane the simulated carrier really has.
struct SmallCell {
  fs::path dir;
  std::string config_path;
  std::string models;
  app::Config config;

  // Under the temporary folder, per process.
  static SmallCell named(const std::string& name) { return SmallCell(test::scratch_root() / "db" / name); }

  explicit SmallCell(const fs::path& where) {
    dir = where;
    fs::remove_all(dir);
    fs::create_directories(dir);
    fs::copy_file(CELLSIGHT_SOURCE_DIR "/config/parts.yaml", dir / "parts.yaml");
    std::string text = read_all(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
    const auto replace = [&](const std::string& from, const std::string& to) {
      const auto at = text.find(from);
      REQUIRE(at != std::string::npos);
      text.replace(at, from.size(), to);
    };
    replace("folds: 5", "folds: 3");
    replace("sa_iterations: 200", "sa_iterations: 6");
    // Coarser grid, same extent: an 8x smaller distance map keeps the test fast under the sanitizers.
    replace("  nx: 296", "  nx: 148");
    replace("  ny: 500", "  ny: 250");
    replace("  nz: 182", "  nz: 91");
    replace("  resolution_m: 0.0022", "  resolution_m: 0.0044");
    // One frame per grid cell, as the grid (the soak's cell, scripts/sim_cell.sh): half the frames to render and
    // reconstruct, which were most of these tests' time under the sanitizers (test_model_db 350 -> 243 CPU-seconds).
    replace("  trigger_every_counts: 22 ", "  trigger_every_counts: 44 ");
    config_path = (dir / "cellsight.yaml").string();
    std::ofstream(config_path) << text;
    auto loaded = app::load_config(config_path);
    INFO((loaded.ok() ? std::string() : loaded.error().message));
    REQUIRE(loaded.ok());
    config = *loaded;
    test::write_true_calibration(config, (dir / "calibration.yaml").string());
    models = (dir / "models").string();
  }

  // `env`: "NAME=value ..." for the command's environment.
  [[nodiscard]] Run run(const std::string& args, const std::string& env = "") const {
    return run_with_config(config_path, args, env);
  }
  // As run(), with another configuration file.
  [[nodiscard]] Run run_with_config(const std::string& config_file, const std::string& args,
                                    const std::string& env = "") const {
    const std::string command = (env.empty() ? "" : env + " ") + kExe + " --config " + config_file + " --models " +
                                models + " --log-level warn " + args + " 2>&1";
    return run_command(command);
  }
};

}  // namespace cellsight::test
