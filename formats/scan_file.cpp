// Compact taught-scan files: quantise, split into planes, delta + zig-zag + LEB128, zlib. Every field of a file is
// checked before it is used, because a database can be copied, damaged or edited.
#include "formats/scan_file.hpp"

#include <zlib.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>

#include "base/crc32.hpp"

namespace cellsight::formats {
namespace {

constexpr std::size_t kAxes = 3;
constexpr std::size_t kPlanes = 5;  // x, y, z, frame, row
constexpr int kDeflateLevel = 6;    // zlib's default: within a few per cent of level 9 here, at a third of the time
// The most bytes an inflated payload can have per compressed byte: deflate codes at most 258 bytes in 2 bits, so a
// valid stream never expands more than ~1032 times; a header that claims more is refused before anything is
// allocated.
constexpr std::uint64_t kMaxInflateRatio = 1032;
constexpr std::uint32_t kMaxStepNm = 1'000'000;  // 1 mm: anything coarser would not be a scan any more
constexpr std::size_t kMaxVarintBytes = 5;       // a zig-zagged difference of two uint32 values takes 33 bits
constexpr std::size_t kMaxIdVarintBytes = 3;     // frame and row: 17 bits
constexpr std::uint64_t kMaxId = std::numeric_limits<std::uint16_t>::max();

// Field offsets in the header.
constexpr std::size_t kOffVersion = 8, kOffHeaderBytes = 12, kOffCount = 16, kOffStep = 24, kOffFlags = 28,
                      kOffOrigin = 32, kOffExtent = 44, kOffRaw = 56, kOffCompressed = 64, kOffReserved = 72,
                      kOffCrc = 76;

struct Header {
  std::uint32_t version = kScanFileVersion;
  std::uint32_t header_bytes = kScanFileHeaderBytes;
  std::uint64_t count = 0;
  std::uint32_t step_nm = kScanStepNm;
  std::uint32_t flags = 0;
  std::array<std::int32_t, kAxes> origin{};
  std::array<std::uint32_t, kAxes> extent{};
  std::uint64_t raw_bytes = 0;
  std::uint64_t compressed_bytes = 0;
};

template <class T>
void put(std::string& out, std::size_t at, T value) {
  std::memcpy(out.data() + at, &value, sizeof value);  // x86-64 and aarch64 Linux are little-endian, as the file
}
template <class T>
T get(std::string_view in, std::size_t at) {
  T value;
  std::memcpy(&value, in.data() + at, sizeof value);
  return value;
}

std::string header_bytes(const Header& h) {
  std::string out(kScanFileHeaderBytes, '\0');
  std::memcpy(out.data(), kScanFileMagic.data(), kScanFileMagic.size());
  put(out, kOffVersion, h.version);
  put(out, kOffHeaderBytes, h.header_bytes);
  put(out, kOffCount, h.count);
  put(out, kOffStep, h.step_nm);
  put(out, kOffFlags, h.flags);
  for (std::size_t a = 0; a < kAxes; ++a) {
    put(out, kOffOrigin + 4 * a, h.origin[a]);
    put(out, kOffExtent + 4 * a, h.extent[a]);
  }
  put(out, kOffRaw, h.raw_bytes);
  put(out, kOffCompressed, h.compressed_bytes);
  put(out, kOffCrc, base::crc32(std::string_view(out).substr(0, kOffCrc)));
  return out;
}

Error fail(const std::string& what) {
  return make_error("scan file: " + what);
}

std::uint64_t zigzag(std::int64_t v) {
  return (static_cast<std::uint64_t>(v) << 1) ^ static_cast<std::uint64_t>(v >> 63);
}
std::int64_t unzigzag(std::uint64_t u) {
  return static_cast<std::int64_t>(u >> 1) ^ -static_cast<std::int64_t>(u & 1);
}

void put_varint(std::string& out, std::uint64_t v) {
  constexpr std::uint64_t kLow7 = 0x7F, kMore = 0x80;
  while (v > kLow7) {
    out.push_back(static_cast<char>((v & kLow7) | kMore));
    v >>= 7;
  }
  out.push_back(static_cast<char>(v));
}

// One plane: the differences of consecutive values, zig-zagged, as varints.
template <class Value>
void put_plane(std::string& out, std::span<const Value> values) {
  std::int64_t previous = 0;
  for (const Value v : values) {
    put_varint(out, zigzag(static_cast<std::int64_t>(v) - previous));
    previous = static_cast<std::int64_t>(v);
  }
}

// Quantised coordinates relative to the origin; refuses what cannot be quantised.
Status quantise(std::span<const algo::ScanPoint> points, double step_m, Header& h,
                std::array<std::vector<std::uint32_t>, kAxes>& q) {
  std::array<std::vector<std::int64_t>, kAxes> steps;
  std::array<std::int64_t, kAxes> lo{}, hi{};
  lo.fill(std::numeric_limits<std::int64_t>::max());
  hi.fill(std::numeric_limits<std::int64_t>::min());
  constexpr double kLimit = std::numeric_limits<std::int32_t>::max();
  for (std::size_t a = 0; a < kAxes; ++a) steps[a].resize(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    const std::array<float, kAxes> xyz = {points[i].x, points[i].y, points[i].z};
    for (std::size_t a = 0; a < kAxes; ++a) {
      const double s = std::round(static_cast<double>(xyz[a]) / step_m);
      if (!(std::fabs(s) <= kLimit)) {  // NaN fails too
        return fail("point " + std::to_string(i) + " has a non-finite coordinate or one beyond +-" +
                    std::to_string(kLimit * step_m) + " m: not a scan");
      }
      steps[a][i] = static_cast<std::int64_t>(s);
      lo[a] = std::min(lo[a], steps[a][i]);
      hi[a] = std::max(hi[a], steps[a][i]);
    }
  }
  for (std::size_t a = 0; a < kAxes; ++a) {
    h.origin[a] = points.empty() ? 0 : static_cast<std::int32_t>(lo[a]);
    h.extent[a] = points.empty() ? 0 : static_cast<std::uint32_t>(hi[a] - lo[a]);
    q[a].resize(points.size());
    for (std::size_t i = 0; i < points.size(); ++i) q[a][i] = static_cast<std::uint32_t>(steps[a][i] - lo[a]);
  }
  return {};
}

}  // namespace

bool is_scan_file(std::string_view bytes) {
  return bytes.substr(0, kScanFileMagic.size()) == kScanFileMagic;
}

Expected<std::string> write_scan_file(std::span<const algo::ScanPoint> points, std::uint32_t step_nm) {
  if (step_nm == 0 || step_nm > kMaxStepNm) return fail("step of " + std::to_string(step_nm) + " nm is not 1..1e6");
  Header h;
  h.count = points.size();
  h.step_nm = step_nm;
  std::array<std::vector<std::uint32_t>, kAxes> q;
  if (Status ok = quantise(points, step_nm * 1e-9, h, q); !ok) return ok.error();
  std::vector<std::uint16_t> frames(points.size()), rows(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    frames[i] = points[i].frame;
    rows[i] = points[i].row;
  }
  std::string payload;
  payload.reserve(points.size() * (kPlanes + 2));
  for (const auto& plane : q) put_plane<std::uint32_t>(payload, plane);
  put_plane<std::uint16_t>(payload, frames);
  put_plane<std::uint16_t>(payload, rows);
  h.raw_bytes = payload.size();

  uLongf compressed_bytes = compressBound(static_cast<uLong>(payload.size()));
  std::string out(kScanFileHeaderBytes + compressed_bytes, '\0');
  const int rc =
      compress2(reinterpret_cast<Bytef*>(out.data() + kScanFileHeaderBytes), &compressed_bytes,
                reinterpret_cast<const Bytef*>(payload.data()), static_cast<uLong>(payload.size()), kDeflateLevel);
  if (rc != Z_OK) return fail("zlib could not compress the scan (error " + std::to_string(rc) + ")");
  out.resize(kScanFileHeaderBytes + compressed_bytes);
  h.compressed_bytes = compressed_bytes;
  const std::string head = header_bytes(h);
  std::memcpy(out.data(), head.data(), head.size());
  return out;
}

namespace {

// The header, every field checked against the others and against the file's size.
Expected<Header> parse_header(std::string_view bytes, const ScanFileLimits& limits) {
  if (!is_scan_file(bytes)) return fail("not a cellsight scan file (no CSCAN magic)");
  if (bytes.size() < kOffVersion + sizeof(std::uint32_t)) return fail("truncated inside the header");
  Header h;
  h.version = get<std::uint32_t>(bytes, kOffVersion);
  if (h.version != kScanFileVersion) {
    return fail("format version " + std::to_string(h.version) + " is not supported (this cellsight reads version " +
                std::to_string(kScanFileVersion) + ")");
  }
  if (bytes.size() < kScanFileHeaderBytes) {
    return fail("truncated: " + std::to_string(bytes.size()) + " bytes, the header alone takes " +
                std::to_string(kScanFileHeaderBytes));
  }
  if (get<std::uint32_t>(bytes, kOffCrc) != base::crc32(bytes.substr(0, kOffCrc))) {
    return fail("the header is damaged (its checksum does not match)");
  }
  h.header_bytes = get<std::uint32_t>(bytes, kOffHeaderBytes);
  h.count = get<std::uint64_t>(bytes, kOffCount);
  h.step_nm = get<std::uint32_t>(bytes, kOffStep);
  h.flags = get<std::uint32_t>(bytes, kOffFlags);
  for (std::size_t a = 0; a < kAxes; ++a) {
    h.origin[a] = get<std::int32_t>(bytes, kOffOrigin + 4 * a);
    h.extent[a] = get<std::uint32_t>(bytes, kOffExtent + 4 * a);
  }
  h.raw_bytes = get<std::uint64_t>(bytes, kOffRaw);
  h.compressed_bytes = get<std::uint64_t>(bytes, kOffCompressed);
  if (h.header_bytes != kScanFileHeaderBytes || h.flags != 0 || get<std::uint32_t>(bytes, kOffReserved) != 0) {
    return fail("header size, flags or reserved bytes are not version 1's");
  }
  if (h.step_nm == 0 || h.step_nm > kMaxStepNm) return fail("step of " + std::to_string(h.step_nm) + " nm");
  if (h.count > limits.max_points) {
    return fail(std::to_string(h.count) + " points is more than a scan can have (limit " +
                std::to_string(limits.max_points) + ")");
  }
  for (std::size_t a = 0; a < kAxes; ++a) {
    if (static_cast<std::int64_t>(h.origin[a]) + h.extent[a] > std::numeric_limits<std::int32_t>::max())
      return fail("the declared extent reaches beyond the quantised range");
  }
  const std::uint64_t body = bytes.size() - kScanFileHeaderBytes;
  if (h.compressed_bytes != body) {
    return fail(h.compressed_bytes > body ? "truncated: " + std::to_string(body) + " compressed bytes of the " +
                                                std::to_string(h.compressed_bytes) + " declared"
                                          : std::to_string(body - h.compressed_bytes) + " bytes after the data");
  }
  // Each point takes 1..5 bytes in each coordinate plane and 1..3 in frame and row.
  const std::uint64_t least = h.count * kPlanes;
  const std::uint64_t most = h.count * (kAxes * kMaxVarintBytes + 2 * kMaxIdVarintBytes);
  // And the compressed stream is no larger than zlib makes it from the payload (which also keeps both in zlib's
  // 32-bit counters: at most 21 bytes x 20 M points).
  if (h.raw_bytes < least || h.raw_bytes > most || h.raw_bytes > h.compressed_bytes * kMaxInflateRatio ||
      h.compressed_bytes > compressBound(static_cast<uLong>(h.raw_bytes))) {
    return fail("the declared sizes do not fit " + std::to_string(h.count) + " points (" + std::to_string(h.raw_bytes) +
                " bytes from " + std::to_string(h.compressed_bytes) + " compressed)");
  }
  return h;
}

// Inflates exactly h.raw_bytes: a stream that ends early, runs on or is damaged is refused.
Expected<std::string> inflate_payload(std::string_view body, const Header& h) {
  std::string out(h.raw_bytes, '\0');
  z_stream z{};
  if (inflateInit(&z) != Z_OK) return fail("zlib could not start");
  z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(body.data()));
  z.avail_in = static_cast<uInt>(body.size());  // within uInt: raw <= 21 x 20 M and compressed <= ~raw
  z.next_out = reinterpret_cast<Bytef*>(out.data());
  z.avail_out = static_cast<uInt>(out.size());
  int rc = inflate(&z, Z_FINISH);
  bool more = false;
  if (rc != Z_STREAM_END && rc != Z_DATA_ERROR && z.avail_out == 0) {
    unsigned char extra = 0;  // more to come? one more byte tells
    z.next_out = &extra;
    z.avail_out = 1;
    rc = inflate(&z, Z_FINISH);
    more = z.avail_out == 0;
  }
  const std::string message = z.msg != nullptr ? z.msg : "";
  const uLong produced = z.total_out;
  const uInt left_in = z.avail_in;
  inflateEnd(&z);
  if (more) {
    return fail("the data inflates to more than the declared " + std::to_string(h.raw_bytes) + " bytes");
  }
  if (rc == Z_DATA_ERROR) return fail("the compressed data is damaged (" + message + ")");
  if (rc != Z_STREAM_END) {
    return fail("the compressed data ends early (" + std::to_string(produced) + " of " + std::to_string(h.raw_bytes) +
                " bytes inflated)");
  }
  if (produced != h.raw_bytes) {
    return fail("the data inflates to " + std::to_string(produced) + " bytes, fewer than the declared " +
                std::to_string(h.raw_bytes));
  }
  if (left_in != 0) return fail(std::to_string(left_in) + " bytes after the compressed stream");
  return out;
}

// Reads one plane, adding into `values` (start 0) and keeping each within [0, most].
struct PlaneReader {
  std::string_view payload;
  std::size_t pos = 0;

