// The Parts and Debug pages' routes (parts_api.hpp): reads of the model database in the HMI's thread, the long
// actions as jobs.
#include "hmi/parts_api.hpp"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <map>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "base/file_read.hpp"
#include "formats/template_file.hpp"
#include "hmi/server_impl.hpp"

namespace cellsight::hmi {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr double kMmPerM = 1e3;
constexpr double kMm2PerM2 = 1e6;
constexpr std::size_t kMaxSummaryBytes = 64 * 1024;  // summary.txt shown on the page
constexpr std::size_t kMaxReviewScansListed = 500;
constexpr int kMaxScanNumber = 99999;
constexpr std::uint8_t kOpaque = 255;

struct Context {
  JobRunner* jobs;
  PartsApiParams params;
};

int send_bytes(mg_connection* conn, const char* type, const std::vector<unsigned char>& bytes) {
  mg_response_header_start(conn, 200);
  mg_response_header_add(conn, "Content-Type", type, -1);
  mg_response_header_add(conn, "Content-Length", std::to_string(bytes.size()).c_str(), -1);
  mg_response_header_add(conn, "Cache-Control", "no-store", -1);
  mg_response_header_add(conn, "X-Content-Type-Options", "nosniff", -1);
  mg_response_header_send(conn);
  mg_write(conn, bytes.data(), bytes.size());
  return 200;
}

json thresholds_json(const formats::PartThresholds& t) {
  if (!t.learnt) return {{"learnt", false}};
  return {{"learnt", true},
          {"max_error", t.max_error},
          {"max_missing_mm2", t.max_missing_area_m2 * kMm2PerM2},
          {"max_extra_mm2", t.max_extra_area_m2 * kMm2PerM2},
          {"max_uncovered", t.max_uncovered},
          {"max_outliers", t.max_outliers},
          {"max_hole_pattern_mm2", t.max_hole_pattern_m2 * kMm2PerM2},
          {"max_size_dev_mm", t.max_size_dev_m * kMmPerM}};
}

// GET /api/parts: the manifest and the templates' headers (no template body is read: cheap).
int get_parts(const Context& c, const Request& r) {
  auto db = app::ModelDb::open(c.params.models_dir, c.params.grid, false);
  if (!db) {  // nothing taught yet, or a damaged manifest: the page says which
    return send_json(r.conn, 200,
                     {{"parts", json::array()}, {"total_bytes", 0}, {"trained", false}, {"error", db.error().message}});
  }
  json parts = json::array();
  for (const formats::PartEntry& p : db->manifest().parts) {
    auto info = formats::read_template_info(db->path_of(p.template_file));
    parts.push_back({{"name", p.name},
                     {"id", p.id},
                     {"scans", p.scans.size()},
                     {"flagged", p.flagged},
                     {"confusable", p.confusable},
                     {"taught_at", p.taught_at},
                     {"template_bytes", info ? json(info->file_bytes) : json(nullptr)},
                     {"template_error", info ? json(nullptr) : json(info.error().message)},
                     {"thresholds", thresholds_json(p.thresholds)}});
  }
  const app::ModelFootprint f = app::model_footprint(*db);
  const formats::SvmEntry& svm = db->manifest().svm;
  const std::string stale = db->svm_stale_reason();
  return send_json(r.conn, 200,
                   {{"parts", parts},
                    {"total_bytes", f.total_bytes()},
                    {"template_bytes", f.template_bytes},
                    {"svm_bytes", f.svm_bytes},
                    {"trained", svm.present && stale.empty()},
                    {"stale_reason", stale.empty() ? json(nullptr) : json(stale)},
                    {"svm",
                     {{"trained_at", svm.trained_at},
                      {"test_accuracy", svm.test_accuracy},
                      {"cv_accuracy", svm.cv_accuracy},
                      {"test_scans", svm.test_scans},
                      {"active_features", svm.active_features}}}});
}

// The part's template, opened and checked whole (TemplateFile), or an HTTP error already sent (status in `status`).
std::optional<formats::TemplateFile> open_template(const Context& c, const Request& r, const std::string& name,
                                                   int& status) {
  if (!formats::valid_part_name(name)) {
    status = send_error(r.conn, 400, "not a part name: letters, digits, '_' and '-', 1 to 64 characters");
    return std::nullopt;
  }
  auto db = app::ModelDb::open(c.params.models_dir, c.params.grid, false);
  if (!db) {
    status = send_error(r.conn, 404, db.error().message);
    return std::nullopt;
  }
  const formats::PartEntry* p = db->find(name);
  if (p == nullptr) {
    status = send_error(r.conn, 404, "no part '" + name + "'");
    return std::nullopt;
  }
  auto file = formats::TemplateFile::open(db->path_of(p->template_file), c.params.grid);
  if (!file) {
    status = send_error(r.conn, 500, file.error().message);
    return std::nullopt;
  }
  return std::move(*file);
}

// The depth image of the template as the camera sees it: per x-y column of the grid the occupied cell nearest the
// camera (+z), coloured by depth over the part's own depth range (turbo: blue far, red near), transparent where the
// column is empty; y up.
std::vector<unsigned char> depth_png(const formats::TemplateFile& t, const algo::GridSpec& g) {
  cv::Mat1b depth(g.ny, g.nx, std::uint8_t{0});
  cv::Mat1b occupied(g.ny, g.nx, std::uint8_t{0});
  int z_lo = g.nz, z_hi = -1;
  for (const algo::SurfaceCell& s : t.surface_cells()) {
    z_lo = std::min<int>(z_lo, s.z);
    z_hi = std::max<int>(z_hi, s.z);
  }
  const double span = std::max(1, z_hi - z_lo);
  constexpr double kLevels = 254.0;  // 1..255: 0 stays "empty" before the colour map
  for (const algo::SurfaceCell& s : t.surface_cells()) {
    if (s.x >= g.nx || s.y >= g.ny) continue;
    const int row = g.ny - 1 - s.y;
    const auto v = static_cast<std::uint8_t>(1.0 + kLevels * (s.z - z_lo) / span);
    if (v > depth(row, s.x)) depth(row, s.x) = v;
    occupied(row, s.x) = kOpaque;
  }
  cv::Mat bgr;
  cv::applyColorMap(depth, bgr, cv::COLORMAP_TURBO);
  cv::Mat bgra;
  cv::cvtColor(bgr, bgra, cv::COLOR_BGR2BGRA);
  cv::Mat alpha_channel[] = {occupied};
  const int from_to[] = {0, 3};
  cv::mixChannels(alpha_channel, 1, &bgra, 1, from_to, 1);
  std::vector<unsigned char> png;
  cv::imencode(".png", bgra, png);
  return png;
}

// The surface cells, every k-th so that at most kMaxPointsJson remain, in mm about the centroid (x right, y up, z
// toward the camera).
json surface_points(const formats::TemplateFile& t, const algo::GridSpec& g) {
  const auto cells = t.surface_cells();
  const std::size_t stride = std::max<std::size_t>(1, (cells.size() + kMaxPointsJson - 1) / kMaxPointsJson);
  const Eigen::Vector3d c(t.centroid_m().x(), t.centroid_m().y(), t.centroid_z_m());
  json points = json::array();
  constexpr double kTenthMm = 10.0;
  const auto round = [](double mm) { return std::round(mm * kTenthMm) / kTenthMm; };
  for (std::size_t i = 0; i < cells.size(); i += stride) {
    const Eigen::Vector3d p = (g.centre(cells[i].x, cells[i].y, cells[i].z) - c) * kMmPerM;
    points.push_back({round(p.x()), round(p.y()), round(p.z())});
  }
  return {{"points", points}, {"cells", cells.size()}, {"resolution_mm", g.resolution_m * kMmPerM}};
}

// GET /api/parts/NAME/template.png and /api/parts/NAME/points.json.
int get_part_file(const Context& c, const Request& r) {
  const std::string rest = r.uri.substr(std::strlen("/api/parts/"));
  const std::size_t slash = rest.find('/');
  if (slash == std::string::npos) return send_error(r.conn, 404, "no such resource: " + r.uri);
  const std::string name = rest.substr(0, slash);
  const std::string what = rest.substr(slash + 1);
  if (what != "template.png" && what != "points.json") return send_error(r.conn, 404, "no such resource: " + r.uri);
  int status = 0;
  const auto t = open_template(c, r, name, status);
  if (!t) return status;
  if (what == "points.json") return send_json(r.conn, 200, surface_points(*t, c.params.grid));
  const std::vector<unsigned char> png = depth_png(*t, c.params.grid);
  if (png.empty()) return send_error(r.conn, 500, "the picture could not be encoded");
  return send_bytes(r.conn, "image/png", png);
}

// A started job's answer, or 409 when another one runs.
int job_started(const Request& r, Expected<std::uint64_t> id) {
  if (!id) return send_error(r.conn, 409, id.error().message);
  return send_json(r.conn, 200, {{"job", *id}});
}

JobHooks reload_when_done(const Context& c) {
  JobHooks h;
  h.on_done = [changed = c.params.models_changed](const JobView& v) {
    if (v.state == "done" && changed) changed();
  };
  return h;
}

int post_delete(const Context& c, const Request& r) {
  const json body = read_json_body(r);
  if (!body.is_object() || !body.contains("name") || !body["name"].is_string()) {
    return send_error(r.conn, 400, "expected {\"name\": PART}");
  }
  const std::string name = body["name"].get<std::string>();
  if (!formats::valid_part_name(name)) {
    return send_error(r.conn, 400, "not a part name: letters, digits, '_' and '-', 1 to 64 characters");
  }
  auto db = app::ModelDb::open(c.params.models_dir, c.params.grid, false);
  if (!db) return send_error(r.conn, 404, db.error().message);
  if (db->find(name) == nullptr) return send_error(r.conn, 404, "no part '" + name + "'");
  return job_started(r,
                     c.jobs->start(JobKind::kDelete, {"parts", "delete", name}, "delete " + name, reload_when_done(c)));
}

// What the page shows of a training report (report.yaml and summary.txt of app/train_report).
json train_summary(const std::string& dir) {
  json j = {{"dir", dir}};
  try {
    const YAML::Node y = YAML::LoadFile(dir + "/report.yaml");
    const auto num = [](const YAML::Node& n) { return n && !n.IsNull() ? json(n.as<double>()) : json(nullptr); };
    j["classes"] = y["classes"].as<std::vector<std::string>>();
    j["train_samples"] = y["train_samples"].as<int>();
    j["test_samples"] = y["test_samples"].as<int>();
    j["stopped"] = y["stopped"].as<bool>();
    j["seconds"] = num(y["seconds"]);
    j["target_accuracy"] = num(y["target_accuracy"]);
    const YAML::Node svm = y["classifiers"]["svm"];
    j["accuracy"] = num(svm["test_accuracy"]);
    j["cv_accuracy"] = num(svm["cv_accuracy"]);
    j["active_features"] = svm["active_features"].as<int>();
    j["parameters"] = svm["parameters"].as<std::string>();
    json recall = json::object();
    for (const auto& kv : svm["per_class_recall"]) recall[kv.first.as<std::string>()] = num(kv.second);
    j["per_class"] = recall;
    j["confusion"] = svm["confusion"].as<std::vector<std::vector<int>>>();
  } catch (const YAML::Exception& e) {
    j["error"] = dir + "/report.yaml: " + e.what();
  }
  if (auto text = base::read_file(dir + "/summary.txt", kMaxSummaryBytes)) j["summary"] = *text;
  return j;
}

int post_retrain(const Context& c, const Request& r) {
  if (c.jobs->busy()) return send_error(r.conn, 409, "a job is running: " + c.jobs->view().title);
  // A fresh folder per training (train refuses to write into a full one; a new one keeps the earlier reports).
  const fs::path reports = fs::path(c.params.models_dir) / "reports";
  std::error_code ec;
  fs::create_directories(reports, ec);
  if (ec) return send_error(r.conn, 500, reports.string() + ": " + ec.message());
  const auto stamp =
      std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
          .count();
  const std::string dir = (reports / ("train-" + std::to_string(stamp))).string();
  JobHooks hooks = reload_when_done(c);
  hooks.result = [dir](const JobView& v) { return v.state == "done" ? train_summary(dir) : json(nullptr); };
  return job_started(
      r, c.jobs->start(JobKind::kTrain, {"train", "--progress", "--report", dir}, "retrain", std::move(hooks)));
}

bool all_digits(const std::string& s, std::size_t max_digits) {
  return !s.empty() && s.size() <= max_digits &&
         std::all_of(s.begin(), s.end(), [](char ch) { return ch >= '0' && ch <= '9'; });
}

// GET /api/debug/scans: the review ring's scans (newest first) and every part's taught scans.
int get_debug_scans(const Context& c, const Request& r) {
  std::vector<unsigned long long> ids;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(fs::path(c.params.models_dir) / "review", ec)) {
    const std::string id = e.path().filename().string();
    if (!review_scan_path(c.params.models_dir, id).empty()) ids.push_back(std::stoull(id));
  }
  std::sort(ids.rbegin(), ids.rend());
  if (ids.size() > kMaxReviewScansListed) ids.resize(kMaxReviewScansListed);
  json review = json::array();
  for (const unsigned long long id : ids) review.push_back(std::to_string(id));
  json parts = json::array();
  if (auto db = app::ModelDb::open(c.params.models_dir, c.params.grid, false)) {
    for (const formats::PartEntry& p : db->manifest().parts) {
      json scans = json::array();
      for (std::size_t i = 0; i < p.scans.size(); ++i) {
        scans.push_back({{"ref", p.name + ":" + std::to_string(i + 1)},
                         {"file", fs::path(p.scans[i].file).filename().string()},
                         {"source", p.scans[i].source}});
      }
      parts.push_back({{"name", p.name}, {"scans", scans}});
    }
  }
  return send_json(r.conn, 200, {{"review", review}, {"parts", parts}});
}

