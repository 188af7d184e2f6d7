// Atomic saves: write beside the target, fsync, rename — a reader sees the old file or the new one, never half.
#pragma once

#include <filesystem>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "base/result.hpp"

namespace cellsight::base {

enum class Overwrite { kReplace, kRefuse };

// Writes `content` to `path` atomically (temp file in the same folder, fsync, rename, fsync of the folder). With
// Overwrite::kRefuse an existing `path` is left alone and reported (the file is linked into place, which fails
// atomically when the name is taken).
[[nodiscard]] Status write_file_atomic(const std::string& path, std::string_view content,
                                       Overwrite overwrite = Overwrite::kReplace);

// The mkstemp template of the temporary file beside `path` ("PATH.tmp-XXXXXX"), for every atomic writer: the name
// remove_orphaned_temp_files recognises.
[[nodiscard]] std::string atomic_temp_template(const std::string& path);

// Whether `file_name` (no folder) is one write_file_atomic gives its temporary file: the target's name, ".tmp-" and
// the six letters or digits mkstemp chose.
[[nodiscard]] bool is_atomic_temp_name(std::string_view file_name);

// Removes, below `dir`, the regular files (a link is never followed nor removed) for which `chosen(path relative to
// dir)` is true. Only for a folder that no other process is writing into. Returns the paths removed.
[[nodiscard]] std::vector<std::string> remove_files_below(
    const std::string& dir, const std::function<bool(const std::filesystem::path&)>& chosen);

// remove_files_below the files whose name is_atomic_temp_name: what a write killed before its rename left behind.
[[nodiscard]] std::vector<std::string> remove_orphaned_temp_files(const std::string& dir);

// A folder filled under a temporary name and renamed into place by commit(); removed again if never committed.
class StagedDirectory {
 public:
  // Fails when `target` exists and is not empty (nothing is overwritten), or its parent is not writable.
  [[nodiscard]] static Expected<StagedDirectory> create(const std::string& target);
  StagedDirectory(StagedDirectory&& other) noexcept;
  StagedDirectory& operator=(StagedDirectory&&) = delete;
  StagedDirectory(const StagedDirectory&) = delete;
  StagedDirectory& operator=(const StagedDirectory&) = delete;
  ~StagedDirectory();

  [[nodiscard]] const std::string& path() const { return staging_; }
  [[nodiscard]] Status commit();

 private:
  StagedDirectory(std::string target, std::string staging) : target_(std::move(target)), staging_(std::move(staging)) {}
  std::string target_;
  std::string staging_;
  bool committed_ = false;
};

}  // namespace cellsight::base
