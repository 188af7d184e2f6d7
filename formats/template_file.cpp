// Template files: streaming atomic write, memory-mapped checked open (built from a scan by template_build.cpp).
#include "formats/template_file.hpp"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cerrno>
#include <chrono>
#include <cinttypes>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <limits>
#include <type_traits>
#include <utility>

#include "base/atomic_file.hpp"
#include "base/crc32.hpp"
#include "formats/template_grid.hpp"

namespace cellsight::formats {
namespace {

using template_grid::dims_of;
using template_grid::number;
using template_grid::validate_grid;

static_assert(std::endian::native == std::endian::little, "template files store numbers as the host does");
static_assert(std::is_trivially_copyable_v<algo::SurfaceCell> && std::is_standard_layout_v<algo::SurfaceCell>,
              "SurfaceCell is read in place from the mapping");

constexpr std::array<char, 8> kMagic = {'\x89', 'D', 'M', 'A', 'P', '\r', '\n', '\x1a'};  // PNG-style transfer check
constexpr std::uint32_t kByteOrderMark = 0x01020304u;
constexpr std::uint32_t kVersionOneFullGrid = 1;
constexpr std::size_t kSurfaceCellBytes = sizeof(algo::SurfaceCell);
constexpr std::size_t kTableEntryBytes = sizeof(std::uint16_t);
constexpr std::size_t kHeaderCrcBytes = kTemplateHeaderBytes - sizeof(std::uint32_t);
// Origin and resolution of the file must equal the configured grid to this (metres): far below any meaningful
// difference, far above the rounding of a number read back from text.
constexpr double kGridToleranceM = 1e-9;
constexpr double kMmPerM = 1000.0;
constexpr double kMsPerS = 1000.0;

// Version 2 header, exactly as on disk.
struct TemplateHeader {
  char magic[8];
  std::uint32_t format_version;
  std::uint32_t header_bytes;
  std::uint32_t byte_order;
  std::uint32_t section_alignment;
  std::int32_t nx, ny, nz;
  std::uint32_t plc_id;
  double resolution_m;
  double origin_m[3];
  double distance_unit_m;
  double band_m;
  double centroid_m[2];
  std::uint64_t occupied_cells;
  std::uint64_t surface_cell_count;
  std::uint64_t surface_offset;
  std::uint64_t brick_count;
  std::uint64_t table_offset;
  std::uint64_t stored_bricks;
  std::uint64_t bricks_offset;
  std::uint64_t file_bytes;
  std::int64_t created_unix_s;
  std::uint32_t body_crc32;
  std::uint32_t brick_edge;
  char part_name[kTemplatePartNameCapacity];
  std::uint8_t reserved[4];
  std::uint32_t header_crc32;
};
static_assert(sizeof(TemplateHeader) == kTemplateHeaderBytes);
static_assert(std::is_trivially_copyable_v<TemplateHeader> && std::is_standard_layout_v<TemplateHeader>);
static_assert(offsetof(TemplateHeader, format_version) == 8 && offsetof(TemplateHeader, byte_order) == 16 &&
                  offsetof(TemplateHeader, resolution_m) == 40 && offsetof(TemplateHeader, occupied_cells) == 104 &&
                  offsetof(TemplateHeader, part_name) == 184 &&
                  offsetof(TemplateHeader, body_crc32) == kTemplateBodyCrcOffset &&
                  offsetof(TemplateHeader, header_crc32) == kHeaderCrcBytes,
              "magic, version and byte order sit where version 1 had them, so a version 1 file is recognised");

std::string errno_text(int error) {
  return std::strerror(error);
}

std::size_t align_up(std::size_t n) {
  return (n + kTemplateSectionAlignment - 1) / kTemplateSectionAlignment * kTemplateSectionAlignment;
}

std::uint32_t header_crc(const TemplateHeader& h) {
  return base::crc32_update(base::kCrc32Empty, &h, kHeaderCrcBytes);
}

// Where the sections of a file with these counts lie.
struct Layout {
  std::size_t surface_offset = 0;
  std::size_t table_offset = 0;
  std::size_t bricks_offset = 0;
  std::size_t file_bytes = 0;
};
Layout layout_for(std::size_t surface_cells, std::size_t brick_count, std::size_t stored_bricks) {
  Layout l;
  l.surface_offset = align_up(kTemplateHeaderBytes);
  l.table_offset = align_up(l.surface_offset + surface_cells * kSurfaceCellBytes);
  l.bricks_offset = align_up(l.table_offset + 2 * brick_count * kTableEntryBytes);
  l.file_bytes = l.bricks_offset + stored_bricks * algo::BrickGrid::kBrickCells;
  return l;
}

// One contiguous piece of the body as written: either bytes of the model or `bytes` zeros.
struct Segment {
  const void* data;  // nullptr: zeros
  std::size_t bytes;
};
constexpr std::array<std::uint8_t, kTemplateSectionAlignment> kZeros{};

std::array<Segment, 7> body_segments(const TemplateModel& model, const Layout& l) {
  const std::size_t surface_bytes = model.surface_cells.size() * kSurfaceCellBytes;
  const std::size_t table_bytes = model.map.brick_table().size() * kTableEntryBytes;
  const std::size_t coarse_bytes = model.map.coarse().size() * kTableEntryBytes;
  return {Segment{nullptr, l.surface_offset - kTemplateHeaderBytes},
          Segment{model.surface_cells.data(), surface_bytes},
          Segment{nullptr, l.table_offset - l.surface_offset - surface_bytes},
          Segment{model.map.brick_table().data(), table_bytes},
          Segment{model.map.coarse().data(), coarse_bytes},
          Segment{nullptr, l.bricks_offset - l.table_offset - table_bytes - coarse_bytes},
          Segment{model.map.bricks().data(), model.map.bricks().size()}};
}

Status validate_name(const std::string& name) {
  if (name.empty() || name.size() >= kTemplatePartNameCapacity) {
    return make_error("template part name must be 1.." + std::to_string(kTemplatePartNameCapacity - 1) +
                      " bytes, got " + std::to_string(name.size()));
  }
  for (const char ch : name) {
    if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) {
      return make_error("template part name \"" + name + "\" contains a control character");
    }
  }
  return {};
}

// File descriptor closed on scope exit unless released.
class UniqueFd {
 public:
  explicit UniqueFd(int fd) : fd_(fd) {}
  UniqueFd(const UniqueFd&) = delete;
  UniqueFd& operator=(const UniqueFd&) = delete;
  ~UniqueFd() {
    if (fd_ >= 0) ::close(fd_);
  }
  [[nodiscard]] int get() const { return fd_; }
  int release() { return std::exchange(fd_, -1); }
  void reset(int fd) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = fd;
  }
  // close() reports errors (a failed close after writing may mean lost data).
  [[nodiscard]] int close() {
    const int rc = ::close(fd_);
    fd_ = -1;
    return rc;
  }

