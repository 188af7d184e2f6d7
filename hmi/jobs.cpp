// JobRunner: one child process at a time (posix_spawn), its stdout and stderr read by the runner's thread into a
// bounded tail, progress lines parsed, the child reaped by that thread (never a zombie), SIGTERM to cancel.
#include "hmi/jobs.hpp"

#include <fcntl.h>
#include <poll.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <mutex>
#include <thread>
#include <utility>

#include "base/start_thread.hpp"
#include "drivers/log.hpp"

extern char** environ;  // NOLINT(readability-redundant-declaration): POSIX declares it nowhere in a header

namespace cellsight::hmi {
namespace {

constexpr const char* kComponent = "hmi";
constexpr const char* kProgressPrefix = "progress: ";
constexpr int kPollMs = 200;
constexpr auto kKillAfter = std::chrono::seconds(10);  // after SIGTERM: a child that ignores it gets SIGKILL
constexpr int kSignalExitBase = 128;                   // the shell's convention for "ended by signal N"

std::int64_t now_ms() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// An owned file descriptor (closed on destruction).
class Fd {
 public:
  Fd() = default;
  explicit Fd(int fd) : fd_(fd) {}
  Fd(Fd&& other) noexcept : fd_(std::exchange(other.fd_, -1)) {}
  Fd& operator=(Fd&& other) noexcept {
    if (this != &other) {
      reset();
      fd_ = std::exchange(other.fd_, -1);
    }
    return *this;
  }
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  ~Fd() { reset(); }
  [[nodiscard]] int get() const { return fd_; }
  void reset() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }

 private:
  int fd_ = -1;
};

// One output stream of the child: bytes in, whole lines out (a line longer than `max` is cut there; the rest of it
// until the newline is dropped, and a cut line is marked).
class LineSplitter {
 public:
  explicit LineSplitter(std::size_t max) : max_(max) {}
  template <class Sink>
  void feed(const char* data, std::size_t n, Sink&& sink) {
    for (std::size_t i = 0; i < n; ++i) {
      const char c = data[i];
      if (c == '\n' || c == '\r') {  // '\r': a progress bar redrawn in place counts as lines too
        if (!line_.empty() || cut_) sink(line_, cut_);
        line_.clear();
        cut_ = false;
      } else if (line_.size() < max_) {
        line_ += c;
      } else {
        cut_ = true;
      }
    }
  }
  template <class Sink>
  void flush(Sink&& sink) {
    if (!line_.empty()) sink(line_, cut_);
    line_.clear();
    cut_ = false;
  }

 private:
  std::size_t max_;
  std::string line_;
  bool cut_ = false;
};

// "progress: 0.42 annealing 40/96" -> 0.42 and "annealing 40/96"; false for any other line.
bool parse_progress(const std::string& line, double& fraction, std::string& text) {
  if (line.rfind(kProgressPrefix, 0) != 0) return false;
  const char* start = line.c_str() + std::strlen(kProgressPrefix);
  char* end = nullptr;
  const double v = std::strtod(start, &end);
  if (end == start || !(v >= 0.0 && v <= 1.0)) return false;
  fraction = v;
  while (*end == ' ') ++end;
  text = end;
  return true;
}

}  // namespace

struct JobRunner::Impl {
  std::vector<std::string> prefix;
  std::string calibration;  // set_calibration()
  std::mutex start_mutex;   // one start() at a time: it may join the last job's thread
  mutable std::mutex mutex;
  JobView view;  // guarded by mutex
  pid_t pid = -1;
  bool cancel_requested = false;
  std::chrono::steady_clock::time_point cancel_time{};
  std::uint64_t next_id = 1;
  std::thread thread;

  [[nodiscard]] Expected<pid_t> spawn(const std::vector<std::string>& args, Fd& out, Fd& err) const;
  void run(pid_t child, Fd out, Fd err, JobHooks hooks);
  void take_line(const std::string& line, bool cut, bool from_stdout, std::vector<nlohmann::json>& json_lines);
  bool kill_overdue(pid_t child);
};

