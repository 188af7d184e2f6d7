// Command-line parsing and mode dispatch.
#include "cli/cli.hpp"

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "cli/calibrate_mode.hpp"
#include "cli/classify_mode.hpp"
#include "cli/hmi_user_mode.hpp"
#include "cli/mode_args.hpp"
#include "cli/parts_mode.hpp"
#include "cli/perturb_mode.hpp"
#include "cli/run_mode.hpp"
#include "cli/scan_mode.hpp"
#include "cli/sim_mode.hpp"
#include "cli/teach_mode.hpp"
#include "cli/train_mode.hpp"
#include "drivers/log.hpp"
#include "drivers/sim/random_catalogue.hpp"

namespace cellsight::cli {
namespace {

constexpr const char* kUsage =
    "usage: cellsight [--config FILE] [--log-level LEVEL] MODE [options]\n"
    "\n"
    "modes:\n"
    "  sim --part NAME [--seed S] [--pose x_m,y_m,theta_deg[,swing_deg[,tilt_deg[,z_m]]]] --out DIR\n"
    "        render one simulated pass: DIR/frames/NNNNNN.png (mono8) and DIR/truth.yaml\n"
    "  sim --list\n"
    "        list the simulated cell's part catalogue (with role and family when the catalogue has them)\n"
    "  sim --random-catalogue N [--seed S] --out FILE.yaml\n"
    "        write a random catalogue of N parts (2..300) with near-twin pairs and 3 untaught parts; same N and seed,\n"
    "        same file; an existing FILE is never overwritten (point sim.catalogue of a config at it)\n"
    "  scan [--sim --part NAME [--seed S] [--pose x,y,theta] | --sim --empty] --out SCAN.ply [--ascii]\n"
    "       [--calibration FILE]\n"
    "        one acquisition with the calibrated sensor -> point cloud (carrier frame, metres, carrier included)\n"
    "  calibrate camera|laser|conveyor ...   technician calibration (see scripts/calibrate.sh)\n"
    "  calibrate support (--scan EMPTY.ply | --sim [--seed S]) [--calibration FILE]\n"
    "        fit the carrier (support) plane on an empty-carrier scan; stored in calibration.yaml\n"
    "  teach --part NAME [--id N] (--sim --count K [--seed S] [--perturb SPEC] | SCAN.ply ...) [--calibration FILE]\n"
    "        store scans of a part type in the model database; the one that agrees best with the others becomes its\n"
    "        Perfect Match template\n"
    "  train [--report DIR] [--compare] [--iterations N] [--seed S] [--progress] [--calibration FILE]\n"
    "        features of every taught scan, simulated-annealing feature selection + k-fold CV, the SVM,\n"
    "        acceptance thresholds per template; --compare also trains kNN and an MLP (thesis ch. 4);\n"
    "        --progress adds lines 'progress: FRACTION WHAT' for programs (the operator's screen)\n"
    "  classify [--json] [--svm-only|--pm-only] SCAN.ply|TAUGHT.cscan ...   one decision per scan\n"
    "  eval --scans DIR [--json]   DIR/<part>/*.ply [+ DIR/truth.csv: file,x_m,y_m,theta_deg] -> accuracy,\n"
    "        confusion, pose errors, timing (folders of parts that are not taught must come out unknown)\n"
    "  eval --sim --count K [--seed S] [--parts A,B] [--perturb SPEC] --scans DIR   generate the labelled set first\n"
    "  perturb --kind SPEC [--seed S] [--calibration FILE] IN.ply OUT.ply\n"
    "        seeded scan artefacts; SPEC: KIND[:STRENGTH][@SHARE],... with KIND noise, dropout, glare, stray_edge,\n"
    "        stray_points, thin, swing, mixed or none (see README, 'Robustness')\n"
    "  parts list | show NAME | delete NAME\n"
    "  parts export NAME --out DIR\n"
    "        the part's taught scans as binary PLY files (DIR/NNNNN.ply, DIR created) to teach them elsewhere\n"
    "  parts rebuild [NAME ...] [--calibration FILE]\n"
    "        build the templates again from the stored scans (e.g. of an older template format); then train\n"
    "  help  this text\n";

constexpr const char* kUsageGlobals =
    "\n"
    "global options:\n"
    "  --config FILE     configuration (default: $CELLSIGHT_CONFIG, ./config/cellsight.yaml, <install>/config)\n"
    "  --log-level L     debug | info | warn | error | off (overrides log_level in the config)\n"
    "  --models DIR      model database (default: runtime.models_dir of the config, 'models')\n"
    "\n"
    "exit codes: 0 done, 1 failed while running, 2 bad input (arguments, configuration, data)\n";

// Options that take a value; everything else starting with "--" is a flag.
const std::set<std::string> kValueOptions = {"--config", "--log-level",   "--models",
                                             "--part",   "--seed",        "--pose",
                                             "--out",    "--calibration", "--random-catalogue"};

struct Args {
  std::string mode;
  std::map<std::string, std::string> values;
  std::set<std::string> flags;
};

int usage_error(const std::string& message) {
  std::fprintf(stderr, "cellsight: %s\n(run 'cellsight help' for usage)\n", message.c_str());
  return kExitUsage;
}

bool parse_args(int argc, char** argv, Args& args, std::string& error) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a.rfind("--", 0) == 0) {
      if (kValueOptions.count(a) != 0) {
        if (i + 1 >= argc) {
          error = a + " needs a value";
          return false;
        }
        args.values[a] = argv[++i];
      } else {
        args.flags.insert(a);
      }
    } else if (args.mode.empty()) {
      args.mode = a;
    } else {
      error = "unexpected argument '" + a + "'";
      return false;
    }
  }
  return true;
}