 private:
  int fd_;
};

// Removes the temp file on scope exit unless the rename happened.
class TempFileGuard {
 public:
  explicit TempFileGuard(std::string path) : path_(std::move(path)) {}
  TempFileGuard(const TempFileGuard&) = delete;
  TempFileGuard& operator=(const TempFileGuard&) = delete;
  ~TempFileGuard() {
    if (!path_.empty()) ::unlink(path_.c_str());
  }
  void release() { path_.clear(); }

 private:
  std::string path_;
};

Status write_all(int fd, const void* data, std::size_t bytes, const std::string& path) {
  const auto* p = static_cast<const std::uint8_t*>(data);
  while (bytes > 0) {
    const ssize_t n = ::write(fd, p, bytes);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return make_error(path + ": write failed: " + errno_text(n < 0 ? errno : EIO));
    p += n;
    bytes -= static_cast<std::size_t>(n);
  }
  return {};
}

Status write_segment(int fd, const Segment& s, const std::string& path) {
  if (s.data != nullptr) return write_all(fd, s.data, s.bytes, path);
  for (std::size_t done = 0; done < s.bytes;) {
    const std::size_t chunk = std::min(s.bytes - done, kZeros.size());
    if (Status w = write_all(fd, kZeros.data(), chunk, path); !w) return w;
    done += chunk;
  }
  return {};
}

std::string parent_of(const std::string& path) {
  const std::filesystem::path parent = std::filesystem::path(path).parent_path();
  return parent.empty() ? "." : parent.string();
}