const char* to_string(JobKind kind) {
  switch (kind) {
    case JobKind::kTeach: return "teach";
    case JobKind::kDelete: return "delete";
    case JobKind::kTrain: return "train";
    case JobKind::kClassify: return "classify";
  }
  return "?";
}

nlohmann::json to_json(const JobView& v) {
  return {{"id", v.id},
          {"kind", to_string(v.kind)},
          {"title", v.title},
          {"state", v.state},
          {"progress", v.progress >= 0.0 ? nlohmann::json(v.progress) : nlohmann::json(nullptr)},
          {"progress_text", v.progress_text},
          {"started_ms", v.started_ms},
          {"ended_ms", v.ended_ms},
          {"exit_code", v.exit_code},
          {"log_tail", v.log_tail},
          {"result", v.result}};
}

JobRunner::JobRunner(const std::string& exe, const std::string& config_path, const std::string& models_dir)
    : impl_(std::make_unique<Impl>()) {
  std::error_code ec;
  impl_->prefix = {exe};
  // Absolute: the child starts in this process's folder, but a relative path read in the log is ambiguous.
  if (!config_path.empty()) {
    const auto absolute = std::filesystem::absolute(config_path, ec);
    impl_->prefix.insert(impl_->prefix.end(), {"--config", ec ? config_path : absolute.string()});
  }
  impl_->prefix.insert(impl_->prefix.end(), {"--models", models_dir});
}

void JobRunner::set_calibration(std::string path) {
  impl_->calibration = std::move(path);
}

JobRunner::JobRunner(std::vector<std::string> command_prefix) : impl_(std::make_unique<Impl>()) {
  impl_->prefix = std::move(command_prefix);
}

JobRunner::~JobRunner() {
  cancel();
  if (impl_->thread.joinable()) impl_->thread.join();
}

Expected<pid_t> JobRunner::Impl::spawn(const std::vector<std::string>& args, Fd& out, Fd& err) const {
  std::array<int, 2> out_pipe{-1, -1}, err_pipe{-1, -1};
  if (::pipe2(out_pipe.data(), O_CLOEXEC) != 0) return make_error(std::string("pipe: ") + std::strerror(errno));
  Fd out_read(out_pipe[0]), out_write(out_pipe[1]);
  if (::pipe2(err_pipe.data(), O_CLOEXEC) != 0) return make_error(std::string("pipe: ") + std::strerror(errno));
  Fd err_read(err_pipe[0]), err_write(err_pipe[1]);

  std::vector<std::string> words = prefix;
  words.insert(words.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (std::string& w : words) argv.push_back(w.data());
  argv.push_back(nullptr);

  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_adddup2(&actions, out_write.get(), STDOUT_FILENO);  // dup2 clears O_CLOEXEC
  posix_spawn_file_actions_adddup2(&actions, err_write.get(), STDERR_FILENO);
  // Nothing else of `run` reaches the child, whether or not its opener set O_CLOEXEC: not the camera, the GPIO
  // chip, the PLC's or the screen's sockets (a child alive after `run` would hold the ports). glibc >= 2.34.
  posix_spawn_file_actions_addclosefrom_np(&actions, STDERR_FILENO + 1);
  // The child starts with no signal blocked and the stop signals at their defaults: `run` blocks SIGTERM in its
  // helper threads (the main thread takes it) and a child would inherit that mask and be uncancellable.
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t none;
  sigset_t defaults;
  sigemptyset(&none);
  sigemptyset(&defaults);
  for (const int s : {SIGTERM, SIGINT, SIGPIPE, SIGHUP}) sigaddset(&defaults, s);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setsigdefault(&attr, &defaults);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETSIGDEF);
  pid_t child = -1;
  const int rc = ::posix_spawn(&child, argv[0], &actions, &attr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attr);
  if (rc != 0) return make_error("cannot start " + words.front() + ": " + std::strerror(rc));
  // Low priority from here on. posix_spawn has no attribute for niceness, and a `nice` wrapper would be one more
  // program to ship: the child is reniced at once, while it is still loading (threads it starts later inherit it).
  if (::setpriority(PRIO_PROCESS, static_cast<id_t>(child), kNice) != 0) {
    log::write(log::Level::kWarn, kComponent, "job %d runs at normal priority: setpriority: %s", child,
               std::strerror(errno));
  }
  out = std::move(out_read);
  err = std::move(err_read);
  return child;
}