// A scan reference of the page -> the file; "" with `why` set when it names none.
std::string scan_of_ref(const Context& c, const std::optional<app::ModelDb>& db, const std::string& ref,
                        std::string& why) {
  if (all_digits(ref, kMaxReviewIdDigits)) {
    std::string path = review_scan_path(c.params.models_dir, ref);
    if (path.empty()) why = "no stored review scan " + ref;
    return path;
  }
  const std::size_t colon = ref.find(':');
  const std::string name = ref.substr(0, colon);
  const std::string number = colon == std::string::npos ? "" : ref.substr(colon + 1);
  if (!formats::valid_part_name(name) || !all_digits(number, std::to_string(kMaxScanNumber).size())) {
    constexpr std::size_t kShown = 80;  // of a bad reference, in the message
    why = std::string("'")
              .append(ref, 0, kShown)
              .append("': expected a review id (1 to 12 digits) or PART:N (a part's taught scan N)");
    return {};
  }
  const formats::PartEntry* p = db ? db->find(name) : nullptr;
  const std::size_t n = std::stoul(number);
  if (p == nullptr || n < 1 || n > p->scans.size()) {
    why = "no taught scan " + number + " of part '" + name + "'";
    return {};
  }
  return db->path_of(p->scans[n - 1].file);
}

