// `cellsight classify` (one decision per scan) and `cellsight eval` (labelled scans -> accuracy, confusion, pose).
#include "cli/classify_mode.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <numbers>
#include <optional>
#include <sstream>

#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"
#include "base/atomic_file.hpp"
#include "base/file_read.hpp"
#include "cli/cli.hpp"
#include "cli/eval_set.hpp"
#include "cli/mode_args.hpp"
#include "cli/perturb_mode.hpp"
#include "drivers/sim/sim_cell.hpp"
#include "formats/calibration_file.hpp"
#include "formats/input_file.hpp"
#include "formats/ply.hpp"
#include "formats/scan_file.hpp"
#include "formats/template_file.hpp"

namespace cellsight::cli {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

int fail(int code, const std::string& message) {
  std::fprintf(stderr, "cellsight: %s\n", message.c_str());
  return code;
}

std::string json_string(const std::string& s) {
  std::string out = "\"";
  for (const char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

std::string json_number(double v) {
  if (!std::isfinite(v)) return "null";
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.6g", v);
  return buf;
}

// Class index -> name (empty for -1).
using ClassNames = std::function<std::string(int)>;

std::string decision_json(const std::string& scan, const algo::Decision& d, std::string_view class_name,
                          const ClassNames& names) {
  std::ostringstream o;
  o << "{\"scan\": " << json_string(scan)
    << ", \"class\": " << (d.class_index >= 0 ? json_string(std::string(class_name)) : "null")
    << ", \"id\": " << d.part_id << ", \"status\": \"" << algo::to_string(d.source)
    << "\", \"probability\": " << json_number(d.probability) << ", \"pm_error\": " << json_number(d.pm_error)
    << ", \"pose\": ";
  // Added keys (issue 13): z, rx_deg, ry_deg (null where the geometry does not fix them) and their 1-sigma.
  const auto pose_object = [&o](double x, double y, double theta, double z, double rx, double ry) {
    o << "{\"x\": " << json_number(x) << ", \"y\": " << json_number(y)
      << ", \"theta_deg\": " << json_number(theta * kRadToDeg) << ", \"z\": " << json_number(z)
      << ", \"rx_deg\": " << json_number(rx * kRadToDeg) << ", \"ry_deg\": " << json_number(ry * kRadToDeg) << "}";
  };
  const auto sigma = [&d](algo::PoseAxis a) { return d.pose_sigma[static_cast<std::size_t>(a)]; };
  if (d.pose_valid) {
    pose_object(d.pose.x_m, d.pose.y_m, d.pose.theta_rad, d.z_m, d.rx_rad, d.ry_rad);
    o << ", \"sigma\": ";
    pose_object(sigma(algo::PoseAxis::kX), sigma(algo::PoseAxis::kY), sigma(algo::PoseAxis::kRz),
                sigma(algo::PoseAxis::kZ), sigma(algo::PoseAxis::kRx), sigma(algo::PoseAxis::kRy));
  } else {
    o << "null, \"sigma\": null";
  }
  // The two-way check of the chosen class (of the closest candidate when unknown), for diagnosis.
  o << ", \"coverage\": " << json_number(d.template_coverage) << ", \"outliers\": " << json_number(d.scan_outliers)
    << ", \"missing_mm2\": " << json_number(d.missing_area_m2 * 1e6)
    << ", \"extra_mm2\": " << json_number(d.extra_area_m2 * 1e6) << ", \"ms\": " << json_number(d.total_ms);
  // Added fields (issue 10): why, and what the cascade looked at, in the SVM's rank order.
  o << ", \"reason\": \"" << algo::to_string(d.unknown_reason) << "\", \"verified\": " << d.verified_count
    << ", \"candidates\": [";
  for (int i = 0; i < d.candidate_count; ++i) {
    const algo::CandidateOutcome& c = d.candidates[static_cast<std::size_t>(i)];
    if (i > 0) o << ", ";
    o << "{\"class\": " << json_string(names(c.class_index)) << ", \"p\": " << json_number(c.probability)
      << ", \"verified\": " << (c.verified ? "true" : "false") << ", \"passed\": " << (c.passed ? "true" : "false")
      << ", \"rejected_by\": "
      << (c.rejected_by == algo::RejectReason::kNone ? std::string("null")
                                                     : "\"" + std::string(algo::to_string(c.rejected_by)) + "\"")
      << ", \"value\": " << json_number(c.value) << ", \"limit\": " << json_number(c.limit)
      << ", \"pm_error\": " << json_number(c.pm_error)
      << ", \"pm_stopped_early\": " << (c.pm_stopped_early ? "true" : "false")
      << ", \"missing_mm2\": " << json_number(c.missing_area_m2 * 1e6)
      << ", \"extra_mm2\": " << json_number(c.extra_area_m2 * 1e6) << ", \"coverage\": " << json_number(c.coverage)
      << ", \"outliers\": " << json_number(c.outliers) << ", \"size_dev_mm\": " << json_number(c.size_dev_m * 1e3)
      << ", \"edge_dev_mm\": " << json_number(c.edge_dev_m * 1e3) << ", \"size_off_mm\": ["
      << json_number(c.size_off_xy_m[0] * 1e3) << ", " << json_number(c.size_off_xy_m[1] * 1e3)
      << "], \"edge_off_mm\": {\"left\": " << json_number(c.edge_off_m[0] * 1e3)
      << ", \"right\": " << json_number(c.edge_off_m[1] * 1e3) << ", \"bottom\": " << json_number(c.edge_off_m[2] * 1e3)
      << ", \"top\": " << json_number(c.edge_off_m[3] * 1e3) << "}"
      << ", \"hole_pattern_mm2\": " << json_number(c.hole_pattern_m2 * 1e6);
    if (c.verified) {
      o << ", \"check_pose\": {\"x\": " << json_number(c.check_pose.x_m) << ", \"y\": " << json_number(c.check_pose.y_m)
        << ", \"theta_deg\": " << json_number(c.check_pose.theta_rad * kRadToDeg) << "}";
    }
    o << ", \"ms\": " << json_number(c.ms) << "}";
  }
  o << "]}";
  return o.str();
}

// One line saying why a scan came out unknown: the gate, by how much, against which candidate.
std::string unknown_reason_text(const algo::Decision& d, const ClassNames& names) {
  std::string out = std::string(algo::to_string(d.unknown_reason));
  for (int i = 0; i < d.candidate_count; ++i) {
    const algo::CandidateOutcome& c = d.candidates[static_cast<std::size_t>(i)];
    if (!c.verified) continue;
    char buf[200];
    if (c.rejected_by == algo::RejectReason::kSize || c.rejected_by == algo::RejectReason::kEdge) {
      std::snprintf(buf, sizeof buf, "; %s (p %.2f): %s %.1f > %.1f mm", names(c.class_index).c_str(), c.probability,
                    std::string(algo::to_string(c.rejected_by)).c_str(), c.value * 1e3, c.limit * 1e3);
    } else if (c.rejected_by == algo::RejectReason::kPmError || c.rejected_by == algo::RejectReason::kUncovered ||
               c.rejected_by == algo::RejectReason::kOutliers) {
      std::snprintf(buf, sizeof buf, "; %s (p %.2f): %s %.3g > %.3g", names(c.class_index).c_str(), c.probability,
                    std::string(algo::to_string(c.rejected_by)).c_str(), c.value, c.limit);
    } else if (c.rejected_by == algo::RejectReason::kMissingArea || c.rejected_by == algo::RejectReason::kExtraArea ||
               c.rejected_by == algo::RejectReason::kHolePattern) {
      std::snprintf(buf, sizeof buf, "; %s (p %.2f): %s %.0f > %.0f mm2", names(c.class_index).c_str(), c.probability,
                    std::string(algo::to_string(c.rejected_by)).c_str(), c.value * 1e6, c.limit * 1e6);
    } else {
      std::snprintf(buf, sizeof buf, "; %s (p %.2f): %s (evidence %.0f mm2)", names(c.class_index).c_str(),
                    c.probability, std::string(algo::to_string(c.rejected_by)).c_str(), c.evidence_m2 * 1e6);
    }
    out += buf;
  }
  return out;
}

ClassNames class_names(const runtime::Recogniser& r) {
  return [&r](int i) { return std::string(r.class_name(i)); };
}

struct Options {
  app::RecogniserMode mode = app::RecogniserMode::kCascade;
  std::string calibration_path;
};

Expected<Options> common_options(const ModeArgs& args, const app::Config& config) {
  Options o;
  if (args.has("--svm-only") && args.has("--pm-only")) return make_error("--svm-only and --pm-only exclude each other");
  if (args.has("--svm-only")) o.mode = app::RecogniserMode::kSvmOnly;
  if (args.has("--pm-only")) o.mode = app::RecogniserMode::kPmOnly;
  const std::string* c = args.value("--calibration");
  o.calibration_path = c != nullptr ? *c : app::default_calibration_path(config);
  return o;
}

using TruthPose = algo::FullPose;  // cli/eval_set.hpp

struct LabelledScan {
  std::string path;
  std::string truth_class;  // folder name
  bool has_pose = false;
  TruthPose pose{};
  std::vector<algo::ScanPoint> points;  // filled for generated scans only
};

struct EvalTotals {
  std::vector<std::string> names;  // truth classes seen (taught or not) + "unknown"
  std::map<std::string, std::map<std::string, int>> confusion;
  int scans = 0, correct = 0, wrong = 0, unknown = 0, untaught = 0, untaught_unknown = 0;
  int svm_ranked = 0, svm_top1 = 0, svm_top2 = 0, decided = 0, decided_within_two = 0;
  std::vector<std::string> reasons;  // one line per unknown taught scan or wrong id
  std::vector<double> pose_mm, pose_deg, ms;
  // Per PoseAxis: |error| of every published value with a true one, and how many of them lay within 1 and 2 sigma;
  // published counts the accepted scans with a truth where the axis was published (the rest: invalid).
  std::array<std::vector<double>, algo::kPoseAxes> axis_error;
  std::array<int, algo::kPoseAxes> within_1s{}, within_2s{}, published{}, with_truth{};
  std::vector<double> features_ms, svm_ms, cascade_ms;  // the decision's stages (ms = their sum)
  std::map<std::string, int> sources;
};

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const std::size_t i = std::min(v.size() - 1, static_cast<std::size_t>(std::ceil(p * v.size())) - (p > 0 ? 1 : 0));
  return v[i];
}

void print_stats(const char* name, const std::vector<double>& v, const char* unit) {
  if (v.empty()) return;
  double sum = 0;
  for (double x : v) sum += x;
  std::printf("  %-12s mean %.3f  p95 %.3f  max %.3f %s  (%zu; median %.3f)\n", name, sum / v.size(),
              percentile(v, 0.95), *std::max_element(v.begin(), v.end()), unit, v.size(), percentile(v, 0.5));
}

// A taught scan of the database (scans/PART/NNNNN.cscan), so that the operator's screen and a technician can
// classify what was taught without exporting it first; its own header checksum and checked inflate guard it.
bool is_taught_scan(const std::string& path) {
  return fs::path(path).extension() == app::kTaughtScanExtension;
}

Expected<std::vector<algo::ScanPoint>> load_scan(const std::string& path) {
  if (!is_taught_scan(path)) return formats::load_ply_file(path);
  auto bytes = base::read_file(path, app::kMaxTaughtScanBytes);
  if (!bytes) return bytes.error();
  auto points = formats::parse_scan_file(*bytes);
  if (!points) return make_error(path + ": " + points.error().message);
  return points;
}

}  // namespace

int run_classify(const std::vector<std::string>& words, const app::Config& config, const std::string& models_dir) {
  ModeArgs args;
  std::string error;
  if (!parse_mode_args(words, {"--calibration"}, {"--json", "--svm-only", "--pm-only"}, args, error)) {
    return fail(kExitUsage, "classify: " + error);
  }
  if (args.positional.empty()) return fail(kExitUsage, "classify needs scan files: classify [--json] SCAN.ply ...");
  // Every scan is checked from a stat and its header before the models load: a device, a folder or a file whose
  // header declares more than it holds is refused at once, not after seconds of loading or a read without end.
  int failures = 0;
  std::vector<std::string> scans;
  for (const std::string& path : args.positional) {
    if (Status ok = is_taught_scan(path) ? formats::check_regular_file(path, "") : formats::check_ply_file(path); !ok) {
      std::fprintf(stderr, "cellsight: %s\n", ok.error().message.c_str());
      ++failures;
    } else {
      scans.push_back(path);
    }
  }
  if (scans.empty()) return kExitUsage;
  auto options = common_options(args, config);
  if (!options) return fail(kExitUsage, "classify: " + options.error().message);
  auto recogniser = app::make_recogniser(config, models_dir, options->calibration_path, options->mode);
  if (!recogniser) return fail(kExitUsage, recogniser.error().message);
  for (const std::string& path : scans) {
    auto points = load_scan(path);
    if (!points) {
      std::fprintf(stderr, "cellsight: %s\n", points.error().message.c_str());
      ++failures;
      continue;
    }
    const auto deadline = Clock::now() + std::chrono::milliseconds(config.runtime.deadline_ms);
    const algo::Decision d = (*recogniser)->recognise(*points, deadline);
    const std::string_view name = (*recogniser)->class_name(d.class_index);
    if (args.has("--json")) {
      std::printf("%s\n", decision_json(path, d, name, class_names(**recogniser)).c_str());
    } else {
      std::printf("%s: %s (%s, p %.3f, PM error %.3g", path.c_str(),
                  d.class_index >= 0 ? std::string(name).c_str() : "unknown",
                  std::string(algo::to_string(d.source)).c_str(), d.probability, d.pm_error);
      if (d.pose_valid) {
        std::printf(", pose x %.2f mm y %.2f mm theta %.3f deg", d.pose.x_m * 1e3, d.pose.y_m * 1e3,
                    d.pose.theta_rad * kRadToDeg);
      }
      std::printf(", %.1f ms)\n", d.total_ms);
    }
  }
  return failures == 0 ? kExitOk : kExitUsage;
}

namespace {

// eval --sim: generates the labelled set into `dir` first (it stays there: the same scans can be run again, or
// elsewhere, as PLY). An exit code when it fails (the message printed), nothing when the set is written.
std::optional<int> generate_eval_set(const ModeArgs& args, const app::Config& config, const std::string& models_dir,
                                     const Options& options, const app::PassPerturbation* perturb,
                                     const std::string& dir) {
  std::int64_t count = 0, seed = 100001;
  const std::string* c = args.value("--count");
  if (c == nullptr || !parse_whole(*c, 1, 100000, count)) return fail(kExitUsage, "eval --sim needs --count K");
  if (const std::string* s = args.value("--seed"); s != nullptr && !parse_whole(*s, 0, INT64_MAX, seed)) {
    return fail(kExitUsage, "eval: --seed '" + *s + "': expected a whole number");
  }
  auto db = app::ModelDb::open(models_dir, app::grid_spec(config), false);
  if (!db) return fail(kExitUsage, db.error().message);
  std::vector<std::string> parts;
  if (const std::string* list = args.value("--parts")) {
    std::stringstream in(*list);
    for (std::string p; std::getline(in, p, ',');) {
      if (!p.empty()) parts.push_back(p);
    }
  } else {
    for (const formats::PartEntry& p : db->manifest().parts) parts.push_back(p.name);
  }
  if (fs::exists(dir) && !fs::is_empty(dir)) return fail(kExitUsage, "eval --sim: " + dir + " is not empty");
  if (auto ok = generate_sim_scans(config, *db, parts, static_cast<int>(count), static_cast<std::uint64_t>(seed),
                                   options.calibration_path, dir, perturb);
      !ok) {
    return fail(kExitFailure, "eval --sim: " + ok.error().message);
  }
  return std::nullopt;
}

// DIR/<part>/*.ply, labelled with the folder's name and, when DIR/truth.csv lists it, the true pose; sorted by path.
std::vector<LabelledScan> labelled_scans(const std::string& dir, const std::map<std::string, TruthPose>& truth) {
  std::vector<LabelledScan> scans;
  for (const auto& entry : fs::directory_iterator(dir)) {
    if (!entry.is_directory()) continue;
    for (const auto& f : fs::directory_iterator(entry.path())) {
      if (f.path().extension() != ".ply") continue;
      LabelledScan s;
      s.path = f.path().string();
      s.truth_class = entry.path().filename().string();
      const std::string rel = s.truth_class + "/" + f.path().filename().string();
      if (const auto t = truth.find(rel); t != truth.end()) {
        s.has_pose = true;
        s.pose = t->second;
      }
      scans.push_back(std::move(s));
    }
  }
  std::sort(scans.begin(), scans.end(), [](const auto& a, const auto& b) { return a.path < b.path; });
  return scans;
}

// Error and sigma coverage per axis of an accepted scan with a true pose.
void count_pose_axes(const TruthPose& truth, const algo::Decision& d, EvalTotals& t) {
  using algo::PoseAxis;
  const std::array<double, algo::kPoseAxes> value = {d.pose.x_m, d.pose.y_m, d.z_m,
                                                     d.rx_rad,   d.ry_rad,   d.pose.theta_rad};
  for (std::size_t a = 0; a < algo::kPoseAxes; ++a) {
    if (!std::isfinite(truth.axis[a])) continue;
    ++t.with_truth[a];
    if (!std::isfinite(value[a])) continue;
    ++t.published[a];
    const double error = std::abs(value[a] - truth.axis[a]);
    t.axis_error[a].push_back(error * (a < 3 ? 1e3 : kRadToDeg));
    const double sigma = d.pose_sigma[a];
    if (error <= sigma) ++t.within_1s[a];
    if (error <= 2.0 * sigma) ++t.within_2s[a];
  }
}

// Counts one decision on a labelled scan: right, wrong or unknown, pose error, source, time, what the SVM alone
// would have said (its rank order is in the decision) and how far the cascade had to go.
void count_decision(const LabelledScan& s, const algo::Decision& d, const runtime::Recogniser& recogniser, bool taught,
                    EvalTotals& t) {
  const std::string decided = d.class_index >= 0 ? std::string(recogniser.class_name(d.class_index)) : "unknown";
  ++t.scans;
  ++t.confusion[s.truth_class][decided];
  ++t.sources[std::string(algo::to_string(d.source))];
  t.ms.push_back(d.total_ms);
  t.features_ms.push_back(d.features_ms);
  t.svm_ms.push_back(d.svm_ms);
  t.cascade_ms.push_back(d.total_ms - d.features_ms - d.svm_ms);
  if (!taught) {
    ++t.untaught;
    if (d.class_index < 0)
      ++t.untaught_unknown;
    else
      ++t.wrong;
  } else if (decided == s.truth_class) {
    ++t.correct;
    if (s.has_pose && d.pose_valid) {
      using algo::PoseAxis;
      t.pose_mm.push_back(std::hypot(d.pose.x_m - s.pose[PoseAxis::kX], d.pose.y_m - s.pose[PoseAxis::kY]) * 1e3);
      t.pose_deg.push_back(std::abs(d.pose.theta_rad - s.pose[PoseAxis::kRz]) * kRadToDeg);
      count_pose_axes(s.pose, d, t);
    }
  } else if (d.class_index < 0) {
    ++t.unknown;
  } else {
    ++t.wrong;
  }
  if (taught && d.candidate_count > 0) {
    ++t.svm_ranked;
    for (int r = 0; r < std::min(2, d.candidate_count); ++r) {
      if (recogniser.class_name(d.candidates[static_cast<std::size_t>(r)].class_index) != s.truth_class) continue;
      if (r == 0) ++t.svm_top1;
      ++t.svm_top2;
    }
  }
  if (d.accepted()) {
    ++t.decided;
    if (d.verified_count <= 2) ++t.decided_within_two;
  }
  if (taught && d.class_index < 0) {
    t.reasons.push_back(s.path + " (" + s.truth_class + "): " + unknown_reason_text(d, class_names(recogniser)));
  } else if (d.class_index >= 0 && decided != s.truth_class) {
    t.reasons.push_back(s.path + " (" + s.truth_class + "): WRONG id " + decided);
  }
}

void print_eval_totals(const EvalTotals& t, const std::string& dir) {
  const int taught_scans = t.scans - t.untaught;
  std::printf("eval of %d scans in %s (%d of taught parts, %d of parts not taught)\n", t.scans, dir.c_str(),
              taught_scans, t.untaught);
  if (taught_scans > 0) {
    std::printf("  accuracy     %.2f %% (%d correct, %d unknown, %d wrong)\n", 100.0 * t.correct / taught_scans,
                t.correct, t.unknown, t.wrong - (t.untaught - t.untaught_unknown));
  }
  if (t.untaught > 0) {
    std::printf("  not taught   %d of %d came out unknown\n", t.untaught_unknown, t.untaught);
  }
  std::printf("  wrong ids    %d\n", t.wrong);
  std::printf("  sources     ");
  for (const auto& [k, v] : t.sources) std::printf(" %s %d", k.c_str(), v);
  std::printf("\n");
  if (t.svm_ranked > 0) {
    std::printf("  SVM alone    top-1 %.2f %%, true class among its two most probable %.2f %% (%d taught scans)\n",
                100.0 * t.svm_top1 / t.svm_ranked, 100.0 * t.svm_top2 / t.svm_ranked, t.svm_ranked);
  }
  if (t.decided > 0) {
    std::printf("  verification %.2f %% of accepted scans decided after at most 2 candidates\n",
                100.0 * t.decided_within_two / t.decided);
  }
  for (const std::string& r : t.reasons) std::printf("  unknown/wrong %s\n", r.c_str());
  print_stats("pose xy", t.pose_mm, "mm");
  print_stats("pose theta", t.pose_deg, "deg");
  constexpr std::array<const char*, algo::kPoseAxes> kAxes = {"x", "y", "z", "rx", "ry", "theta"};
  for (std::size_t a = 0; a < algo::kPoseAxes; ++a) {
    if (t.with_truth[a] == 0) continue;
    const std::vector<double>& e = t.axis_error[a];
    const char* unit = a < 3 ? "mm" : "deg";
    if (e.empty()) {
      std::printf("  pose %-5s   published for 0 of %d (invalid: not fixed by the geometry)\n", kAxes[a],
                  t.with_truth[a]);
      continue;
    }
    const double n = static_cast<double>(e.size());
    std::printf(
        "  pose %-5s   |error| median %.3f  p95 %.3f  max %.3f %s; within 1 sigma %.1f %%, 2 sigma %.1f %% "
        "(published for %d of %d)\n",
        kAxes[a], percentile(e, 0.5), percentile(e, 0.95), *std::max_element(e.begin(), e.end()), unit,
        100.0 * t.within_1s[a] / n, 100.0 * t.within_2s[a] / n, t.published[a], t.with_truth[a]);
  }
  print_stats("time", t.ms, "ms");
  print_stats(" features", t.features_ms, "ms");  // scan -> part points -> grid -> 74 features
  print_stats(" svm", t.svm_ms, "ms");
  print_stats(" cascade", t.cascade_ms, "ms");  // Perfect Match + two-way checks of the candidates
}

// Rows: the true classes seen; columns: the taught parts in manifest order, then unknown.
void print_confusion(const EvalTotals& t, const formats::Manifest& manifest) {
  std::printf("confusion (rows: truth, columns: decision)\n");
  std::vector<std::string> columns;
  for (const formats::PartEntry& p : manifest.parts) columns.push_back(p.name);
  columns.push_back("unknown");
  std::printf("  %-20s", "");
  for (std::size_t c = 0; c < columns.size(); ++c) std::printf(" %4zu", c);
  std::printf("\n");
  for (const auto& [truth_class, row] : t.confusion) {
    std::printf("  %-20s", truth_class.c_str());
    for (const std::string& c : columns) {
      const auto it = row.find(c);
      std::printf(" %4d", it == row.end() ? 0 : it->second);
    }
    std::printf("\n");
  }
  for (std::size_t c = 0; c < columns.size(); ++c) std::printf("  column %zu = %s\n", c, columns[c].c_str());
}

}  // namespace

int run_eval(const std::vector<std::string>& words, const app::Config& config, const std::string& models_dir) {
  ModeArgs args;
  std::string error;
  if (!parse_mode_args(words, {"--scans", "--calibration", "--count", "--seed", "--parts", "--perturb"},
                       {"--json", "--svm-only", "--pm-only", "--sim"}, args, error) ||
      !args.positional.empty()) {
    return fail(kExitUsage,
                "eval: " + (error.empty() ? "unexpected argument '" + args.positional.front() + "'" : error));
  }
  const std::string* dir = args.value("--scans");
  if (dir == nullptr) return fail(kExitUsage, "eval needs --scans DIR (DIR/<part>/*.ply, optional DIR/truth.csv)");
  auto options = common_options(args, config);
  if (!options) return fail(kExitUsage, "eval: " + options.error().message);
  auto perturb = perturbation_option(args, config, options->calibration_path, app::kPerturbEval);
  if (!perturb) return fail(kExitUsage, "eval: " + perturb.error().message);
  if (*perturb && !args.has("--sim")) return fail(kExitUsage, "eval: --perturb applies to --sim only");
  if (args.has("--sim")) {
    if (auto failed = generate_eval_set(args, config, models_dir, *options, *perturb ? &**perturb : nullptr, *dir)) {
      return *failed;
    }
  }
  std::error_code ec;
  if (!fs::is_directory(*dir, ec)) return fail(kExitUsage, "eval: " + *dir + " is not a folder");
  auto truth = read_truth(*dir);
  if (!truth) return fail(kExitUsage, "eval: " + truth.error().message);
  const std::vector<LabelledScan> scans = labelled_scans(*dir, *truth);
  if (scans.empty()) return fail(kExitUsage, "eval: no DIR/<part>/*.ply under " + *dir);
  auto recogniser = app::make_recogniser(config, models_dir, options->calibration_path, options->mode);
  if (!recogniser) return fail(kExitUsage, recogniser.error().message);
  auto db = app::ModelDb::open(models_dir, app::grid_spec(config), false);
  if (!db) return fail(kExitUsage, db.error().message);

  EvalTotals t;
  for (const LabelledScan& s : scans) {
    auto points = formats::load_ply_file(s.path);
    if (!points) return fail(kExitUsage, points.error().message);
    const auto deadline = Clock::now() + std::chrono::milliseconds(config.runtime.deadline_ms);
    const algo::Decision d = (*recogniser)->recognise(*points, deadline);
    count_decision(s, d, **recogniser, db->find(s.truth_class) != nullptr, t);
    if (args.has("--json")) {
      const std::string decided =
          d.class_index >= 0 ? std::string((*recogniser)->class_name(d.class_index)) : "unknown";
      std::printf("%s\n", decision_json(s.path, d, decided, class_names(**recogniser)).c_str());
    }
  }
  print_eval_totals(t, *dir);
  print_confusion(t, db->manifest());
  return kExitOk;
}

}  // namespace cellsight::cli
