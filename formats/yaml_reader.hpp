// Validating reader over yaml-cpp: every value range-checked, every unknown key an error, each error one line
// naming file, line, column, key, value and the expected range with its unit.
#pragma once

#include <yaml-cpp/yaml.h>

#include <Eigen/Core>
#include <initializer_list>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "algo/result.hpp"

namespace cellsight::formats {

class YamlErrors {
 public:
  // Lines kept and printed; the rest are only counted (a file of unknown keys must not print a line each).
  static constexpr std::size_t kMaxLines = 20;

  explicit YamlErrors(std::string file) : file_(std::move(file)) {}
  void add(const YAML::Mark& mark, const std::string& key, const std::string& message);
  [[nodiscard]] bool empty() const { return count_ == 0; }
  // The first kMaxLines errors.
  [[nodiscard]] const std::vector<std::string>& lines() const { return lines_; }
  [[nodiscard]] std::size_t count() const { return count_; }
  [[nodiscard]] const std::string& file() const { return file_; }
  // The kept lines joined with '\n', then "... and N more" when errors were left out, for an Error.
  [[nodiscard]] std::string joined() const;

 private:
  std::string file_;
  std::vector<std::string> lines_;
  std::size_t count_ = 0;
};

// A mapping node and the dotted path that leads to it. Reads leave the target untouched when the key is absent
// (the built-in default stays), so a maintenance engineer may ship a file with only the keys that differ.
class YamlSection {
 public:
  YamlSection(YAML::Node node, std::string path, YamlErrors* errors);

  [[nodiscard]] bool has(const char* key) const;
  void number(const char* key, double& value, double min, double max, const char* unit);
  void integer(const char* key, int& value, int min, int max, const char* unit);
  void integer(const char* key, std::int64_t& value, std::int64_t min, std::int64_t max, const char* unit);
  void boolean(const char* key, bool& value);
  void text(const char* key, std::string& value, bool allow_empty = false);
  void choice(const char* key, std::string& value, std::initializer_list<const char*> allowed);
  void vec3(const char* key, Eigen::Vector3d& value, double min, double max, const char* unit);
  // A list of [x, y] pairs.
  void points2(const char* key, std::vector<Eigen::Vector2d>& value, double min, double max, const char* unit);
  // Marks the key as known and returns it as a section (an empty one when absent).
  [[nodiscard]] YamlSection section(const char* key);
  // Marks the key as known and returns each element of the list (which must be mappings).
  [[nodiscard]] std::vector<YamlSection> list(const char* key);
  // Requires the key to be present (call before reading it).
  void require(const char* key);
  // Reports every key that no read asked for: typos must not pass silently.
  void finish();

  void error(const char* key, const std::string& message);
  [[nodiscard]] const std::string& path() const { return path_; }
  [[nodiscard]] YAML::Mark mark() const { return node_.Mark(); }

 private:
  [[nodiscard]] bool get(const char* key, YAML::Node& out);
  [[nodiscard]] std::string key_path(const char* key) const;
  YAML::Node node_;
  std::string path_;
  YamlErrors* errors_;
  std::set<std::string> used_;
};

// Loads a YAML file; a syntax error becomes one "file:line:col: ..." line.
[[nodiscard]] Expected<YAML::Node> load_yaml_file(const std::string& path);
// load_yaml_file on text already in memory; `path` only names it in messages (the fuzz target's entry point).
[[nodiscard]] Expected<YAML::Node> parse_yaml_text(const std::string& text, const std::string& path);

}  // namespace cellsight::formats