int post_debug(const Context& c, const Request& r) {
  const json body = read_json_body(r);
  if (!body.is_object() || !body.contains("mode") || !body["mode"].is_string() || !body.contains("files") ||
      !body["files"].is_array()) {
    return send_error(r.conn, 400, "expected {\"mode\": \"svm\"|\"pm\"|\"cascade\", \"files\": [...]}");
  }
  const std::string mode = body["mode"].get<std::string>();
  if (mode != "svm" && mode != "pm" && mode != "cascade") {
    return send_error(r.conn, 400, "mode must be svm, pm or cascade");
  }
  const json& files = body["files"];
  if (files.empty() || files.size() > kMaxDebugFiles) {
    return send_error(r.conn, 400, "give 1 to " + std::to_string(kMaxDebugFiles) + " scans");
  }
  std::optional<app::ModelDb> db;
  if (auto opened = app::ModelDb::open(c.params.models_dir, c.params.grid, false)) db = std::move(*opened);
  std::vector<std::string> args = {"classify", "--json"};
  if (mode != "cascade") args.push_back(mode == "svm" ? "--svm-only" : "--pm-only");
  std::map<std::string, std::string> ref_of_path;
  const std::size_t first_file = args.size();
  for (const json& f : files) {
    if (!f.is_string()) return send_error(r.conn, 400, "each scan is named by a string");
    std::string why;
    const std::string path = scan_of_ref(c, db, f.get<std::string>(), why);
    if (path.empty()) return send_error(r.conn, 400, why);
    if (ref_of_path.emplace(path, f.get<std::string>()).second) args.push_back(path);
  }
  JobHooks hooks;
  // Each decision carries the page's name of its scan ("ref"); classify goes on past a scan it cannot read.
  hooks.result = [ref_of_path](const JobView& v) {
    json out = json::array();
    for (json d : v.result.is_array() ? v.result : json::array()) {
      const auto it = ref_of_path.find(d.value("scan", ""));
      d["ref"] = it != ref_of_path.end() ? json(it->second) : json(nullptr);
      out.push_back(std::move(d));
    }
    return out;
  };
  const std::size_t n = args.size() - first_file;
  const std::string title = "debug " + mode + " (" + std::to_string(n) + (n == 1 ? " scan)" : " scans)");
  return job_started(r, c.jobs->start(JobKind::kClassify, std::move(args), title, std::move(hooks)));
}

}  // namespace