// Everything a header must satisfy on its own and against the file length. `path` prefixes every message.
Expected<TemplateInfo> check_header(const std::string& path, const TemplateHeader& h, std::uint64_t file_length) {
  const auto fail = [&path](const std::string& why) { return make_error(path + ": " + why); };
  if (std::memcmp(h.magic, kMagic.data(), kMagic.size()) != 0) {
    return fail("not a cellsight template file (wrong magic number)");
  }
  if (h.byte_order != kByteOrderMark) return fail("byte-order mark is wrong (corrupt, or written by another machine)");
  if (h.format_version == kVersionOneFullGrid) {
    return fail("template format version 1 (a full-grid map of ~157 MB), this build reads version " +
                std::to_string(kTemplateFormatVersion) +
                " (sparse bricks, a few MB); run `cellsight parts rebuild` to regenerate the templates from the "
                "stored scans");
  }
  if (h.format_version != kTemplateFormatVersion) {
    return fail("template format version " + std::to_string(h.format_version) + ", this build reads version " +
                std::to_string(kTemplateFormatVersion) + "; re-teach the part with this version");
  }
  if (h.header_bytes != kTemplateHeaderBytes) {
    return fail("header size " + std::to_string(h.header_bytes) + " bytes, version " +
                std::to_string(kTemplateFormatVersion) + " has " + std::to_string(kTemplateHeaderBytes));
  }
  if (header_crc(h) != h.header_crc32) return fail("header checksum mismatch: the header is corrupt");

  // From here on the fields are as written, so a failure means a writer bug or a different build.
  if (h.brick_edge != algo::BrickGrid::kBrickEdge || h.section_alignment != kTemplateSectionAlignment) {
    return fail("brick edge " + std::to_string(h.brick_edge) + " or alignment " + std::to_string(h.section_alignment) +
                " B differs from this build's");
  }
  if (h.distance_unit_m != algo::kDistanceUnitM) {
    return fail("map quantization (distance unit " + number(h.distance_unit_m) +
                " m) differs from this build's; re-teach the part");
  }
  if (!(h.band_m > 0.0 && h.band_m <= algo::kMaxFineDistanceM))
    return fail("band " + number(h.band_m) + " m is invalid");
  TemplateInfo info;
  info.format_version = h.format_version;
  info.grid.nx = h.nx;
  info.grid.ny = h.ny;
  info.grid.nz = h.nz;
  info.grid.resolution_m = h.resolution_m;
  info.grid.origin_m = Eigen::Vector3d(h.origin_m[0], h.origin_m[1], h.origin_m[2]);
  if (Status g = validate_grid(info.grid); !g) return fail(g.error().message);
  info.band_m = h.band_m;
  info.centroid_m = Eigen::Vector2d(h.centroid_m[0], h.centroid_m[1]);
  if (!info.centroid_m.allFinite()) return fail("centroid is not finite");
  const std::size_t grid_cells = info.grid.cells();
  if (h.occupied_cells == 0 || h.occupied_cells > grid_cells || h.surface_cell_count == 0 ||
      h.surface_cell_count > h.occupied_cells) {
    return fail("inconsistent counts: " + std::to_string(h.occupied_cells) + " occupied cells, " +
                std::to_string(h.surface_cell_count) + " surface cells, grid of " + std::to_string(grid_cells) +
                " cells");
  }
  const std::size_t bricks = algo::BrickGrid(dims_of(info.grid)).brick_count();
  if (h.brick_count != bricks || h.stored_bricks == 0 || h.stored_bricks > std::min(bricks, algo::kMaxStoredBricks)) {
    return fail("brick counts (" + std::to_string(h.brick_count) + " in the grid, " + std::to_string(h.stored_bricks) +
                " stored) do not match the grid's " + std::to_string(bricks));
  }
  const Layout l = layout_for(h.surface_cell_count, bricks, h.stored_bricks);
  if (h.surface_offset != l.surface_offset || h.table_offset != l.table_offset || h.bricks_offset != l.bricks_offset ||
      h.file_bytes != l.file_bytes) {
    return fail("section offsets or file size in the header are inconsistent with its counts");
  }
  if (std::memchr(h.part_name, '\0', sizeof h.part_name) == nullptr || h.part_name[0] == '\0') {
    return fail("part name is empty or not terminated");
  }
  if (file_length < h.file_bytes) {
    return fail("truncated: the file has " + std::to_string(file_length) + " bytes, its header says " +
                std::to_string(h.file_bytes));
  }
  if (file_length > h.file_bytes) {
    return fail("has " + std::to_string(file_length - h.file_bytes) + " bytes more than its header says (" +
                std::to_string(h.file_bytes) + "): appended to or overwritten");
  }
  info.occupied_cells = h.occupied_cells;
  info.surface_cell_count = h.surface_cell_count;
  info.brick_count = h.brick_count;
  info.stored_bricks = h.stored_bricks;
  info.file_bytes = h.file_bytes;
  info.body_crc32 = h.body_crc32;
  info.part_name = h.part_name;
  info.plc_id = h.plc_id;
  info.created_unix_s = h.created_unix_s;
  return info;
}

