// The text of the YAML files cellsight writes (calibration, manifest): exact numbers, quoted strings, checksums in
// hex and the checksum line that ends each file. One copy for every writer and reader.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

namespace cellsight::formats {

// YAML double-quoted scalar: '"' and '\' escaped, a line break written as \n.
[[nodiscard]] std::string yaml_quoted(std::string_view s);

// "%.17g": reads back as the very same double.
[[nodiscard]] std::string number(double v);

// Eight lower-case hex digits.
[[nodiscard]] std::string hex32(std::uint32_t v);

// Exactly eight hex digits into `out`; false (and `out` untouched) otherwise.
[[nodiscard]] bool parse_hex32(const std::string& text, std::uint32_t& out);

// Where the checksum line starts: the last line that begins with "KEY:", or npos.
[[nodiscard]] std::size_t checksum_line_start(std::string_view text, std::string_view key);

}  // namespace cellsight::formats
