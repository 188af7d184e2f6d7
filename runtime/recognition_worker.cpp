// The recognition thread: mailbox protocol and job execution.
#include "runtime/recognition_worker.hpp"

#include "base/local_time.hpp"
#include "base/start_thread.hpp"
#include "drivers/log.hpp"
#include "runtime/futex.hpp"

namespace cellsight::runtime {

namespace {
constexpr const char* kComponent = "loop";
}  // namespace

RecognitionWorker::~RecognitionWorker() {
  stop();
}

void RecognitionWorker::set_recogniser(std::unique_ptr<Recogniser> recogniser) {
  recogniser_ = std::move(recogniser);
  has_recogniser_.store(recogniser_ != nullptr, std::memory_order_release);
}

void RecognitionWorker::set_loader(RecogniserLoader loader) {
  loader_ = std::move(loader);
}

void RecognitionWorker::set_keeper(ScanKeeper* keeper, bool keep_unknown) {
  keeper_ = keeper;
  keep_unknown_ = keep_unknown;
}

Status RecognitionWorker::start() {
  if (thread_.joinable()) return make_error("recognition worker: start() called twice");
  exit_.store(false, std::memory_order_release);
  return base::start_thread(thread_, "cs-recognise", [this] { run(); });
}

void RecognitionWorker::stop() {
  exit_.store(true, std::memory_order_release);
  futex_ring(bell_);
  if (thread_.joinable()) thread_.join();
}

void RecognitionWorker::swap_recogniser(std::unique_ptr<Recogniser>& recogniser) {
  std::swap(recogniser_, recogniser);
  has_recogniser_.store(recogniser_ != nullptr, std::memory_order_release);
}

bool RecognitionWorker::idle() const {
  return done_seq_.load(std::memory_order_acquire) == posted_seq_.load(std::memory_order_relaxed);
}

void RecognitionWorker::post(WorkerJob job) {
  job_ = job;
  posted_at_ = Clock::now();
  posted_seq_.store(posted_seq_.load(std::memory_order_relaxed) + 1, std::memory_order_release);
  futex_ring(bell_);
}

bool RecognitionWorker::post_recognise(std::span<const algo::ScanPoint> points, Clock::time_point deadline,
                                       const KeepTag& tag) {
  if (!idle()) return false;
  points_ = points;
  tag_ = tag;
  deadline_ = deadline;
  post(WorkerJob::kRecognise);
  return true;
}

bool RecognitionWorker::post_load() {
  if (!idle() || !loader_) return false;
  post(WorkerJob::kLoad);
  return true;
}

bool RecognitionWorker::wait_idle(Clock::time_point until) {
  for (;;) {
    const std::uint32_t done = done_seq_.load(std::memory_order_acquire);
    if (done == posted_seq_.load(std::memory_order_relaxed)) return true;
    const Clock::time_point now = Clock::now();
    if (now >= until) return false;
    futex_wait(done_seq_, done, until - now);
  }
}

std::string_view RecognitionWorker::class_name(int class_index) const {
  if (class_index < 0 || !idle() || recogniser_ == nullptr) return {};
  return recogniser_->class_name(class_index);
}

// A bounded copy (memcpy of at most max_points) and no allocation; the class names are copied into fixed fields.
void RecognitionWorker::keep(const algo::Decision& decision) {
  const bool unknown =
      decision.source == algo::DecisionSource::kUnknown || decision.source == algo::DecisionSource::kTimeout;
  const bool for_review = keeper_ != nullptr && (tag_.teach || (keep_unknown_ && unknown));
  if (!for_review && preview_ == nullptr) return;
  KeptScanInfo& info = kept_info_;
  info.tag = tag_;
  info.wall_ms = base::wall_clock_ms();
  info.decision = decision;
  for (auto& name : info.names) name[0] = '\0';
  if (recogniser_ != nullptr) {
    for (int i = 0; i < decision.candidate_count && i < algo::kMaxReportedCandidates; ++i) {
      ScanKeeper::put_name(info.names[static_cast<std::size_t>(i)],
                           recogniser_->class_name(decision.candidates[static_cast<std::size_t>(i)].class_index));
    }
    ScanKeeper::put_name(info.names[algo::kMaxReportedCandidates], recogniser_->class_name(decision.class_index));
  }
  if (for_review) (void)keeper_->keep(points_, info);
  if (preview_ != nullptr) (void)preview_->keep_thinned(points_, info);
}

void RecognitionWorker::run() {
  std::uint32_t taken = 0;  // the last posted_seq_ this thread worked on
  for (;;) {
    // Look at the bell before the words it guards: a post or stop after this load changes the bell, so the
    // futex_wait below returns at once instead of missing it.
    const std::uint32_t bell = bell_.load(std::memory_order_acquire);
    const std::uint32_t posted = posted_seq_.load(std::memory_order_acquire);
    if (posted == taken) {
      if (exit_.load(std::memory_order_acquire)) return;
      futex_wait(bell_, bell);
      continue;
    }
    taken = posted;
    WorkerAnswer answer;
    answer.job = job_;
    answer.posted_at = posted_at_;
    if (job_ == WorkerJob::kRecognise) {
      if (recogniser_ != nullptr) {
        answer.decision = recogniser_->recognise(points_, deadline_);
      } else {
        answer.decision.source = algo::DecisionSource::kUnknown;
      }
      keep(answer.decision);
    } else if (loader_) {
      auto loaded = loader_();  // may allocate: the loop is in fault "model database invalid" meanwhile
      if (loaded) {
        recogniser_ = std::move(*loaded);
        answer.load_ok = recogniser_ != nullptr;
        has_recogniser_.store(answer.load_ok, std::memory_order_release);
      } else {
        CS_LOG_ERROR(kComponent, "model database: %s", loaded.error().message.c_str());
      }
    }
    answer.finished_at = Clock::now();
    answer_ = answer;
    done_seq_.store(taken, std::memory_order_release);
    futex_wake_all(done_seq_);
  }
}

}  // namespace cellsight::runtime
