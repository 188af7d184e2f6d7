// Temporary folders for tests that write files. Every folder lies under one folder of the test process
// (`cellsight-test-PID` in the system's temporary folder), which is removed with everything in it when the process
// exits normally, so passing runs leave nothing behind; a run that crashes keeps its files for a look.
#pragma once

#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <string>
#include <system_error>
#include <vector>

namespace cellsight::test {

// This process's folder (created on first use).
inline const std::filesystem::path& scratch_root() {
  struct Root {
    std::filesystem::path path;
    ~Root() {
      std::error_code ec;
      std::filesystem::remove_all(path, ec);
    }
  };
  static const Root root{[] {
    auto path = std::filesystem::temp_directory_path() / ("cellsight-test-" + std::to_string(::getpid()));
    std::filesystem::create_directories(path);
    return path;
  }()};
  return root.path;
}

// `name` (may hold subfolders) under scratch_root(), with whatever an earlier call left there removed; its parent
// exists, the path itself does not (for commands that must create it themselves).
inline std::filesystem::path scratch_path(const std::string& name) {
  const std::filesystem::path path = scratch_root() / name;
  std::filesystem::remove_all(path);
  std::filesystem::create_directories(path.parent_path());
  return path;
}

// An empty folder `name` under scratch_root().
inline std::filesystem::path scratch_dir(const std::string& name) {
  const std::filesystem::path path = scratch_path(name);
  std::filesystem::create_directories(path);
  return path;
}

// A fresh numbered folder `prefix-N` under scratch_root(), for tests that need many.
inline std::filesystem::path numbered_scratch_dir(const std::string& prefix) {
  static int counter = 0;
  return scratch_dir(prefix + "-" + std::to_string(counter++));
}

// A fresh numbered folder under scratch_root() that is removed with everything in it at scope exit (for tests
// whose files are large: templates).
class TempDir {
 public:
  TempDir() : path_(numbered_scratch_dir("tmp")) {}
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  [[nodiscard]] const std::filesystem::path& path() const { return path_; }
  [[nodiscard]] std::string file(const std::string& name) const { return (path_ / name).string(); }
  [[nodiscard]] std::vector<std::string> entries() const {  // file names, sorted
    std::vector<std::string> names;
    for (const auto& e : std::filesystem::directory_iterator(path_)) names.push_back(e.path().filename().string());
    std::sort(names.begin(), names.end());
    return names;
  }

 private:
  std::filesystem::path path_;
};

}  // namespace cellsight::test
