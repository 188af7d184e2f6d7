// `cellsight perturb` (seeded artefacts on a PLY scan) and the --perturb option of teach and eval --sim.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "algo/perturb.hpp"
#include "algo/random.hpp"
#include "app/config.hpp"
#include "app/mode_args.hpp"

namespace cellsight::app {

// Salts of the perturbation seeds: a taught and a test pass with the same pass seed never share a draw.
inline constexpr std::uint64_t kPerturbTeach = 0x7EAC;
inline constexpr std::uint64_t kPerturbEval = 0xE7A1;

// What teach and eval --sim apply to every generated pass before it is stored or written.
struct PassPerturbation {
  algo::PerturbSpec spec;
  algo::Plane support;
  std::uint64_t purpose = 0;  // kPerturbTeach or kPerturbEval

  [[nodiscard]] std::uint64_t seed_for(std::uint64_t pass_seed) const { return algo::mix_seed(pass_seed, purpose); }
};

// The --perturb SPEC option of a mode (nullopt when absent or "none"), with the carrier plane from the calibration
// file and the carrier band from the configuration.
[[nodiscard]] Expected<std::optional<PassPerturbation>> perturbation_option(const ModeArgs& args, const Config& config,
                                                                            const std::string& calibration_path,
                                                                            std::uint64_t purpose);

// `cellsight perturb --kind SPEC [--seed S] [--calibration FILE] IN.ply OUT.ply`
[[nodiscard]] int run_perturb(const std::vector<std::string>& args, const Config& config);

}  // namespace cellsight::app
