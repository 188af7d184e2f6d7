// Validating YAML reader implementation.
#include "formats/yaml_reader.hpp"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <sstream>

#include "formats/input_file.hpp"

namespace cellsight::formats {
namespace {

std::string scalar_text(const YAML::Node& node) {
  if (node.IsScalar()) return "'" + node.Scalar() + "'";
  if (node.IsSequence()) return "a list";
  if (node.IsMap()) return "a mapping";
  return "nothing";
}

std::string format_range(double min, double max, const char* unit) {
  std::ostringstream out;
  out << "expected a number from " << min << " to " << max;
  if (unit != nullptr && unit[0] != '\0') out << " " << unit;
  return out.str();
}

bool parse_double(const YAML::Node& node, double& out) {
  if (!node.IsScalar()) return false;
  const std::string& s = node.Scalar();
  if (s.empty()) return false;
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (errno != 0 || end == s.c_str() || *end != '\0' || !std::isfinite(v)) return false;
  out = v;
  return true;
}

bool parse_int64(const YAML::Node& node, std::int64_t& out) {
  if (!node.IsScalar()) return false;
  const std::string& s = node.Scalar();
  if (s.empty()) return false;
  char* end = nullptr;
  errno = 0;
  const long long v = std::strtoll(s.c_str(), &end, 10);
  if (errno != 0 || end == s.c_str() || *end != '\0') return false;
  out = v;
  return true;
}

// How many values the walk below visits at most. An alias is a reference, so a few hundred bytes of aliases of
// aliases (&a [x, x, ...], &b [*a, *a, ...], ...) make a document of 10^9 values that the walk would take hours over;
// the shipped configuration has about 200 values, the catalogue of 15 parts about 300.
constexpr std::size_t kMaxWalkedValues = 100'000;

// yaml-cpp keeps every pair of a mapping and answers a lookup with the first, so a key written twice would pass
// silently with its first value: every mapping of the document is walked and a repeated key reported. Stops when
// `values_left` runs out (the caller reports that).
void report_repeated_keys(const YAML::Node& node, const std::string& path, int depth, std::size_t& values_left,
                          YamlErrors& errors) {
  constexpr int kMaxDepth = 64;  // a configuration is a few levels deep; aliases must not recurse for ever
  if (depth > kMaxDepth || values_left == 0) return;
  --values_left;
  if (node.IsMap()) {
    std::map<std::string, int> first_line;
    for (const auto& kv : node) {
      if (values_left == 0) return;
      const std::string key = kv.first.IsScalar() ? kv.first.Scalar() : std::string();
      const std::string child = path.empty() ? key : path + "." + key;
      if (kv.first.IsScalar()) {  // a list or mapping as a key is no key of ours: the reader reports it unknown
        const auto [first, fresh] = first_line.emplace(key, kv.first.Mark().line);
        if (!fresh) {
          errors.add(kv.first.Mark(), child,
                     "given twice (first at line " + std::to_string(first->second + 1) + "); keep one");
        }
      }
      report_repeated_keys(kv.second, child, depth + 1, values_left, errors);
    }
  } else if (node.IsSequence()) {
    std::size_t index = 0;
    for (const auto& element : node) {
      if (values_left == 0) return;
      report_repeated_keys(element, path + "[" + std::to_string(index++) + "]", depth + 1, values_left, errors);
    }
  }
}

}  // namespace

void YamlErrors::add(const YAML::Mark& mark, const std::string& key, const std::string& message) {
  if (++count_ > kMaxLines) return;
  std::ostringstream line;
  line << file_;
  if (mark.line >= 0) line << ":" << mark.line + 1 << ":" << mark.column + 1;
  line << ": " << key << ": " << message;
  lines_.push_back(line.str());
}

std::string YamlErrors::joined() const {
  std::string out;
  for (const auto& l : lines_) out += (out.empty() ? "" : "\n") + l;
  if (count_ > lines_.size()) out += "\n... and " + std::to_string(count_ - lines_.size()) + " more";
  return out;
}

YamlSection::YamlSection(YAML::Node node, std::string path, YamlErrors* errors)
    : node_(std::move(node)), path_(std::move(path)), errors_(errors) {
  if (node_.IsDefined() && !node_.IsNull() && !node_.IsMap()) {
    errors_->add(node_.Mark(), path_.empty() ? "(top level)" : path_,
                 "expected a mapping of keys, found " + scalar_text(node_));
    node_ = YAML::Node(YAML::NodeType::Map);
  }
}

std::string YamlSection::key_path(const char* key) const {
  return path_.empty() ? key : path_ + "." + key;
}

bool YamlSection::has(const char* key) const {
  if (!node_.IsMap()) return false;
  const YAML::Node& map = node_;  // const access: operator[] must not insert the key
  const YAML::Node n = map[key];
  return n.IsDefined() && !n.IsNull();
}

bool YamlSection::get(const char* key, YAML::Node& out) {
  used_.insert(key);
  if (!has(key)) return false;
  const YAML::Node& map = node_;
  out = map[key];
  return true;
}

void YamlSection::error(const char* key, const std::string& message) {
  const YAML::Node& map = node_;
  errors_->add(has(key) ? map[key].Mark() : node_.Mark(), key_path(key), message);
}

void YamlSection::require(const char* key) {
  if (!has(key)) errors_->add(node_.Mark(), key_path(key), "missing (this key is required)");
}

void YamlSection::number(const char* key, double& value, double min, double max, const char* unit) {
  YAML::Node n;
  if (!get(key, n)) return;
  double v = 0;
  if (!parse_double(n, v) || v < min || v > max) {
    errors_->add(n.Mark(), key_path(key), scalar_text(n) + " is not valid, " + format_range(min, max, unit));
    return;
  }
  value = v;
}

void YamlSection::integer(const char* key, std::int64_t& value, std::int64_t min, std::int64_t max, const char* unit) {
  YAML::Node n;
  if (!get(key, n)) return;
  std::int64_t v = 0;
  if (!parse_int64(n, v) || v < min || v > max) {
    std::ostringstream expect;
    expect << "expected a whole number from " << min << " to " << max << (unit[0] != '\0' ? " " : "") << unit;
    errors_->add(n.Mark(), key_path(key), scalar_text(n) + " is not valid, " + expect.str());
    return;
  }
  value = v;
}

void YamlSection::integer(const char* key, int& value, int min, int max, const char* unit) {
  std::int64_t v = value;
  integer(key, v, min, max, unit);
  value = static_cast<int>(v);
}

void YamlSection::boolean(const char* key, bool& value) {
  YAML::Node n;
  if (!get(key, n)) return;
  if (n.IsScalar() && (n.Scalar() == "true" || n.Scalar() == "false")) {
    value = n.Scalar() == "true";
    return;
  }
  errors_->add(n.Mark(), key_path(key), scalar_text(n) + " is not valid, expected true or false");
}

void YamlSection::text(const char* key, std::string& value, bool allow_empty) {
  YAML::Node n;
  if (!get(key, n)) return;
  if (!n.IsScalar() || (!allow_empty && n.Scalar().empty())) {
    errors_->add(n.Mark(), key_path(key), scalar_text(n) + " is not valid, expected a non-empty text");
    return;
  }
  value = n.Scalar();
}

void YamlSection::choice(const char* key, std::string& value, std::initializer_list<const char*> allowed) {
  YAML::Node n;
  if (!get(key, n)) return;
  std::string options;
  for (const char* a : allowed) {
    if (n.IsScalar() && n.Scalar() == a) {
      value = a;
      return;
    }
    options += (options.empty() ? "" : " | ") + std::string(a);
  }
  errors_->add(n.Mark(), key_path(key), scalar_text(n) + " is not valid, expected one of: " + options);
}

void YamlSection::vec3(const char* key, Eigen::Vector3d& value, double min, double max, const char* unit) {
  YAML::Node n;
  if (!get(key, n)) return;
  Eigen::Vector3d v;
  bool ok = n.IsSequence() && n.size() == 3;
  for (std::size_t i = 0; ok && i < 3; ++i)
    ok = parse_double(n[i], v[static_cast<int>(i)]) && v[static_cast<int>(i)] >= min && v[static_cast<int>(i)] <= max;
  if (!ok) {
    errors_->add(n.Mark(), key_path(key), "is not valid, expected [x, y, z] with each " + format_range(min, max, unit));
    return;
  }
  value = v;
}

void YamlSection::points2(const char* key, std::vector<Eigen::Vector2d>& value, double min, double max,
                          const char* unit) {
  YAML::Node n;
  if (!get(key, n)) return;
  std::vector<Eigen::Vector2d> out;
  bool ok = n.IsSequence();
  for (std::size_t i = 0; ok && i < n.size(); ++i) {
    const YAML::Node p = n[i];
    double x = 0, y = 0;
    ok = p.IsSequence() && p.size() == 2 && parse_double(p[0], x) && parse_double(p[1], y) && x >= min && x <= max &&
         y >= min && y <= max;
    out.emplace_back(x, y);
  }
  if (!ok) {
    errors_->add(n.Mark(), key_path(key),
                 "is not valid, expected a list of [x, y] with each " + format_range(min, max, unit));
    return;
  }
  value = std::move(out);
}

YamlSection YamlSection::section(const char* key) {
  YAML::Node n;
  if (!get(key, n)) n = YAML::Node(YAML::NodeType::Map);
  return YamlSection(n, key_path(key), errors_);
}

std::vector<YamlSection> YamlSection::list(const char* key) {
  std::vector<YamlSection> out;
  YAML::Node n;
  if (!get(key, n)) return out;
  if (!n.IsSequence()) {
    errors_->add(n.Mark(), key_path(key), "is not valid, expected a list");
    return out;
  }
  for (std::size_t i = 0; i < n.size(); ++i) {
    out.emplace_back(n[i], key_path(key) + "[" + std::to_string(i) + "]", errors_);
  }
  return out;
}

void YamlSection::finish() {
  if (!node_.IsMap()) return;
  for (const auto& kv : node_) {
    const std::string key = kv.first.as<std::string>("");
    if (used_.count(key) == 0) {
      errors_->add(kv.first.Mark(), key_path(key.c_str()),
                   "unknown key (misspelt? see the commented defaults in config/)");
    }
  }
}

namespace {

// The document from `in`, then the repeated-key check; every failure one line naming `path`.
Expected<YAML::Node> parse_yaml_stream(std::istream& in, const std::string& path) {
  YAML::Node doc;
  try {
    doc = YAML::Load(in);
  } catch (const YAML::Exception& e) {  // yaml-cpp reports through exceptions; stop them at this boundary
    std::ostringstream line;
    line << path << ":" << e.mark.line + 1 << ":" << e.mark.column + 1 << ": YAML syntax error: " << e.msg;
    return make_error(line.str());
  } catch (const std::exception& e) {  // a read error (std::ios_failure) from the stream under yaml-cpp
    return make_error(path + ": cannot read: " + e.what());
  }
  YamlErrors repeated(path);
  std::size_t values_left = kMaxWalkedValues + 1;  // 0 left: one more than the limit was there
  report_repeated_keys(doc, "", 0, values_left, repeated);
  if (values_left == 0) {
    repeated.add(doc.Mark(), "(top level)",
                 "the document holds more than " + std::to_string(kMaxWalkedValues) +
                     " values once its aliases are expanded (aliases of aliases?); refused");
  }
  if (!repeated.empty()) return make_error(repeated.joined());
  return doc;
}

}  // namespace

Expected<YAML::Node> load_yaml_file(const std::string& path) {
  // A folder opens as a stream but throws std::ios_failure from yaml-cpp's first read: refuse it here.
  if (Status regular = check_regular_file(path, ", not a configuration file"); !regular) return regular.error();
  std::ifstream in(path);
  if (!in) return make_error(path + ": cannot open: " + std::strerror(errno));
  return parse_yaml_stream(in, path);
}

Expected<YAML::Node> parse_yaml_text(const std::string& text, const std::string& path) {
  std::istringstream in(text);
  return parse_yaml_stream(in, path);
}

}  // namespace cellsight::formats
