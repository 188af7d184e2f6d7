// PLY reader and writer. Hand-written because no Debian 12 C++ library we already depend on reads PLY
// (OpenCV's viz module is not in Debian's libopencv-dev core set, PCL would be a large new dependency), and the
// format subset we need is small; every field is bounds-checked because scans come from outside.
#include "formats/ply.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <sstream>

namespace cellsight::formats {
namespace {

enum class Type { kInt8, kUint8, kInt16, kUint16, kInt32, kUint32, kFloat32, kFloat64, kInvalid };

Type parse_type(std::string_view t) {
  if (t == "char" || t == "int8") return Type::kInt8;
  if (t == "uchar" || t == "uint8") return Type::kUint8;
  if (t == "short" || t == "int16") return Type::kInt16;
  if (t == "ushort" || t == "uint16") return Type::kUint16;
  if (t == "int" || t == "int32") return Type::kInt32;
  if (t == "uint" || t == "uint32") return Type::kUint32;
  if (t == "float" || t == "float32") return Type::kFloat32;
  if (t == "double" || t == "float64") return Type::kFloat64;
  return Type::kInvalid;
}

std::size_t type_size(Type t) {
  switch (t) {
    case Type::kInt8:
    case Type::kUint8: return 1;
    case Type::kInt16:
    case Type::kUint16: return 2;
    case Type::kInt32:
    case Type::kUint32:
    case Type::kFloat32: return 4;
    case Type::kFloat64: return 8;
    case Type::kInvalid: return 0;
  }
  return 0;
}

double read_binary(const char* p, Type t) {
  switch (t) {
    case Type::kInt8: {
      std::int8_t v;
      std::memcpy(&v, p, 1);
      return v;
    }
    case Type::kUint8: {
      std::uint8_t v;
      std::memcpy(&v, p, 1);
      return v;
    }
    case Type::kInt16: {
      std::int16_t v;
      std::memcpy(&v, p, 2);
      return v;
    }
    case Type::kUint16: {
      std::uint16_t v;
      std::memcpy(&v, p, 2);
      return v;
    }
    case Type::kInt32: {
      std::int32_t v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case Type::kUint32: {
      std::uint32_t v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case Type::kFloat32: {
      float v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case Type::kFloat64: {
      double v;
      std::memcpy(&v, p, 8);
      return v;
    }
    case Type::kInvalid: break;
  }
  return 0.0;
}

struct Property {
  std::string name;
  Type type = Type::kInvalid;
  bool is_list = false;
  Type count_type = Type::kInvalid;
};

struct Element {
  std::string name;
  std::size_t count = 0;
  std::vector<Property> properties;
};

std::vector<std::string_view> split_words(std::string_view line) {
  std::vector<std::string_view> words;
  std::size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == '\r')) ++i;
    const std::size_t start = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t' && line[i] != '\r') ++i;
    if (i > start) words.push_back(line.substr(start, i - start));
  }
  return words;
}

Error fail(const std::string& what) {
  return make_error("PLY: " + what);
}

// Cursor over ASCII data: whitespace-separated numbers.
struct AsciiCursor {
  std::string_view data;
  std::size_t pos = 0;
  bool next(double& out) {
    while (pos < data.size() && std::isspace(static_cast<unsigned char>(data[pos]))) ++pos;
    if (pos >= data.size()) return false;
    const char* begin = data.data() + pos;
    const char* end = data.data() + data.size();
    const auto [ptr, ec] = std::from_chars(begin, end, out);
    if (ec != std::errc() || ptr == begin) return false;
    pos += static_cast<std::size_t>(ptr - begin);
    return pos >= data.size() || std::isspace(static_cast<unsigned char>(data[pos]));
  }
};

// The header, checked: where the data starts and what it holds.
struct ParsedHeader {
  bool binary = false;
  std::size_t data_start = 0;
  std::vector<Element> elements;
  std::size_t vertex_index = 0;
  int ix = -1, iy = -1, iz = -1;
};

// One line of the header after the magic (words split, comments and empty lines already skipped).
Status parse_header_line(const std::vector<std::string_view>& words, const std::string& where, ParsedHeader& out,
                         bool& have_format) {
  std::vector<Element>& elements = out.elements;
  if (words[0] == "format") {
    if (words.size() != 3 || words[2] != "1.0") return fail(where + "expected 'format <kind> 1.0'");
    if (words[1] == "ascii") {
      out.binary = false;
    } else if (words[1] == "binary_little_endian") {
      out.binary = true;
    } else {
      return fail(where + "format '" + std::string(words[1]) + "' is not supported (ascii or binary_little_endian)");
    }
    have_format = true;
  } else if (words[0] == "element") {
    if (words.size() != 3) return fail(where + "expected 'element <name> <count>'");
    Element e;
    e.name = std::string(words[1]);
    const auto [ptr, ec] = std::from_chars(words[2].data(), words[2].data() + words[2].size(), e.count);
    if (ec != std::errc() || ptr != words[2].data() + words[2].size())
      return fail(where + "element count is not a number");
    elements.push_back(std::move(e));
  } else if (words[0] == "property") {
    if (elements.empty()) return fail(where + "property before any element");
    Property p;
    if (words.size() == 5 && words[1] == "list") {
      p.is_list = true;
      p.count_type = parse_type(words[2]);
      p.type = parse_type(words[3]);
      p.name = std::string(words[4]);
      if (p.count_type == Type::kInvalid || p.type == Type::kInvalid || p.count_type == Type::kFloat32 ||
          p.count_type == Type::kFloat64) {
        return fail(where + "bad list property types");
      }
    } else if (words.size() == 3) {
      p.type = parse_type(words[1]);
      p.name = std::string(words[2]);
      if (p.type == Type::kInvalid) return fail(where + "unknown property type '" + std::string(words[1]) + "'");
    } else {
      return fail(where + "expected 'property <type> <name>'");
    }
    elements.back().properties.push_back(std::move(p));
  } else {
    return fail(where + "unknown keyword '" + std::string(words[0]) + "'");
  }
  return {};
}

// The vertex element and its x, y, z properties (float or double), within the vertex limit.
Status find_vertex_coordinates(ParsedHeader& out, const PlyLimits& limits) {
  const std::vector<Element>& elements = out.elements;
  const Element* vertex = nullptr;
  for (std::size_t i = 0; i < elements.size(); ++i) {
    if (elements[i].name == "vertex") {
      vertex = &elements[i];
      out.vertex_index = i;
      break;
    }
  }
  if (vertex == nullptr) return fail("no 'element vertex' in the header");
  int& ix = out.ix;
  int& iy = out.iy;
  int& iz = out.iz;
  for (std::size_t i = 0; i < vertex->properties.size(); ++i) {
    const Property& p = vertex->properties[i];
    const bool real = !p.is_list && (p.type == Type::kFloat32 || p.type == Type::kFloat64);
    if (p.name == "x") ix = real ? static_cast<int>(i) : -2;
    if (p.name == "y") iy = real ? static_cast<int>(i) : -2;
    if (p.name == "z") iz = real ? static_cast<int>(i) : -2;
  }
  if (ix == -2 || iy == -2 || iz == -2) return fail("vertex x, y, z must be float or double");
  if (ix < 0 || iy < 0 || iz < 0) return fail("vertex element lacks x, y or z");
  if (vertex->count > limits.max_vertices) {
    return fail(std::to_string(vertex->count) + " vertices is more than a scan can have (limit " +
                std::to_string(limits.max_vertices) + ")");
  }
  return {};
}

Expected<ParsedHeader> parse_header(std::string_view bytes, const PlyLimits& limits) {
  if (bytes.substr(0, 4) != "ply\n" && bytes.substr(0, 5) != "ply\r\n") return fail("not a PLY file (no 'ply' magic)");
  // Only the first max_header_bytes may hold the header, the line break after end_header included: a file that is
  // no scan is refused from its first bytes, and a file is judged alike from those bytes alone (formats/input_file).
  const std::string_view window = bytes.substr(0, limits.max_header_bytes);
  const bool window_full = bytes.size() >= limits.max_header_bytes;
  const std::size_t header_end = window.find("end_header");
  if (header_end == std::string_view::npos) {
    if (window_full) {
      return fail("no end_header in the first " + std::to_string(limits.max_header_bytes) + " bytes: not a PLY scan");
    }
    return fail("no end_header: the header is truncated");
  }
  ParsedHeader out;
  std::size_t data_start = window.find('\n', header_end);
  if (data_start == std::string_view::npos) {
    if (window_full) {
      return fail("the end_header line does not end in the first " + std::to_string(limits.max_header_bytes) +
                  " bytes: not a PLY scan");
    }
    return fail("no line break after end_header");
  }
  out.data_start = data_start + 1;
  const std::string_view header = bytes.substr(0, header_end);
  bool have_format = false;
  std::size_t line_start = 0;
  int line_number = 0;
  while (line_start < header.size()) {
    std::size_t line_end = header.find('\n', line_start);
    if (line_end == std::string_view::npos) line_end = header.size();
    const auto words = split_words(header.substr(line_start, line_end - line_start));
    line_start = line_end + 1;
    ++line_number;
    if (words.empty() || words[0] == "ply" || words[0] == "comment" || words[0] == "obj_info") continue;
    const std::string where = "header line " + std::to_string(line_number) + ": ";
    if (Status line = parse_header_line(words, where, out, have_format); !line) return line.error();
  }
  if (!have_format) return fail("the header has no format line");
  if (Status vertex = find_vertex_coordinates(out, limits); !vertex) return vertex.error();
  return out;
}

std::size_t saturating_add(std::size_t a, std::size_t b) {
  return b > SIZE_MAX - a ? SIZE_MAX : a + b;
}
std::size_t saturating_mul(std::size_t a, std::size_t b) {
  return b != 0 && a > SIZE_MAX / b ? SIZE_MAX : a * b;
}

// The least data the elements up to and including vertex need: fixed sizes (a list at least its count) in binary,
// one digit and a separator per value in ASCII.
std::size_t min_data_bytes(const ParsedHeader& h) {
  std::size_t total = 0;
  for (std::size_t e = 0; e <= h.vertex_index; ++e) {
    const Element& element = h.elements[e];
    std::size_t row = 0;
    for (const Property& p : element.properties) {
      constexpr std::size_t kAsciiValueBytes = 2;
      row += h.binary ? type_size(p.is_list ? p.count_type : p.type) : kAsciiValueBytes;
    }
    total = saturating_add(total, saturating_mul(element.count, row));
  }
  return !h.binary && total > 0 ? total - 1 : total;  // the last value needs no separator
}

// Appends the vertex whose property values are `values`. False when a coordinate is not finite or lies beyond the
// range of the float a scan point stores (a larger double would become an infinity, or undefined behaviour).
bool add_vertex(const std::vector<double>& values, const ParsedHeader& h, std::vector<algo::ScanPoint>& points) {
  const double xyz[3] = {values[static_cast<std::size_t>(h.ix)], values[static_cast<std::size_t>(h.iy)],
                         values[static_cast<std::size_t>(h.iz)]};
  for (const double v : xyz) {
    if (!(std::fabs(v) <= std::numeric_limits<float>::max())) return false;  // NaN fails too
  }
  points.push_back({static_cast<float>(xyz[0]), static_cast<float>(xyz[1]), static_cast<float>(xyz[2]), 0, 0});
  return true;
}

Error bad_coordinate(std::size_t vertex) {
  return fail("vertex " + std::to_string(vertex) + " has a non-finite coordinate or one beyond float range");
}

}  // namespace

Expected<PlyHeader> parse_ply_header(std::string_view bytes, const PlyLimits& limits) {
  auto h = parse_header(bytes, limits);
  if (!h) return h.error();
  return PlyHeader{h->binary, h->data_start, h->elements[h->vertex_index].count, min_data_bytes(*h)};
}

Expected<std::vector<algo::ScanPoint>> parse_ply(std::string_view bytes, const PlyLimits& limits) {
  auto parsed = parse_header(bytes, limits);
  if (!parsed) return parsed.error();
  const bool binary = parsed->binary;
  const std::vector<Element>& elements = parsed->elements;
  const std::size_t vertex_index = parsed->vertex_index;
  const Element* vertex = &elements[vertex_index];

  // --- data: skip the elements before vertex, then read vertices ---
  const std::string_view data = bytes.substr(parsed->data_start);
  std::vector<algo::ScanPoint> points;
  // The count is the header's word: reserve no more than the data could hold (a vertex takes at least 6 bytes, "1 2 3"
  // and a separator; 12 in binary), so a short text claiming 20 M vertices does not allocate 320 MB to be refused.
  constexpr std::size_t kMinVertexBytes = 6;
  points.reserve(std::min(vertex->count, data.size() / kMinVertexBytes + 1));
  std::vector<double> values(vertex->properties.size());
  if (binary) {
    std::size_t pos = 0;
    auto skip_element_row = [&](const Element& e) -> bool {
      for (const Property& p : e.properties) {
        if (p.is_list) {
          const std::size_t cs = type_size(p.count_type);
          if (pos + cs > data.size()) return false;
          const double n = read_binary(data.data() + pos, p.count_type);
          pos += cs;
          if (n < 0) return false;
          const std::size_t bytes_needed = static_cast<std::size_t>(n) * type_size(p.type);
          if (bytes_needed > data.size() - pos) return false;
          pos += bytes_needed;
        } else {
          pos += type_size(p.type);
          if (pos > data.size()) return false;
        }
      }
      return true;
    };
    for (std::size_t e = 0; e < vertex_index; ++e) {
      if (elements[e].properties.empty()) continue;  // rows of nothing: a count of 2^64 - 1 must not spin for ever
      for (std::size_t r = 0; r < elements[e].count; ++r) {
        if (!skip_element_row(elements[e])) return fail("data truncated in element '" + elements[e].name + "'");
      }
    }
    for (std::size_t r = 0; r < vertex->count; ++r) {
      for (std::size_t i = 0; i < vertex->properties.size(); ++i) {
        const Property& p = vertex->properties[i];
        if (p.is_list) {
          Element single{"", 1, {p}};
          if (!skip_element_row(single)) return fail("data truncated at vertex " + std::to_string(r));
          continue;
        }
        const std::size_t size = type_size(p.type);
        if (pos + size > data.size())
          return fail("data truncated at vertex " + std::to_string(r) + " of " + std::to_string(vertex->count));
        values[i] = read_binary(data.data() + pos, p.type);
        pos += size;
      }
      if (!add_vertex(values, *parsed, points)) return bad_coordinate(r);
    }
  } else {
    AsciiCursor cursor{data};
    double v = 0;
    auto skip_element_row = [&](const Element& e) -> bool {
      for (const Property& p : e.properties) {
        if (p.is_list) {
          if (!cursor.next(v) || v < 0 || v > 1e6) return false;
          for (int k = 0; k < static_cast<int>(v); ++k) {
            double ignored = 0;
            if (!cursor.next(ignored)) return false;
          }
        } else if (!cursor.next(v)) {
          return false;
        }
      }
      return true;
    };
    for (std::size_t e = 0; e < vertex_index; ++e) {
      if (elements[e].properties.empty()) continue;  // rows of nothing: a count of 2^64 - 1 must not spin for ever
      for (std::size_t r = 0; r < elements[e].count; ++r) {
        if (!skip_element_row(elements[e])) return fail("bad or missing data in element '" + elements[e].name + "'");
      }
    }
    for (std::size_t r = 0; r < vertex->count; ++r) {
      for (std::size_t i = 0; i < vertex->properties.size(); ++i) {
        const Property& p = vertex->properties[i];
        if (p.is_list) {
          Element single{"", 1, {p}};
          if (!skip_element_row(single)) return fail("bad or missing data at vertex " + std::to_string(r));
          continue;
        }
        if (!cursor.next(values[i])) {
          return fail("bad or missing number at vertex " + std::to_string(r) + " of " + std::to_string(vertex->count));
        }
      }
      if (!add_vertex(values, *parsed, points)) return bad_coordinate(r);
    }
  }
  return points;
}

namespace {
std::string header(std::size_t count, const char* format) {
  std::ostringstream h;
  h << "ply\nformat " << format << " 1.0\ncomment cellsight scan, carrier frame, metres\nelement vertex " << count
    << "\nproperty float x\nproperty float y\nproperty float z\nproperty ushort frame\nproperty ushort "
       "row\nend_header\n";
  return h.str();
}
}  // namespace

std::string write_ply_binary(std::span<const algo::ScanPoint> points) {
  std::string out = header(points.size(), "binary_little_endian");
  constexpr std::size_t kRecord = 3 * sizeof(float) + 2 * sizeof(std::uint16_t);
  const std::size_t start = out.size();
  out.resize(start + points.size() * kRecord);
  char* p = out.data() + start;
  for (const algo::ScanPoint& s : points) {  // x86-64 and aarch64 Linux are little-endian, as the format says
    std::memcpy(p, &s.x, 4);
    std::memcpy(p + 4, &s.y, 4);
    std::memcpy(p + 8, &s.z, 4);
    std::memcpy(p + 12, &s.frame, 2);
    std::memcpy(p + 14, &s.row, 2);
    p += kRecord;
  }
  return out;
}

std::string write_ply_ascii(std::span<const algo::ScanPoint> points) {
  std::ostringstream out;
  out << header(points.size(), "ascii");
  out.precision(9);
  for (const algo::ScanPoint& s : points)
    out << s.x << ' ' << s.y << ' ' << s.z << ' ' << s.frame << ' ' << s.row << '\n';
  return out.str();
}

}  // namespace cellsight::formats