Expected<std::uint64_t> JobRunner::start(JobKind kind, std::vector<std::string> args, std::string title,
                                         JobHooks hooks) {
  Impl& d = *impl_;
  const std::lock_guard<std::mutex> one_start(d.start_mutex);
  std::unique_lock<std::mutex> lock(d.mutex);
  if (d.view.state == "running") return make_error("a job is running: " + d.view.title);
  if (d.thread.joinable()) {
    lock.unlock();  // the last job has ended (its state is set last): its thread is about to return
    d.thread.join();
    lock.lock();
    if (d.view.state == "running") return make_error("a job is running: " + d.view.title);
  }
  if (!d.calibration.empty() && !args.empty() && kind != JobKind::kDelete) {
    args.insert(args.begin() + 1, {"--calibration", d.calibration});
  }
  Fd out, err;
  auto child = d.spawn(args, out, err);
  if (!child) return child.error();
  JobView v;
  v.id = d.next_id++;
  v.kind = kind;
  v.title = std::move(title);
  v.state = "running";
  v.started_ms = now_ms();
  d.view = std::move(v);
  d.pid = *child;
  d.cancel_requested = false;
  const Status started =
      base::start_thread(d.thread, "cs-hmi-job",
                         [&d, pid = *child, o = std::move(out), e = std::move(err), h = std::move(hooks)]() mutable {
                           d.run(pid, std::move(o), std::move(e), std::move(h));
                         });
  if (!started) {
    ::kill(*child, SIGKILL);
    int status = 0;
    ::waitpid(*child, &status, 0);
    d.view.state = "failed";
    d.pid = -1;
    return started.error();
  }
  log::write(log::Level::kInfo, kComponent, "job %llu (%s) started: pid %d", static_cast<unsigned long long>(d.view.id),
             d.view.title.c_str(), *child);
  return d.view.id;
}

void JobRunner::Impl::take_line(const std::string& line, bool cut, bool from_stdout,
                                std::vector<nlohmann::json>& json_lines) {
  if (from_stdout && !cut && !line.empty() && line.front() == '{' && json_lines.size() < kResultLines) {
    nlohmann::json j = nlohmann::json::parse(line, nullptr, false);
    if (!j.is_discarded() && j.is_object()) json_lines.push_back(std::move(j));
  }
  double fraction = 0.0;
  std::string text;
  const std::lock_guard<std::mutex> lock(mutex);
  if (parse_progress(line, fraction, text)) {
    view.progress = fraction;
    view.progress_text = std::move(text);
    return;
  }
  std::string shown = line.size() > kLineBytes ? line.substr(0, kLineBytes) : line;
  if (cut || line.size() > kLineBytes) shown += " [...]";
  view.log_tail.push_back(std::move(shown));
  if (view.log_tail.size() > kTailLines) view.log_tail.erase(view.log_tail.begin());
}

bool JobRunner::Impl::kill_overdue(pid_t child) {
  const std::lock_guard<std::mutex> lock(mutex);
  if (!cancel_requested || std::chrono::steady_clock::now() - cancel_time < kKillAfter) return false;
  ::kill(child, SIGKILL);
  return true;
}

