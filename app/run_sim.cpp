// `cellsight run --sim`: the simulated conveyor's feed, the oracle and the truth log.
#include "app/run_sim.hpp"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cinttypes>
#include <cstdlib>
#include <cstring>
#include <numbers>
#include <random>
#include <span>
#include <string_view>
#include <vector>

#include "app/model_db.hpp"
#include "app/recognition.hpp"
#include "app/sim_setup.hpp"
#include "drivers/log.hpp"
#include "formats/template_file.hpp"

namespace cellsight::app {

using runtime::LoopObserver;
using runtime::PartRecord;
using runtime::TriggerSource;

namespace {

constexpr const char* kComponent = "run";
constexpr std::size_t kQueuedPassesAhead = 2;  // parts waiting on the simulated conveyor
constexpr std::size_t kAcqRing = 256;          // acquisition id -> simulated pass, for the truth log
constexpr double kDegPerRad = 180.0 / std::numbers::pi;

// The simulated conveyor's parts: drawn once at start-up, then fed in order (cycling for long runs).
struct SimFeed {
  std::vector<sim::PassSpec> passes;
  std::vector<int> part_index;  // into the catalogue, per pass
};

Expected<SimFeed> draw_passes(const sim::SimCell& cell, std::uint64_t seed, std::uint64_t parts,
                              const std::vector<std::string>& only, std::uint64_t distinct) {
  SimFeed feed;
  const std::size_t count = distinct > 0 ? distinct
                            : parts == 0 ? kPregeneratedPasses
                                         : std::min<std::uint64_t>(parts, kPregeneratedPasses);
  const auto& catalogue = cell.catalogue();
  std::vector<std::size_t> candidates;  // catalogue indices that may arrive
  for (std::size_t i = 0; i < catalogue.size(); ++i) {
    if (only.empty() || std::find(only.begin(), only.end(), catalogue[i].name) != only.end()) candidates.push_back(i);
  }
  for (const std::string& name : only) {
    if (cell.find_part(name) == nullptr) return cell.random_pass(name, 0).error();  // names the known parts
  }
  if (candidates.empty()) return make_error("the simulated cell's catalogue has no parts");
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<std::size_t> pick(0, candidates.size() - 1);
  feed.passes.reserve(count);
  feed.part_index.reserve(count);
  constexpr std::uint64_t kSeedStride = 1'000'003;  // distinct pass seeds per run seed
  for (std::size_t k = 0; k < count; ++k) {
    const std::size_t index = candidates[pick(rng)];
    auto pass = cell.random_pass(catalogue[index].name, seed * kSeedStride + k);
    if (!pass) return pass.error();
    feed.passes.push_back(std::move(*pass));
    feed.part_index.push_back(static_cast<int>(index));
  }
  return feed;
}

// --sim-oracle: the simulator's truth of the pass under the sensor as the decision, so the runtime (loop, Modbus,
// handshake, truth log) can be tested end to end before a model database exists. PLC id = catalogue index + 1.
class SimOracle final : public runtime::Recogniser {
 public:
  SimOracle(const sim::SimLine& line, const sim::SimCell& cell, const SimFeed& feed)
      : line_(line), cell_(cell), feed_(feed) {}

  algo::Decision recognise(std::span<const algo::ScanPoint> points,
                           std::chrono::steady_clock::time_point deadline) override {
    algo::Decision d;
    if (std::chrono::steady_clock::now() > deadline) {
      d.source = algo::DecisionSource::kTimeout;
      return d;
    }
    const std::uint64_t started = line_.passes_started();
    if (started == 0 || points.empty()) {
      d.source = algo::DecisionSource::kNoPart;
      return d;
    }
    const std::size_t k = (started - 1) % feed_.passes.size();
    const sim::PassSpec& pass = feed_.passes[k];
    d.source = algo::DecisionSource::kSvm;
    d.class_index = feed_.part_index[k];
    d.part_id = d.class_index + 1;
    d.probability = 1.0;
    d.pose_valid = true;
    d.pose = {pass.pose.x_m, pass.pose.y_m, pass.pose.theta_rad};
    // All six axes, so the PLC test checks every pose register's encoding against the truth log; no sigma (the truth
    // has no uncertainty to report: 0xFFFF).
    d.z_m = pass.pose.z_m;
    d.rx_rad = pass.pose.tilt_rad;
    d.ry_rad = pass.pose.swing_rad;
    return d;
  }

  std::string_view class_name(int class_index) const override {
    if (class_index < 0 || static_cast<std::size_t>(class_index) >= cell_.catalogue().size()) return {};
    return cell_.catalogue()[static_cast<std::size_t>(class_index)].name;
  }