bool same_grid(const algo::GridSpec& a, const algo::GridSpec& b) {
  return a.nx == b.nx && a.ny == b.ny && a.nz == b.nz && std::abs(a.resolution_m - b.resolution_m) <= kGridToleranceM &&
         (a.origin_m - b.origin_m).cwiseAbs().maxCoeff() <= kGridToleranceM;
}

// Opens for reading and reads the file length; a message names the file.
Expected<std::uint64_t> open_for_reading(const std::string& path, UniqueFd& fd) {
  const int raw = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (raw < 0) return make_error(path + ": cannot open the template file: " + errno_text(errno));
  fd.reset(raw);
  struct stat st {};
  if (::fstat(raw, &st) != 0) return make_error(path + ": cannot stat: " + errno_text(errno));
  if (!S_ISREG(st.st_mode)) return make_error(path + ": not a regular file");
  const auto length = static_cast<std::uint64_t>(st.st_size);
  if (length < kTemplateHeaderBytes) {
    return make_error(path + ": truncated: the file has " + std::to_string(length) + " bytes, the header alone " +
                      std::to_string(kTemplateHeaderBytes));
  }
  return length;
}

double ms_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() * kMsPerS;
}

}  // namespace

std::string describe_grid(const algo::GridSpec& grid) {
  return std::to_string(grid.nx) + " x " + std::to_string(grid.ny) + " x " + std::to_string(grid.nz) + " cells of " +
         number(grid.resolution_m * kMmPerM) + " mm, origin (" + number(grid.origin_m.x()) + ", " +
         number(grid.origin_m.y()) + ", " + number(grid.origin_m.z()) + ") m";
}

// --- write -----------------------------------------------------------------------------------------------------------

