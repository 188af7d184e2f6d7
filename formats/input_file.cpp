// Reading files from outside: refused from a stat and the first bytes when they cannot be what they should be.
#include "formats/input_file.hpp"

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>

#include "base/file_read.hpp"

namespace cellsight::formats {
namespace {

constexpr const char* kScanIsPly = "; a scan is a PLY file";

struct CheckedPly {
  std::string bytes;  // the first bytes, header included
  std::size_t file_bytes = 0;
};

// Opens `path` into `in`, reads at most limits.max_header_bytes and checks the header against the file's size.
Expected<CheckedPly> open_ply(const std::string& path, std::ifstream& in, const formats::PlyLimits& limits) {
  auto size = base::regular_file_size(path, kScanIsPly);
  if (!size) return size.error();
  in.open(path, std::ios::binary);
  if (!in) return make_error(path + ": cannot open: " + std::strerror(errno));
  CheckedPly out;
  out.file_bytes = *size;
  out.bytes.resize(std::min(*size, limits.max_header_bytes));
  in.read(out.bytes.data(), static_cast<std::streamsize>(out.bytes.size()));
  if (in.bad()) return make_error(path + ": read failed");
  out.bytes.resize(static_cast<std::size_t>(in.gcount()));
  auto header = formats::parse_ply_header(out.bytes, limits);
  if (!header) return make_error(path + ": " + header.error().message);
  const std::size_t after_header = out.file_bytes - std::min(out.file_bytes, header->data_start);
  if (header->min_data_bytes > after_header) {
    return make_error(path + ": PLY: the header declares " + std::to_string(header->vertex_count) +
                      " vertices (at least " + std::to_string(header->min_data_bytes) +
                      " bytes of data), the file holds " + std::to_string(after_header) +
                      " after the header: it is truncated");
  }
  return out;
}

}  // namespace

Status check_regular_file(const std::string& path, const std::string& what) {
  auto size = base::regular_file_size(path, what);
  if (!size) return size.error();
  return {};
}

Status check_ply_file(const std::string& path, const formats::PlyLimits& limits) {
  std::ifstream in;
  auto ply = open_ply(path, in, limits);
  if (!ply) return ply.error();
  return {};
}

Expected<std::string> read_ply_file(const std::string& path, const formats::PlyLimits& limits) {
  std::ifstream in;
  auto ply = open_ply(path, in, limits);
  if (!ply) return ply.error();
  std::string bytes = std::move(ply->bytes);
  const std::size_t have = bytes.size();
  bytes.resize(std::max(have, ply->file_bytes));
  in.read(bytes.data() + have, static_cast<std::streamsize>(bytes.size() - have));
  if (in.bad()) return make_error(path + ": read failed");
  bytes.resize(have + static_cast<std::size_t>(in.gcount()));
  return bytes;
}

Expected<std::vector<algo::ScanPoint>> load_ply_file(const std::string& path, const formats::PlyLimits& limits) {
  auto bytes = read_ply_file(path, limits);
  if (!bytes) return bytes.error();
  auto points = formats::parse_ply(*bytes, limits);
  if (!points) return make_error(path + ": " + points.error().message);
  return points;
}

}  // namespace cellsight::formats
