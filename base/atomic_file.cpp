// Atomic file and folder saves.
#include "base/atomic_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <filesystem>

namespace cellsight::base {
namespace {

namespace fs = std::filesystem;

// The temporary name of write_file_atomic: the target's name, this suffix, then kTempRandomChars from mkstemp.
constexpr std::string_view kTempSuffix = ".tmp-";
constexpr std::size_t kTempRandomChars = 6;

std::string errno_text() {
  return std::strerror(errno);
}

Status fsync_path(const std::string& path, int flags) {
  const int fd = ::open(path.c_str(), flags | O_CLOEXEC);
  if (fd < 0) return make_error(path + ": cannot open to sync: " + errno_text());
  const int rc = ::fsync(fd);
  const int saved = errno;
  ::close(fd);
  if (rc != 0) return make_error(path + ": fsync failed: " + std::strerror(saved));
  return {};
}

std::string parent_of(const std::string& path) {
  const fs::path parent = fs::path(path).parent_path();
  return parent.empty() ? "." : parent.string();
}

}  // namespace

std::string atomic_temp_template(const std::string& path) {
  return path + std::string(kTempSuffix) + std::string(kTempRandomChars, 'X');
}

bool is_atomic_temp_name(std::string_view file_name) {
  const std::size_t suffix = kTempSuffix.size() + kTempRandomChars;
  if (file_name.size() <= suffix) return false;
  const std::string_view tail = file_name.substr(file_name.size() - suffix);
  if (tail.substr(0, kTempSuffix.size()) != kTempSuffix) return false;
  for (const char c : tail.substr(kTempSuffix.size())) {
    const bool alnum = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9');
    if (!alnum) return false;
  }
  return true;
}

std::vector<std::string> remove_files_below(const std::string& dir,
                                            const std::function<bool(const std::filesystem::path&)>& chosen) {
  std::vector<std::string> removed;
  std::error_code ec;
  const fs::path root(dir);
  for (fs::recursive_directory_iterator it(root, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code type_ec;  // the entry itself: a link of that name is not a file the writer made
    if (!fs::is_regular_file(it->symlink_status(type_ec)) || !chosen(it->path().lexically_relative(root))) continue;
    std::error_code remove_ec;
    if (fs::remove(it->path(), remove_ec)) removed.push_back(it->path().string());
  }
  return removed;
}

std::vector<std::string> remove_orphaned_temp_files(const std::string& dir) {
  return remove_files_below(dir,
                            [](const fs::path& relative) { return is_atomic_temp_name(relative.filename().string()); });
}

namespace {

// Fault seam for the crash-consistency tests (issue 15): with CELLSIGHT_FAULT_KILL_BEFORE_RENAME set to a file name,
// the process kills itself with SIGKILL when that file's new content is written and synced but not yet renamed into
// place -- for "manifest.yaml", exactly between a teach's or train's other files and the manifest that names them.
// A kill at any moment is what the atomic saves are for; the variable only picks the moment.
void kill_here_if_asked(const std::string& path) {
  const char* name = std::getenv("CELLSIGHT_FAULT_KILL_BEFORE_RENAME");
  if (name == nullptr || *name == '\0') return;
  if (std::filesystem::path(path).filename() == name) ::raise(SIGKILL);
}

}  // namespace

Status write_file_atomic(const std::string& path, std::string_view content, Overwrite overwrite) {
  std::string temp = atomic_temp_template(path);
  const int fd = ::mkstemp(temp.data());
  if (fd < 0) return make_error(path + ": cannot create a temporary file beside it: " + errno_text());
  std::size_t done = 0;
  while (done < content.size()) {
    const ssize_t n = ::write(fd, content.data() + done, content.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) {
      const std::string why = errno_text();
      ::close(fd);
      ::unlink(temp.c_str());
      return make_error(path + ": write failed: " + why);
    }
    done += static_cast<std::size_t>(n);
  }
  if (::fchmod(fd, 0644) != 0 || ::fsync(fd) != 0) {
    const std::string why = errno_text();
    ::close(fd);
    ::unlink(temp.c_str());
    return make_error(path + ": cannot finish the file: " + why);
  }
  ::close(fd);
  kill_here_if_asked(path);
  if (overwrite == Overwrite::kRefuse) {
    const int rc = ::link(temp.c_str(), path.c_str());
    const int saved = errno;
    ::unlink(temp.c_str());
    if (rc != 0 && saved == EEXIST) return make_error(path + ": already exists; refusing to overwrite it");
    if (rc != 0) return make_error(path + ": cannot create: " + std::strerror(saved));
  } else if (::rename(temp.c_str(), path.c_str()) != 0) {
    const std::string why = errno_text();
    ::unlink(temp.c_str());
    return make_error(path + ": cannot replace: " + why);
  }
  return fsync_path(parent_of(path), O_RDONLY | O_DIRECTORY);
}

Expected<StagedDirectory> StagedDirectory::create(const std::string& target) {
  std::error_code ec;
  if (fs::exists(target, ec) && !(fs::is_directory(target, ec) && fs::is_empty(target, ec))) {
    return make_error(target + ": already exists and is not an empty folder; choose a new output folder or remove it");
  }
  const std::string parent = parent_of(target);
  if (!fs::is_directory(parent, ec)) return make_error(target + ": the parent folder " + parent + " does not exist");
  std::string name = fs::path(target).filename().string();
  name.insert(0, 1, '.');
  name.append(".tmp-XXXXXX");
  std::string staging = (fs::path(parent) / name).string();
  if (::mkdtemp(staging.data()) == nullptr) {
    return make_error(target + ": cannot write in " + parent + ": " + errno_text());
  }
  return StagedDirectory(target, staging);
}

StagedDirectory::StagedDirectory(StagedDirectory&& other) noexcept
    : target_(std::move(other.target_)), staging_(std::move(other.staging_)), committed_(other.committed_) {
  other.committed_ = true;  // the moved-from object owns nothing
}

StagedDirectory::~StagedDirectory() {
  if (!committed_ && !staging_.empty()) {
    std::error_code ec;
    fs::remove_all(staging_, ec);
  }
}

Status StagedDirectory::commit() {
  std::error_code ec;
  if (fs::is_directory(target_, ec) && fs::is_empty(target_, ec)) fs::remove(target_, ec);
  if (::rename(staging_.c_str(), target_.c_str()) != 0) {
    return make_error(target_ + ": cannot move the finished output into place: " + errno_text());
  }
  committed_ = true;
  return fsync_path(parent_of(target_), O_RDONLY | O_DIRECTORY);
}

}  // namespace cellsight::base
