// Argument parsing for the modes that take files (teach, train, classify, eval, parts, run): options with values,
// flags and positional words, each checked against what the mode knows.
#pragma once

#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <map>
#include <set>
#include <string>
#include <vector>

namespace cellsight::cli {

struct ModeArgs {
  std::map<std::string, std::string> values;
  std::set<std::string> flags;
  std::vector<std::string> positional;

  [[nodiscard]] bool has(const std::string& flag) const { return flags.count(flag) != 0; }
  [[nodiscard]] const std::string* value(const std::string& key) const {
    const auto it = values.find(key);
    return it == values.end() ? nullptr : &it->second;
  }
};

// `value_options` take the next word; `flag_options` stand alone; anything else starting with "--" is an error,
// as is a missing value. Words not starting with "--" are positional.
[[nodiscard]] inline bool parse_mode_args(const std::vector<std::string>& words,
                                          const std::set<std::string>& value_options,
                                          const std::set<std::string>& flag_options, ModeArgs& out,
                                          std::string& error) {
  for (std::size_t i = 0; i < words.size(); ++i) {
    const std::string& w = words[i];
    if (w.rfind("--", 0) == 0) {
      if (value_options.count(w) != 0) {
        if (i + 1 >= words.size()) {
          error = w + " needs a value";
          return false;
        }
        out.values[w] = words[++i];
      } else if (flag_options.count(w) != 0) {
        out.flags.insert(w);
      } else {
        error = "unknown option " + w;
        return false;
      }
    } else {
      out.positional.push_back(w);
    }
  }
  return true;
}

// A whole number in [min, max]; false otherwise.
[[nodiscard]] inline bool parse_whole(const std::string& text, std::int64_t min, std::int64_t max, std::int64_t& out) {
  if (text.empty()) return false;
  char* end = nullptr;
  errno = 0;
  const long long v = std::strtoll(text.c_str(), &end, 10);
  if (*end != '\0' || errno != 0 || v < min || v > max) return false;
  out = v;
  return true;
}

}  // namespace cellsight::cli