  Status read(std::size_t count, std::uint64_t most, std::size_t max_bytes, std::vector<std::uint32_t>& values,
              const char* name) {
    values.resize(count);
    std::int64_t value = 0;
    for (std::size_t i = 0; i < count; ++i) {
      std::uint64_t u = 0;
      std::size_t n = 0;
      for (;; ++n) {
        if (n == max_bytes || pos == payload.size())
          return fail(std::string(name) + ": bad difference at point " + std::to_string(i));
        const auto byte = static_cast<unsigned char>(payload[pos++]);
        u |= static_cast<std::uint64_t>(byte & 0x7FU) << (7 * n);
        if ((byte & 0x80U) == 0) break;
      }
      value += unzigzag(u);
      if (value < 0 || static_cast<std::uint64_t>(value) > most) {
        return fail(std::string(name) + " of point " + std::to_string(i) + " lies beyond the declared range");
      }
      values[i] = static_cast<std::uint32_t>(value);
    }
    return {};
  }
};

}  // namespace

Expected<std::vector<algo::ScanPoint>> parse_scan_file(std::string_view bytes, const ScanFileLimits& limits) {
  auto h = parse_header(bytes, limits);
  if (!h) return h.error();
  auto payload = inflate_payload(bytes.substr(kScanFileHeaderBytes), *h);
  if (!payload) return payload.error();
  const auto count = static_cast<std::size_t>(h->count);
  PlaneReader reader{*payload};
  std::array<std::vector<std::uint32_t>, kPlanes> planes;
  constexpr std::array<const char*, kPlanes> kNames = {"x", "y", "z", "frame", "row"};
  for (std::size_t p = 0; p < kPlanes; ++p) {
    const bool axis = p < kAxes;
    if (Status ok = reader.read(count, axis ? h->extent[p] : kMaxId, axis ? kMaxVarintBytes : kMaxIdVarintBytes,
                                planes[p], kNames[p]);
        !ok) {
      return ok.error();
    }
  }
  if (reader.pos != payload->size()) {
    return fail(std::to_string(payload->size() - reader.pos) + " bytes of data beyond the " + std::to_string(count) +
                " points");
  }
  const double step_m = h->step_nm * 1e-9;
  std::vector<algo::ScanPoint> points(count);
  for (std::size_t i = 0; i < count; ++i) {
    const auto coord = [&](std::size_t a) {
      return static_cast<float>(static_cast<double>(static_cast<std::int64_t>(h->origin[a]) + planes[a][i]) * step_m);
    };
    points[i] = {coord(0), coord(1), coord(2), static_cast<std::uint16_t>(planes[3][i]),
                 static_cast<std::uint16_t>(planes[4][i])};
  }
  return points;
}

}  // namespace cellsight::formats