std::string review_scan_path(const std::string& models_dir, const std::string& ref) {
  if (!all_digits(ref, kMaxReviewIdDigits)) return {};
  const fs::path path = fs::path(models_dir) / "review" / ref / "scan.ply";
  std::error_code ec;
  return fs::is_regular_file(path, ec) ? path.string() : std::string();
}

std::vector<Route> parts_routes(JobRunner& jobs, PartsApiParams params) {
  const auto c = std::make_shared<const Context>(Context{&jobs, std::move(params)});
  const auto bind = [c](int (*fn)(const Context&, const Request&)) {
    return [c, fn](const Request& r) { return fn(*c, r); };
  };
  return {
      {"GET", "/api/parts", Role::kNone, bind(get_parts)},
      {"GET", "/api/parts/", Role::kNone, bind(get_part_file)},
      {"POST", "/api/parts/delete", Role::kMaintenance, bind(post_delete)},
      {"POST", "/api/retrain", Role::kMaintenance, bind(post_retrain)},
      {"GET", "/api/job", Role::kNone,
       [c](const Request& r) { return send_json(r.conn, 200, to_json(c->jobs->view())); }},
      {"POST", "/api/job/cancel", Role::kMaintenance,
       [c](const Request& r) {
         if (!c->jobs->cancel()) return send_error(r.conn, 409, "no job is running");
         return send_json(r.conn, 200, {{"cancelling", c->jobs->view().id}});
       }},
      {"GET", "/api/debug/scans", Role::kNone, bind(get_debug_scans)},
      {"POST", "/api/debug", Role::kMaintenance, bind(post_debug)},
  };
}

}  // namespace cellsight::hmi