 private:
  const sim::SimLine& line_;
  const sim::SimCell& cell_;
  const SimFeed& feed_;
};

// --truth-log: one JSON line per acquisition with the simulator's truth of its pass. Runs on the loop thread; formats
// with fprintf into the FILE's buffer (no operator new).
class TruthLog final : public LoopObserver {
 public:
  TruthLog(std::FILE* file, const sim::SimLine& line, const SimFeed& feed, const sim::FaultPlan& faults,
           bool with_oracle_ids)
      : file_(file), line_(line), feed_(feed), faults_(faults), with_oracle_ids_(with_oracle_ids) {
    pass_of_acq_.fill(-1);
  }

  void on_pass_started(std::uint32_t acq_id, TriggerSource trigger) override {
    const std::uint64_t started = line_.passes_started();
    pass_of_acq_[acq_id % kAcqRing] =
        trigger == TriggerSource::kPartPresent && started > 0 ? static_cast<std::int64_t>(started - 1) : -1;
  }

  void on_part_done(const PartRecord& record) override {
    const std::int64_t pass_index = pass_of_acq_[record.acq_id % kAcqRing];
    if (pass_index < 0) {
      std::fprintf(file_, "{\"acq_id\": %" PRIu32 ", \"pass\": null}\n", record.acq_id);
      std::fflush(file_);
      return;
    }
    const std::size_t k = static_cast<std::size_t>(pass_index) % feed_.passes.size();
    const sim::PassSpec& pass = feed_.passes[k];
    std::fprintf(file_,
                 "{\"acq_id\": %" PRIu32 ", \"pass\": %" PRId64 ", \"part\": \"%s\", \"seed\": %" PRIu64
                 ", \"pose\": {\"x_m\": %.9f, \"y_m\": %.9f, \"theta_deg\": %.9f, \"swing_deg\": %.9f, "
                 "\"tilt_deg\": %.9f, \"z_m\": %.9f}, \"coating\": \"%s\"",
                 record.acq_id, pass_index, pass.part.c_str(), pass.seed, pass.pose.x_m, pass.pose.y_m,
                 pass.pose.theta_rad * kDegPerRad, pass.pose.swing_rad * kDegPerRad, pass.pose.tilt_rad * kDegPerRad,
                 pass.pose.z_m, pass.coating_a.name.c_str());
    if (with_oracle_ids_) std::fprintf(file_, ", \"oracle_part_id\": %d", feed_.part_index[k] + 1);
    const std::string_view fault = faults_.kind_of(static_cast<std::uint64_t>(pass_index));
    if (!fault.empty()) std::fprintf(file_, ", \"fault\": \"%.*s\"", static_cast<int>(fault.size()), fault.data());
    std::fputs("}\n", file_);
    std::fflush(file_);
  }