bool check_known(const Args& args, const std::set<std::string>& values, const std::set<std::string>& flags,
                 std::string& error) {
  for (const auto& [key, value] : args.values) {
    if (key != "--config" && key != "--log-level" && key != "--models" && values.count(key) == 0) {
      error = "option " + key + " does not apply to '" + args.mode + "'";
      return false;
    }
  }
  for (const auto& f : args.flags) {
    if (flags.count(f) == 0) {
      error = "unknown option " + f + " for '" + args.mode + "'";
      return false;
    }
  }
  return true;
}

bool parse_seed(const std::string& text, std::uint64_t& out) {
  char* end = nullptr;
  errno = 0;
  const unsigned long long v = std::strtoull(text.c_str(), &end, 10);
  if (text.empty() || *end != '\0' || errno != 0 || text[0] == '-') return false;
  out = v;
  return true;
}

// --seed and --pose of `sim` and `scan --sim`; the usage error, or "" when both are absent or valid.
std::string read_seed_and_pose(const Args& args, std::uint64_t& seed, std::optional<sim::PartPose>& pose) {
  if (const auto s = args.values.find("--seed"); s != args.values.end() && !parse_seed(s->second, seed)) {
    return "--seed '" + s->second + "': expected a whole number >= 0";
  }
  if (const auto p = args.values.find("--pose"); p != args.values.end()) {
    auto parsed = parse_pose(p->second);
    if (!parsed) return parsed.error().message;
    pose = *parsed;
  }
  return {};
}

int run_random_catalogue(const Args& args, const app::Config& config) {
  if (args.flags.count("--list") != 0 || args.values.count("--part") != 0 || args.values.count("--pose") != 0) {
    return usage_error("sim --random-catalogue takes only --seed and --out");
  }
  std::int64_t count = 0;
  const std::string& count_text = args.values.at("--random-catalogue");
  if (!parse_whole(count_text, sim::kRandomCatalogueMinParts, sim::kRandomCatalogueMaxParts, count)) {
    return usage_error("--random-catalogue '" + count_text + "': expected a whole number of parts from " +
                       std::to_string(sim::kRandomCatalogueMinParts) + " to " +
                       std::to_string(sim::kRandomCatalogueMaxParts));
  }
  std::uint64_t seed = 1;
  if (const auto s = args.values.find("--seed"); s != args.values.end() && !parse_seed(s->second, seed)) {
    return usage_error("--seed '" + s->second + "': expected a whole number >= 0");
  }
  const auto out = args.values.find("--out");
  if (out == args.values.end()) return usage_error("sim --random-catalogue needs --out FILE.yaml");
  if (auto ok = write_random_catalogue(config, static_cast<int>(count), seed, out->second); !ok) {
    std::fprintf(stderr, "cellsight: %s\n", ok.error().message.c_str());
    return kExitUsage;
  }
  return kExitOk;
}

