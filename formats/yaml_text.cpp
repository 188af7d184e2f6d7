// The text of the YAML files cellsight writes: one copy of the helpers the calibration and manifest files share.
#include "formats/yaml_text.hpp"

#include <cerrno>
#include <cinttypes>
#include <cstdio>
#include <cstdlib>

namespace cellsight::formats {

std::string yaml_quoted(std::string_view s) {
  std::string out = "\"";
  for (const char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    if (c == '\n') {
      out += "\\n";
      continue;
    }
    out += c;
  }
  return out + "\"";
}

std::string number(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}

std::string hex32(std::uint32_t v) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "%08" PRIx32, v);
  return buf;
}

bool parse_hex32(const std::string& text, std::uint32_t& out) {
  if (text.size() != 8) return false;
  char* end = nullptr;
  errno = 0;
  const unsigned long v = std::strtoul(text.c_str(), &end, 16);
  if (errno != 0 || end != text.c_str() + text.size()) return false;
  out = static_cast<std::uint32_t>(v);
  return true;
}

std::size_t checksum_line_start(std::string_view text, std::string_view key) {
  const std::string line_key = std::string(key) + ":";
  std::size_t found = std::string_view::npos;
  for (std::size_t pos = text.find(line_key); pos != std::string_view::npos; pos = text.find(line_key, pos + 1)) {
    if (pos == 0 || text[pos - 1] == '\n') found = pos;
  }
  return found;
}

}  // namespace cellsight::formats
