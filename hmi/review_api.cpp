// The Review page's routes and the teach session (see review_api.hpp).
#include "hmi/review_api.hpp"

#include <chrono>
#include <thread>

#include "base/file_read.hpp"
#include "formats/manifest.hpp"
#include "hmi/server_impl.hpp"

namespace cellsight::hmi {
namespace {

constexpr int kMaxPasses = 50;

// ids from a JSON array of numbers; empty when malformed.
std::vector<std::uint64_t> ids_of(const nlohmann::json& value) {
  std::vector<std::uint64_t> ids;
  if (!value.is_array() || value.empty() || value.size() > 200) return {};
  for (const auto& v : value) {
    if (!v.is_number_unsigned()) return {};
    ids.push_back(v.get<std::uint64_t>());
  }
  return ids;
}

// name and part_id of a body, checked as `teach` checks them; an error message or "".
std::string check_part(const nlohmann::json& body, std::string& name, int& part_id) {
  if (!body.is_object() || !body.contains("name") || !body["name"].is_string()) return "name: a part name is needed";
  name = body["name"].get<std::string>();
  if (!formats::valid_part_name(name)) {
    return "name '" + name + "': letters, digits, '_', '-' and '.', 1-64 characters, not starting with '.'";
  }
  if (!body.contains("part_id") || !body["part_id"].is_number_integer()) return "part_id: a PLC id 1-65535 is needed";
  part_id = body["part_id"].get<int>();
  if (part_id < 1 || part_id > 65535) return "part_id " + std::to_string(part_id) + ": must be 1-65535";
  return {};
}

}  // namespace

ReviewApi::ReviewApi(ReviewStore& store, JobRunner& jobs, CellCommands& cell)
    : store_(store), jobs_(jobs), cell_(cell) {
  store_.set_on_stored([this](const ReviewEntry& entry) { on_stored(entry); });
}

std::vector<Route> ReviewApi::routes() {
  return {
      {"GET", "/api/review", Role::kNone, [this](const Request& r) { return list(r); }},
      {"GET", "/api/review/", Role::kNone, [this](const Request& r) { return image(r); }},
      {"POST", "/api/review/teach", Role::kOperator, [this](const Request& r) { return teach_picked(r); }},
      {"POST", "/api/review/discard", Role::kOperator, [this](const Request& r) { return discard(r); }},
      {"GET", "/api/teach", Role::kNone, [this](const Request& r) { return send_json(r.conn, 200, teach_json()); }},
      {"POST", "/api/teach/start", Role::kOperator, [this](const Request& r) { return teach_start(r); }},
      {"POST", "/api/teach/stop", Role::kOperator, [this](const Request& r) { return teach_stop(r); }},
  };
}

int ReviewApi::list(const Request& r) {
  nlohmann::json entries = nlohmann::json::array();
  for (const ReviewEntry& e : store_.list()) {
    nlohmann::json item = e.info;
    item["image"] = "/api/review/" + std::to_string(e.id) + "/depth.png";
    entries.push_back(std::move(item));
  }
  return send_json(r.conn, 200, {{"entries", entries}, {"stored", store_.stored()}, {"failed", store_.failed()}});
}

int ReviewApi::image(const Request& r) {
  // /api/review/<id>/depth.png
  const std::string rest = r.uri.substr(std::string("/api/review/").size());
  const auto slash = rest.find('/');
  if (slash == std::string::npos || rest.substr(slash) != "/depth.png" || slash == 0 || slash > 12 ||
      rest.find_first_not_of("0123456789") != slash) {
    return send_error(r.conn, 404, "no such resource: " + r.uri);
  }
  const std::uint64_t id = std::stoull(rest.substr(0, slash));
  if (!store_.find(id)) return send_error(r.conn, 404, "no review entry " + std::to_string(id));
  constexpr std::size_t kMaxImageBytes = std::size_t{8} << 20;  // a 1200 x 1200 picture is well below
  const auto read = base::read_file(store_.image_path(id), kMaxImageBytes);
  const std::string png = read ? *read : std::string();
  if (png.empty()) return send_error(r.conn, 404, "entry " + std::to_string(id) + " has no image");
  return send_png(r, png);
}

Expected<std::uint64_t> ReviewApi::start_teach(const std::string& name, int part_id,
                                               const std::vector<std::uint64_t>& ids, bool for_session) {
  std::vector<std::string> args = {"teach", "--part", name, "--id", std::to_string(part_id)};
  for (const std::uint64_t id : ids) {
    if (!store_.find(id)) return make_error("no review entry " + std::to_string(id));
    args.push_back(store_.scan_path(id));
  }
  const std::string title = "teach " + name + " (" + std::to_string(ids.size()) + " scans)";
  JobHooks hooks;
  hooks.on_done = [this, ids, for_session](const JobView& job) {
    if (job.state == "done") (void)store_.remove(ids);
    const std::lock_guard<std::mutex> lock(mutex_);
    if (for_session) {
      session_.job = job.id;
      session_.state = job.state == "done" ? "done" : "failed";
      session_.message = job.state == "done" ? "taught; retrain to recognise it"
                                             : (job.log_tail.empty() ? job.state : job.log_tail.back());
    }
  };
  return jobs_.start(JobKind::kTeach, std::move(args), title, std::move(hooks));
}

int ReviewApi::teach_picked(const Request& r) {
  const nlohmann::json body = read_json_body(r);
  std::string name;
  int part_id = 0;
  if (const std::string why = check_part(body, name, part_id); !why.empty()) return send_error(r.conn, 400, why);
  const std::vector<std::uint64_t> ids = body.contains("ids") ? ids_of(body["ids"]) : std::vector<std::uint64_t>{};
  if (ids.empty()) return send_error(r.conn, 400, "ids: a list of review entries (1-200) is needed");
  auto job = start_teach(name, part_id, ids, false);
  if (!job) return send_error(r.conn, 409, job.error().message);
  return send_json(r.conn, 200, {{"job", *job}});
}

int ReviewApi::discard(const Request& r) {
  const nlohmann::json body = read_json_body(r);
  const std::vector<std::uint64_t> ids =
      body.is_object() && body.contains("ids") ? ids_of(body["ids"]) : std::vector<std::uint64_t>{};
  if (ids.empty()) return send_error(r.conn, 400, "ids: a list of review entries (1-200) is needed");
  return send_json(r.conn, 200, {{"removed", store_.remove(ids)}});
}

bool ReviewApi::command(drivers::CommandCode code, std::uint32_t arg) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(1);
  while (!cell_.post(code, arg)) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  while (cell_.fate() == CellCommands::Fate::kPending) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return cell_.fate() == CellCommands::Fate::kDone;
}