int run_sim(const Args& args, const app::Config& config) {
  std::string error;
  if (!check_known(args, {"--part", "--seed", "--pose", "--out", "--random-catalogue"}, {"--list"}, error)) {
    return usage_error(error);
  }
  if (args.values.count("--random-catalogue") != 0) return run_random_catalogue(args, config);
  auto cell = app::make_sim_cell(config);
  if (!cell) return usage_error(cell.error().message);
  if (args.flags.count("--list") != 0) {
    const auto& parts = cell->catalogue();
    const bool roles = std::any_of(parts.begin(), parts.end(), [](const sim::PartSpec& p) {
      return p.role != sim::PartRole::kUnspecified || !p.family.empty();
    });
    if (roles) {
      std::printf("%-20s %9s %9s  %-8s %-20s %s\n", "part", "width_mm", "height_mm", "role", "family", "description");
    } else {
      std::printf("%-20s %9s %9s  %s\n", "part", "width_mm", "height_mm", "description");
    }
    for (const auto& p : parts) {
      if (roles) {
        const char* role = p.role == sim::PartRole::kTaught     ? "taught"
                           : p.role == sim::PartRole::kUntaught ? "untaught"
                                                                : "-";
        std::printf("%-20s %9.0f %9.0f  %-8s %-20s %s\n", p.name.c_str(), p.width_mm, p.height_mm, role,
                    p.family.empty() ? "-" : p.family.c_str(), p.description.c_str());
      } else {
        std::printf("%-20s %9.0f %9.0f  %s\n", p.name.c_str(), p.width_mm, p.height_mm, p.description.c_str());
      }
    }
    return kExitOk;
  }
  SimOptions options;
  const auto part = args.values.find("--part");
  const auto out = args.values.find("--out");
  if (part == args.values.end()) return usage_error("sim needs --part NAME (see 'cellsight sim --list')");
  if (out == args.values.end()) return usage_error("sim needs --out DIR");
  options.part = part->second;
  options.out_dir = out->second;
  if (std::string why = read_seed_and_pose(args, options.seed, options.pose); !why.empty()) return usage_error(why);
  if (cell->find_part(options.part) == nullptr) {
    return usage_error(cell->random_pass(options.part, 0).error().message);
  }
  if (auto ok = write_sim_pass(config, *cell, options); !ok) {
    std::fprintf(stderr, "cellsight: %s\n", ok.error().message.c_str());
    return kExitUsage;
  }
  return kExitOk;
}

int run_scan_mode(const Args& args, const app::Config& config) {
  std::string error;
  if (!check_known(args, {"--part", "--seed", "--pose", "--out", "--calibration"}, {"--sim", "--empty", "--ascii"},
                   error)) {
    return usage_error(error);
  }
  app::ScanOptions options;
  options.sim = args.flags.count("--sim") != 0;
  options.empty_carrier = args.flags.count("--empty") != 0;
  options.ascii = args.flags.count("--ascii") != 0;
  const auto out = args.values.find("--out");
  if (out == args.values.end()) return usage_error("scan needs --out SCAN.ply");
  options.out_path = out->second;
  if (const auto c = args.values.find("--calibration"); c != args.values.end()) options.calibration_path = c->second;
  if (options.sim && !options.empty_carrier) {
    const auto part = args.values.find("--part");
    if (part == args.values.end())
      return usage_error("scan --sim needs --part NAME or --empty (see 'cellsight sim --list')");
    options.part = part->second;
  }
  if (!options.sim && (args.values.count("--part") != 0 || options.empty_carrier)) {
    return usage_error("--part and --empty choose what the simulated cell scans; add --sim");
  }
  if (std::string why = read_seed_and_pose(args, options.seed, options.pose); !why.empty()) return usage_error(why);
  auto summary = run_scan(config, options);
  if (!summary) {
    std::fprintf(stderr, "cellsight: %s\n", summary.error().message.c_str());
    return kExitUsage;
  }
  std::printf("%zu points, %d frames, stripe width in band in %d of %d frames, final exposure %d us -> %s\n",
              summary->points, summary->frames, summary->frames_in_band, summary->frames_with_stripe,
              summary->final_exposure_us, options.out_path.c_str());
  return kExitOk;
}

}  // namespace