// The runner's thread: reads both pipes until the child has closed them (or has ended: a grandchild holding a pipe
// open must not keep the job running), reaps it, then publishes the end state with the result.
void JobRunner::Impl::run(pid_t child, Fd out, Fd err, JobHooks hooks) {
  for (const Fd* fd : {&out, &err}) ::fcntl(fd->get(), F_SETFL, ::fcntl(fd->get(), F_GETFL) | O_NONBLOCK);
  std::array<LineSplitter, 2> splitters{LineSplitter(kResultLineBytes), LineSplitter(kResultLineBytes)};
  std::vector<nlohmann::json> json_lines;
  std::array<bool, 2> open{true, true};
  int status = 0;
  bool reaped = false;
  bool killed = false;
  std::array<char, 4096> buffer{};
  while (open[0] || open[1]) {
    std::array<pollfd, 2> fds{pollfd{open[0] ? out.get() : -1, POLLIN, 0}, pollfd{open[1] ? err.get() : -1, POLLIN, 0}};
    const int n = ::poll(fds.data(), fds.size(), kPollMs);
    if (n < 0 && errno != EINTR) break;
    for (std::size_t s = 0; s < 2; ++s) {
      if (!open[s] || (fds[s].revents & (POLLIN | POLLHUP | POLLERR)) == 0) continue;
      const ssize_t got = ::read(fds[s].fd, buffer.data(), buffer.size());
      if (got > 0) {
        splitters[s].feed(buffer.data(), static_cast<std::size_t>(got),
                          [&](const std::string& l, bool cut) { take_line(l, cut, s == 0, json_lines); });
      } else if (got == 0 || (errno != EAGAIN && errno != EINTR)) {
        open[s] = false;
      }
    }
    if (!killed) killed = kill_overdue(child);
    if (n == 0 && ::waitpid(child, &status, WNOHANG) == child) {
      reaped = true;  // ended, and nothing came for a poll period: what a grandchild still writes is not waited for
      break;
    }
  }
  for (std::size_t s = 0; s < 2; ++s) {
    splitters[s].flush([&](const std::string& l, bool cut) { take_line(l, cut, s == 0, json_lines); });
  }
  while (!reaped && ::waitpid(child, &status, 0) < 0 && errno == EINTR) {
  }
  // The state stays "running" for readers until the result is in: the page never sees an ended job without it.
  std::string final_state;
  JobView ended;
  {
    const std::lock_guard<std::mutex> lock(mutex);
    pid = -1;  // reaped: cancel() must not signal a pid the kernel may give to another process
    view.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : kSignalExitBase + WTERMSIG(status);
    final_state = view.exit_code == 0 ? "done" : cancel_requested ? "cancelled" : "failed";
    view.result = json_lines.empty() ? nlohmann::json(nullptr) : nlohmann::json(json_lines);
    ended = view;
    ended.state = final_state;
  }
  nlohmann::json result = hooks.result ? hooks.result(ended) : ended.result;
  {
    const std::lock_guard<std::mutex> lock(mutex);
    view.result = std::move(result);
    view.ended_ms = now_ms();
    if (final_state == "done") view.progress = 1.0;
    view.state = final_state;
    ended = view;
  }
  log::write(log::Level::kInfo, kComponent, "job %llu (%s) %s, exit code %d", static_cast<unsigned long long>(ended.id),
             ended.title.c_str(), ended.state.c_str(), ended.exit_code);
  if (hooks.on_done) hooks.on_done(ended);
}

JobView JobRunner::view() const {
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->view;
}

bool JobRunner::busy() const {
  const std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->view.state == "running";
}

bool JobRunner::cancel() {
  Impl& d = *impl_;
  const std::lock_guard<std::mutex> lock(d.mutex);
  if (d.pid <= 0 || d.view.state != "running") return false;
  if (!d.cancel_requested) {
    d.cancel_requested = true;
    d.cancel_time = std::chrono::steady_clock::now();
    ::kill(d.pid, SIGTERM);
  }
  return true;
}

}  // namespace cellsight::hmi