int ReviewApi::teach_start(const Request& r) {
  const nlohmann::json body = read_json_body(r);
  std::string name;
  int part_id = 0;
  if (const std::string why = check_part(body, name, part_id); !why.empty()) return send_error(r.conn, 400, why);
  const int passes = body.contains("passes") && body["passes"].is_number_integer() ? body["passes"].get<int>() : 0;
  if (passes < 1 || passes > kMaxPasses) {
    return send_error(r.conn, 400, "passes: 1-" + std::to_string(kMaxPasses) + " passes are needed");
  }
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (session_.state == "collecting" || session_.state == "teaching") {
      return send_error(r.conn, 409, "already teaching " + session_.name);
    }
    session_ = Session{"collecting", name, part_id, passes, {}, {}, 0};
  }
  // Through the loop's command path, as the PLC's ENTER_TEACH: it applies from the next pass.
  if (!command(drivers::CommandCode::kEnterTeach, static_cast<std::uint32_t>(part_id))) {
    const std::lock_guard<std::mutex> lock(mutex_);
    session_.state = "failed";
    session_.message = "the loop refused teach mode";
    return send_error(r.conn, 409, session_.message);
  }
  return send_json(r.conn, 200, teach_json());
}

int ReviewApi::teach_stop(const Request& r) {
  const nlohmann::json body = read_json_body(r);
  const bool teach_now = body.is_object() && body.value("teach_now", false);
  (void)command(drivers::CommandCode::kLeaveTeach, 0);
  Session s;
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (session_.state != "collecting") return send_error(r.conn, 409, "not collecting passes");
    session_.state = "stopped";
    s = session_;
  }
  if (teach_now && !s.collected.empty()) {
    auto job = start_teach(s.name, s.part_id, s.collected, true);
    const std::lock_guard<std::mutex> lock(mutex_);
    if (!job) {
      session_.state = "failed";
      session_.message = job.error().message;
    } else if (session_.state == "stopped") {
      session_.state = "teaching";
      session_.job = *job;
    }
  }
  return send_json(r.conn, 200, teach_json());
}

// Writer thread: a pass of the part being taught was stored.
void ReviewApi::on_stored(const ReviewEntry& entry) {
  if (entry.info.value("kind", "") != "teach") return;
  std::vector<std::uint64_t> ids;
  std::string name;
  int part_id = 0;
  {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (session_.state != "collecting" || entry.info.value("teach_part_id", 0) != session_.part_id) return;
    session_.collected.push_back(entry.id);
    if (static_cast<int>(session_.collected.size()) < session_.wanted) return;
    session_.state = "teaching";
    ids = session_.collected;
    name = session_.name;
    part_id = session_.part_id;
  }
  (void)command(drivers::CommandCode::kLeaveTeach, 0);
  auto job = start_teach(name, part_id, ids, true);
  const std::lock_guard<std::mutex> lock(mutex_);
  if (session_.state == "teaching" && session_.job == 0 && job) session_.job = *job;
  if (!job) {
    session_.state = "failed";
    session_.message = job.error().message;
  }
}

nlohmann::json ReviewApi::teach_json() const {
  const std::lock_guard<std::mutex> lock(mutex_);
  return {{"state", session_.state},
          {"name", session_.name},
          {"part_id", session_.part_id},
          {"passes_wanted", session_.wanted},
          {"passes_kept", session_.collected.size()},
          {"message", session_.message},
          {"job", session_.job},
          {"loop_teaching_part_id", cell_.teaching_part_id()}};
}

}  // namespace cellsight::hmi