Status write_template(const std::string& path, const TemplateModel& model, const TemplateIdentity& identity) {
  const auto fail = [&path](const std::string& why) { return make_error(path + ": " + why); };
  if (Status name = validate_name(identity.part_name); !name) return fail(name.error().message);
  if (Status g = validate_grid(model.grid); !g) return fail(g.error().message);
  const algo::GridDims dims = dims_of(model.grid);
  const algo::GridDims& map_dims = model.map.dims();
  const std::size_t bricks = algo::BrickGrid(dims).brick_count();
  const std::size_t stored = model.map.stored_bricks();
  if (map_dims.nx != dims.nx || map_dims.ny != dims.ny || map_dims.nz != dims.nz ||
      map_dims.resolution_m != dims.resolution_m || model.map.origin_m() != model.grid.origin_m ||
      model.map.brick_table().size() != bricks || model.map.coarse().size() != bricks || stored == 0 ||
      model.map.bricks().size() != stored * algo::BrickGrid::kBrickCells) {
    return fail("template model is inconsistent: its map was not built for its grid");
  }
  if (model.surface_cells.empty() || model.occupied_cells < model.surface_cells.size() ||
      !model.centroid_m.allFinite()) {
    return fail("template model is inconsistent: no surface cells, or not a built template");
  }

  const Layout l = layout_for(model.surface_cells.size(), bricks, stored);
  TemplateHeader h{};
  std::memcpy(h.magic, kMagic.data(), kMagic.size());
  h.format_version = kTemplateFormatVersion;
  h.header_bytes = kTemplateHeaderBytes;
  h.byte_order = kByteOrderMark;
  h.section_alignment = kTemplateSectionAlignment;
  h.nx = dims.nx;
  h.ny = dims.ny;
  h.nz = dims.nz;
  h.plc_id = identity.plc_id;
  h.resolution_m = model.grid.resolution_m;
  for (int a = 0; a < 3; ++a) h.origin_m[a] = model.grid.origin_m[a];
  h.distance_unit_m = algo::kDistanceUnitM;
  h.band_m = model.map.band_m();
  h.centroid_m[0] = model.centroid_m.x();
  h.centroid_m[1] = model.centroid_m.y();
  h.occupied_cells = model.occupied_cells;
  h.surface_cell_count = model.surface_cells.size();
  h.surface_offset = l.surface_offset;
  h.brick_count = bricks;
  h.table_offset = l.table_offset;
  h.stored_bricks = stored;
  h.bricks_offset = l.bricks_offset;
  h.file_bytes = l.file_bytes;
  h.created_unix_s =
      identity.created_unix_s != 0 ? identity.created_unix_s : static_cast<std::int64_t>(std::time(nullptr));
  h.brick_edge = algo::BrickGrid::kBrickEdge;
  std::memcpy(h.part_name, identity.part_name.data(), identity.part_name.size());

  // The body CRC over exactly the bytes about to be written, straight from the model's buffers.
  const std::array<Segment, 7> body = body_segments(model, l);
  std::uint32_t crc = base::kCrc32Empty;
  for (const Segment& s : body) {
    if (s.data != nullptr) {
      crc = base::crc32_update(crc, s.data, s.bytes);
    } else {
      for (std::size_t done = 0; done < s.bytes; done += kZeros.size()) {
        crc = base::crc32_update(crc, kZeros.data(), std::min(kZeros.size(), s.bytes - done));
      }
    }
  }
  h.body_crc32 = crc;
  h.header_crc32 = header_crc(h);

  // Streaming atomic save: temp beside the target, fsync, rename, fsync of the folder (as base/atomic_file).
  std::string temp = base::atomic_temp_template(path);
  UniqueFd fd(::mkstemp(temp.data()));
  if (fd.get() < 0) return fail("cannot create a temporary file beside it: " + errno_text(errno));
  TempFileGuard guard(temp);
  if (Status w = write_all(fd.get(), &h, sizeof h, path); !w) return w;
  for (const Segment& s : body) {
    if (Status w = write_segment(fd.get(), s, path); !w) return w;
  }
  if (::fchmod(fd.get(), 0644) != 0 || ::fsync(fd.get()) != 0)
    return fail("cannot finish the file: " + errno_text(errno));
  if (fd.close() != 0) return fail("cannot finish the file: " + errno_text(errno));
  if (::rename(temp.c_str(), path.c_str()) != 0) return fail("cannot replace: " + errno_text(errno));
  guard.release();
  const std::string folder = parent_of(path);
  UniqueFd dir(::open(folder.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (dir.get() < 0 || ::fsync(dir.get()) != 0) {
    return fail("written, but the folder " + folder + " could not be synced: " + errno_text(errno));
  }
  return {};
}

// --- read ------------------------------------------------------------------------------------------------------------

Expected<TemplateInfo> read_template_info(const std::string& path) {
  UniqueFd fd(-1);
  Expected<std::uint64_t> length = open_for_reading(path, fd);
  if (!length) return length.error();
  TemplateHeader h{};
  const ssize_t n = ::pread(fd.get(), &h, sizeof h, 0);
  if (n != static_cast<ssize_t>(sizeof h)) {
    return make_error(path + ": cannot read the header: " + (n < 0 ? errno_text(errno) : std::string("short read")));
  }
  return check_header(path, h, *length);
}

TemplateFile::TemplateFile(TemplateFile&& other) noexcept
    : path_(std::move(other.path_)),
      memory_(std::exchange(other.memory_, nullptr)),
      memory_bytes_(std::exchange(other.memory_bytes_, 0)),
      info_(std::move(other.info_)),
      centroid_z_m_(other.centroid_z_m_),
      view_(std::exchange(other.view_, {})),
      surface_cells_(std::exchange(other.surface_cells_, {})),
      timing_(other.timing_) {}

TemplateFile& TemplateFile::operator=(TemplateFile&& other) noexcept {
  if (this != &other) {
    release();
    path_ = std::move(other.path_);
    memory_ = std::exchange(other.memory_, nullptr);
    memory_bytes_ = std::exchange(other.memory_bytes_, 0);
    info_ = std::move(other.info_);
    centroid_z_m_ = other.centroid_z_m_;
    view_ = std::exchange(other.view_, {});
    surface_cells_ = std::exchange(other.surface_cells_, {});
    timing_ = other.timing_;
  }
  return *this;
}

TemplateFile::~TemplateFile() {
  release();
}

void TemplateFile::release() {
  view_ = {};
  surface_cells_ = {};
  if (memory_ != nullptr) ::munmap(const_cast<std::uint8_t*>(memory_), memory_bytes_);
  memory_ = nullptr;
  memory_bytes_ = 0;
}

Expected<TemplateFile> TemplateFile::open(const std::string& path, const algo::GridSpec& expected_grid) {
  const auto start = std::chrono::steady_clock::now();
  TemplateFile file;  // owns whatever is acquired below, so every early return releases it
  file.path_ = path;
  UniqueFd fd(-1);
  Expected<std::uint64_t> length = open_for_reading(path, fd);
  if (!length) return length.error();
  // The header first: a version 1 file (157 MB) or a header declaring absurd sizes is refused before anything of
  // the body is allocated or read.
  TemplateHeader h{};
  const ssize_t got = ::pread(fd.get(), &h, sizeof h, 0);
  if (got != static_cast<ssize_t>(sizeof h)) {
    return make_error(path + ": cannot read the header: " + (got < 0 ? errno_text(errno) : std::string("short read")));
  }
  Expected<TemplateInfo> info = check_header(path, h, *length);
  if (!info) return info.error();
  if (!same_grid(info->grid, expected_grid)) {
    return make_error(path + ": built for another grid: the file has " + describe_grid(info->grid) +
                      ", the configuration " + describe_grid(expected_grid) + "; re-teach the part for this grid");
  }
  void* memory = ::mmap(nullptr, *length, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS | MAP_POPULATE, -1, 0);
  if (memory == MAP_FAILED) {
    return make_error(path + ": cannot allocate " + std::to_string(*length) + " bytes: " + errno_text(errno));
  }
  file.memory_ = static_cast<const std::uint8_t*>(memory);
  file.memory_bytes_ = *length;
  auto* bytes = static_cast<std::uint8_t*>(memory);
  for (std::size_t done = 0; done < *length;) {
    const ssize_t n = ::pread(fd.get(), bytes + done, *length - done, static_cast<off_t>(done));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return make_error(path + ": read failed: " + (n < 0 ? errno_text(errno) : std::string("file shrank")));
    done += static_cast<std::size_t>(n);
  }
  if (std::memcmp(bytes, &h, sizeof h) != 0) return make_error(path + ": the file changed while it was read");
  file.info_ = std::move(*info);
  file.timing_.read_ms = ms_since(start);

  const auto verify_start = std::chrono::steady_clock::now();
  const std::uint32_t crc =
      base::crc32_update(base::kCrc32Empty, bytes + kTemplateHeaderBytes, *length - kTemplateHeaderBytes);
  if (crc != h.body_crc32) {
    return make_error(path + ": body checksum mismatch: the maps or surface cells are corrupt; re-teach the part");
  }
  // The checksum proves the bytes are as written; these prove a writer (or a crafted file with fixed checksums)
  // cannot make sample() or the cascade read outside the file's memory.
  const auto* cells = reinterpret_cast<const algo::SurfaceCell*>(bytes + h.surface_offset);
  for (std::size_t i = 0; i < h.surface_cell_count; ++i) {
    if (cells[i].x >= h.nx || cells[i].y >= h.ny || cells[i].z >= h.nz) {
      return make_error(path + ": surface cell " + std::to_string(i) + " lies outside the grid");
    }
  }
  const auto* table = reinterpret_cast<const std::uint16_t*>(bytes + h.table_offset);
  for (std::size_t b = 0; b < h.brick_count; ++b) {
    if (table[b] != algo::kAbsentBrick && table[b] >= h.stored_bricks) {
      return make_error(path + ": brick table entry " + std::to_string(b) + " names brick " + std::to_string(table[b]) +
                        " of " + std::to_string(h.stored_bricks) + " stored");
    }
  }
  if (::mprotect(memory, *length, PROT_READ) != 0) {
    return make_error(path + ": cannot make the template read-only: " + errno_text(errno));
  }
  double sum_z = 0.0;
  for (std::size_t i = 0; i < h.surface_cell_count; ++i) sum_z += cells[i].z + 0.5;
  file.centroid_z_m_ = h.origin_m[2] + h.resolution_m * sum_z / static_cast<double>(h.surface_cell_count);
  file.timing_.verify_ms = ms_since(verify_start);
  file.surface_cells_ = {cells, h.surface_cell_count};
  const algo::SparseMapData data{table, table + h.brick_count, bytes + h.bricks_offset, h.stored_bricks};
  file.view_ = algo::DistanceMapView(dims_of(file.info_.grid), file.info_.grid.origin_m, data);
  return file;
}

}  // namespace cellsight::formats