 private:
  std::FILE* file_;
  const sim::SimLine& line_;
  const SimFeed& feed_;
  const sim::FaultPlan& faults_;
  bool with_oracle_ids_;
  std::array<std::int64_t, kAcqRing> pass_of_acq_{};
};

// --truth-log with a model database: one line per taught part with the truth of its template scan, so a test can
// turn the simulator's poses into DESIGN.md's pose (the displacement from the template about its centroid c):
// for template pose (t_t, theta_t), scan pose (t_s, theta_s) and nominal centre C0 of the simulator,
// theta = theta_s - theta_t and t = t_s - t_t + (I - R(theta)) (C0 + t_t - c). Parts whose template did not come
// from the simulated cell ("sim seed N") get "seed": null.
void write_template_truth(std::FILE* file, const Config& config, const sim::SimCell& cell,
                          const std::string& models_dir) {
  auto db = ModelDb::open(models_dir, grid_spec(config), false);
  if (!db) {
    CS_LOG_WARN(kComponent, "truth log: no template truth: %s", db.error().message.c_str());
    return;
  }
  constexpr std::string_view kSimSeed = "sim seed ";
  for (const formats::PartEntry& part : db->manifest().parts) {
    std::fprintf(file, "{\"template\": \"%s\", \"part_id\": %d", part.name.c_str(), part.id);
    const sim::PartSpec* spec = cell.find_part(part.name);
    std::uint64_t seed = 0;
    const formats::ScanEntry* source = part.template_scan_entry();  // the pass the template was built from
    const bool from_sim = spec != nullptr && source != nullptr && source->source.rfind(kSimSeed, 0) == 0 &&
                          parse_u64(source->source.substr(kSimSeed.size()), seed);
    auto pass = from_sim ? cell.random_pass(part.name, seed) : Expected<sim::PassSpec>(make_error("not simulated"));
    auto info = formats::read_template_info(db->path_of(part.template_file));
    if (pass && info) {
      const Eigen::Vector3d c0 = cell.nominal_centre(*spec);
      std::fprintf(file,
                   ", \"seed\": %" PRIu64
                   ", \"pose\": {\"x_m\": %.9f, \"y_m\": %.9f, \"theta_deg\": %.9f, "
                   "\"swing_deg\": %.9f, \"tilt_deg\": %.9f, \"z_m\": %.9f}, \"nominal_centre_m\": [%.9f, %.9f], "
                   "\"centroid_m\": [%.9f, %.9f]}\n",
                   seed, pass->pose.x_m, pass->pose.y_m, pass->pose.theta_rad * kDegPerRad,
                   pass->pose.swing_rad * kDegPerRad, pass->pose.tilt_rad * kDegPerRad, pass->pose.z_m, c0.x(), c0.y(),
                   info->centroid_m.x(), info->centroid_m.y());
    } else {
      std::fputs(", \"seed\": null}\n", file);
    }
  }
  std::fflush(file);
}

}  // namespace

bool parse_u64(const std::string& text, std::uint64_t& out) {
  if (text.empty() || text[0] == '-' || text[0] == '+') return false;
  char* end = nullptr;
  errno = 0;
  const unsigned long long value = std::strtoull(text.c_str(), &end, 10);
  if (*end != '\0' || errno != 0) return false;
  out = value;
  return true;
}

struct SimRun::State {
  std::optional<sim::SimCell> cell;
  std::optional<sim::SimLine> line;
  SimFeed feed;
  sim::FaultPlan faults;
  std::FILE* truth_file = nullptr;
  std::optional<TruthLog> truth;
  bool oracle = false;
  std::uint64_t replay = 0;
  std::uint64_t fed = 0;
};

Expected<std::unique_ptr<SimRun>> SimRun::create(const Config& config, const RunOptions& options) {
  std::unique_ptr<SimRun> run(new SimRun());
  run->state_ = std::make_unique<State>();
  State& s = *run->state_;
  auto parsed_faults = sim::FaultPlan::parse(options.sim_faults, {config.camera.timeout_ms, config.gpio.debounce_us});
  if (!parsed_faults) return parsed_faults.error();
  s.faults = std::move(*parsed_faults);
  if (!s.faults.empty()) {
    CS_LOG_WARN(kComponent, "--sim-faults %s: faults are injected into the simulated devices",
                options.sim_faults.c_str());
  }
  auto made = make_sim_cell(config);
  if (!made) return made.error();
  s.cell.emplace(std::move(*made));
  s.line.emplace(*s.cell);
  run->line_ = &*s.line;
  auto drawn = draw_passes(*s.cell, options.seed, options.parts, options.sim_parts, options.sim_replay);
  if (!drawn) return drawn.error();
  s.feed = std::move(*drawn);
  s.oracle = options.sim_oracle;
  s.replay = options.sim_replay;
  if (!options.truth_log.empty()) {
    s.truth_file = std::fopen(options.truth_log.c_str(), "w");
    if (s.truth_file == nullptr) {
      return make_error(options.truth_log + ": cannot write the truth log: " + std::strerror(errno));
    }
  }
  return run;
}

SimRun::~SimRun() {
  if (state_ != nullptr && state_->truth_file != nullptr) std::fclose(state_->truth_file);
}

Status SimRun::enable_replay() {
  if (state_->replay == 0) return {};
  if (auto ok = state_->line->enable_frame_memo(state_->replay); !ok) return ok.error();
  CS_LOG_WARN(kComponent,
              "--sim-replay %" PRIu64 ": %" PRIu64 " distinct passes, each rendered once and then replayed from memory",
              state_->replay, state_->replay);
  return {};
}

std::unique_ptr<runtime::Recogniser> SimRun::make_oracle() const {
  return std::make_unique<SimOracle>(*state_->line, *state_->cell, state_->feed);
}

LoopObserver* SimRun::truth_observer(const Config& config, const std::string& models_dir) {
  State& s = *state_;
  if (s.truth_file == nullptr) return nullptr;
  if (!s.oracle) write_template_truth(s.truth_file, config, *s.cell, models_dir);
  s.truth.emplace(s.truth_file, *s.line, s.feed, s.faults, s.oracle);
  return &*s.truth;
}

void SimRun::feed(bool loop_finished) {
  State& s = *state_;
  // Fed until the loop has its parts (an aborted pass does not count, so N passes may not be enough).
  while (!loop_finished && s.line->queued() < kQueuedPassesAhead) {
    const std::uint64_t k = s.fed % s.feed.passes.size();
    s.line->enqueue(s.feed.passes[k], s.faults.for_pass(s.fed, s.cell->frame_count()),
                    s.replay > 0 ? static_cast<std::int64_t>(k) : -1);
    ++s.fed;
  }
}

void SimRun::log_summary(const drivers::DigitalIo& io) const {
  const State& s = *state_;
  const auto* sim_io = dynamic_cast<const sim::SimDigitalIo*>(&io);
  CS_LOG_INFO(kComponent,
              "simulated line: %" PRIu64 " passes started, %" PRIu64 " fed, %" PRIu64
              " part-present bounces filtered, %" PRIu64 " frames replayed, %" PRIu64 " rendered into the memo",
              s.line->passes_started(), s.fed, sim_io != nullptr ? sim_io->bounces() : 0, s.line->frame_memo().hits(),
              s.line->frame_memo().stores());
}

}  // namespace cellsight::app
