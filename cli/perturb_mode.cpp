// `cellsight perturb` and the --perturb option: parse the kinds, load the carrier plane, perturb, write.
#include "cli/perturb_mode.hpp"

#include <cstdio>

#include "app/recognition.hpp"
#include "base/atomic_file.hpp"
#include "cli/cli.hpp"
#include "formats/calibration_file.hpp"
#include "formats/input_file.hpp"
#include "formats/ply.hpp"

namespace cellsight::cli {
namespace {

int fail(int code, const std::string& message) {
  std::fprintf(stderr, "cellsight: %s\n", message.c_str());
  return code;
}

Expected<algo::PerturbSpec> spec_from(const std::string& text, const app::Config& config) {
  auto spec = algo::parse_perturb(text);
  if (!spec) return spec.error();
  spec->carrier_band_m = config.support.distance_threshold_mm * 1e-3;
  return spec;
}

}  // namespace

Expected<std::optional<app::PassPerturbation>> perturbation_option(const ModeArgs& args, const app::Config& config,
                                                                   const std::string& calibration_path,
                                                                   std::uint64_t purpose) {
  const std::string* text = args.value("--perturb");
  if (text == nullptr) return std::optional<app::PassPerturbation>{};
  auto spec = spec_from(*text, config);
  if (!spec) return spec.error();
  if (spec->empty()) return std::optional<app::PassPerturbation>{};
  auto support = app::load_support_plane(calibration_path);
  if (!support) return support.error();
  return std::optional<app::PassPerturbation>{app::PassPerturbation{std::move(*spec), *support, purpose}};
}

int run_perturb(const std::vector<std::string>& words, const app::Config& config) {
  ModeArgs args;
  std::string error;
  if (!parse_mode_args(words, {"--kind", "--seed", "--calibration"}, {}, args, error)) {
    return fail(kExitUsage, "perturb: " + error);
  }
  if (args.positional.size() != 2) return fail(kExitUsage, "perturb needs IN.ply OUT.ply");
  const std::string* kind = args.value("--kind");
  if (kind == nullptr) return fail(kExitUsage, "perturb needs --kind SPEC (e.g. --kind glare or --kind noise:2,thin)");
  auto spec = spec_from(*kind, config);
  if (!spec) return fail(kExitUsage, spec.error().message);
  std::int64_t seed = 1;
  if (const std::string* s = args.value("--seed"); s != nullptr && !parse_whole(*s, 0, INT64_MAX, seed)) {
    return fail(kExitUsage, "perturb: --seed '" + *s + "': expected a whole number >= 0");
  }
  const std::string* calibration = args.value("--calibration");
  auto support = app::load_support_plane(calibration != nullptr ? *calibration : app::default_calibration_path(config));
  if (!support) return fail(kExitUsage, support.error().message);
  const std::string& in = args.positional[0];
  const std::string& out = args.positional[1];
  auto points = formats::load_ply_file(in);
  if (!points) return fail(kExitUsage, points.error().message);
  const algo::PerturbReport r = algo::perturb_scan(*points, *spec, *support, static_cast<std::uint64_t>(seed));
  if (auto ok = base::write_file_atomic(out, formats::write_ply_binary(*points)); !ok) {
    return fail(kExitFailure, "perturb: " + ok.error().message);
  }
  std::printf("%s -> %s: %s, seed %lld: %zu -> %zu points (%s)\n", in.c_str(), out.c_str(), spec->text.c_str(),
              static_cast<long long>(seed), r.points_in, r.points_out, algo::describe(r).c_str());
  return kExitOk;
}

}  // namespace cellsight::cli