// Modes with files and positional words (DESIGN.md "Command line"): globals --config, --log-level and --models may
// stand anywhere; the rest goes to the mode.
int run_file_mode(const std::string& mode, int argc, char** argv) {
  std::string config_path, level_text, models_dir;
  std::vector<std::string> rest;
  bool seen_mode = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--config" || a == "--log-level" || a == "--models") {
      if (i + 1 >= argc) return usage_error(a + " needs a value");
      (a == "--config" ? config_path : a == "--log-level" ? level_text : models_dir) = argv[++i];
      continue;
    }
    if (!seen_mode && a == mode) {
      seen_mode = true;
      continue;
    }
    rest.push_back(a);
  }
  auto config = app::find_and_load_config(config_path);
  if (!config) {
    std::fprintf(stderr, "cellsight: bad configuration:\n%s\n", config.error().message.c_str());
    return kExitUsage;
  }
  if (level_text.empty()) level_text = config->log_level;
  log::Level level{};
  if (!log::parse_level(level_text.c_str(), level)) {
    return usage_error("--log-level '" + level_text + "': expected debug|info|warn|error|off");
  }
  log::set_level(level);
  if (!models_dir.empty()) config->runtime.models_dir = models_dir;
  const std::string& models = config->runtime.models_dir;
  if (mode == "teach") return run_teach(rest, *config, models);
  if (mode == "train") return run_train(rest, *config, models);
  if (mode == "parts") return run_parts(rest, *config, models);
  if (mode == "classify") return run_classify(rest, *config, models);
  if (mode == "eval") return run_eval(rest, *config, models);
  if (mode == "run") return run_run(rest, *config);
  if (mode == "perturb") return run_perturb(rest, *config);
  if (mode == "hmi-user") return run_hmi_user(rest, *config);
  return usage_error("unknown mode '" + mode + "'");
}

namespace {

// Index in argv of the mode word: the first word that is not a global option (--config, --log-level, --models and
// their values); argc when another option or nothing comes first.
int mode_word_index(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--config" || a == "--log-level" || a == "--models") {
      ++i;
      continue;
    }
    if (a.rfind("--", 0) == 0) return argc;
    return i;
  }
  return argc;
}

}  // namespace

int run_cli(int argc, char** argv) {
  Args args;
  std::string error;
  const int mode_at = mode_word_index(argc, argv);
  const std::string mode_word = mode_at < argc ? argv[mode_at] : "";
  if (mode_word == "teach" || mode_word == "train" || mode_word == "parts" || mode_word == "classify" ||
      mode_word == "eval" || mode_word == "run" || mode_word == "perturb" || mode_word == "hmi-user") {
    return run_file_mode(mode_word, argc, argv);
  }
  // `calibrate` has options of its own (--images DIR, ...): it gets every word after the mode.
  if (mode_word == "calibrate") {
    const int i = mode_at;
    Args globals;
    if (!parse_args(i, argv, globals, error)) return usage_error(error);
    const auto config_arg = globals.values.find("--config");
    auto config = app::find_and_load_config(config_arg == globals.values.end() ? "" : config_arg->second);
    if (!config) {
      std::fprintf(stderr, "cellsight: bad configuration:\n%s\n", config.error().message.c_str());
      return kExitUsage;
    }
    if (const auto level = globals.values.find("--log-level"); level != globals.values.end()) {
      log::Level parsed{};
      if (!log::parse_level(level->second.c_str(), parsed))
        return usage_error("--log-level '" + level->second + "': expected debug|info|warn|error|off");
      log::set_level(parsed);
    }
    const std::vector<std::string> rest(argv + i + 1, argv + argc);
    if (!rest.empty() && rest.front() == "support")
      return run_calibrate_support({rest.begin() + 1, rest.end()}, *config);
    return run_calibrate(rest, *config);
  }
  if (!parse_args(argc, argv, args, error)) return usage_error(error);
  if (args.mode.empty() || args.mode == "help" || args.flags.count("--help") != 0) {
    std::FILE* out = args.mode.empty() ? stderr : stdout;
    std::fputs(kUsage, out);
    std::fputs(kRunUsage, out);
    std::fputs(kHmiUserUsage, out);
    std::fputs(kUsageGlobals, out);
    return args.mode.empty() ? kExitUsage : kExitOk;
  }
  const auto config_arg = args.values.find("--config");
  auto config = app::find_and_load_config(config_arg == args.values.end() ? "" : config_arg->second);
  if (!config) {
    std::fprintf(stderr, "cellsight: bad configuration:\n%s\n", config.error().message.c_str());
    return kExitUsage;
  }
  std::string level_text = config->log_level;
  if (const auto level = args.values.find("--log-level"); level != args.values.end()) level_text = level->second;
  log::Level level{};
  if (!log::parse_level(level_text.c_str(), level))
    return usage_error("--log-level '" + level_text + "': expected debug|info|warn|error|off");
  log::set_level(level);
  CS_LOG_DEBUG("config", "using %s", config->source.c_str());

  if (args.mode == "sim") return run_sim(args, *config);
  if (args.mode == "scan") return run_scan_mode(args, *config);

  return usage_error("unknown mode '" + args.mode + "'");
}

}  // namespace cellsight::cli
