// Perfect Match template files (models/templates/NAME.dmap): the sparse distance map (thesis 2.7.3.1,
// algo/distance_map.hpp), centroid and occupied cells of one taught part; built at teach time, read whole into memory
// of its own at start-up (read-only from then on) and used in place at run time.
#pragma once

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "algo/distance_map.hpp"
#include "algo/grid.hpp"
#include "algo/result.hpp"
#include "algo/scan.hpp"

namespace cellsight::formats {

// File layout, version 2 (all numbers little-endian, the types exactly as in memory):
//   [0, 256)                 TemplateHeader: magic, version, sizes, grid, quantization, band, centroid, counts,
//                            offsets, part name and PLC id, creation time, body CRC; header CRC in its last 4 bytes
//   [256, 4096)              zeros
//   [4096, ...)              surface cells: surface_cell_count algo::SurfaceCell (3 x uint16: x, y, z cell indices)
//   zeros up to the next multiple of 4096
//   [table_offset, ...)      brick table: brick_count uint16 (stored brick number, or algo::kAbsentBrick)
//   [+ brick_count * 2, ...) coarse field: brick_count uint16 (algo::kDistanceUnitM)
//   zeros up to the next multiple of 4096
//   [bricks_offset, end)     stored_bricks x 512 uint8: the fine cells (algo::kDistanceUnitM, algo::kFineFar)
// The header CRC (zlib crc32) covers header bytes [0, 252); the body CRC every byte from 256 to the end of the file.
// Sections start on 4 KiB boundaries so that the mapped arrays are page-aligned and read in place.
// Version 1 (a full 296 x 500 x 182 grid of 6-byte cells, 157 MB) is refused with a pointer to `parts rebuild`.
inline constexpr std::uint32_t kTemplateFormatVersion = 2;
inline constexpr std::size_t kTemplateHeaderBytes = 256;
inline constexpr std::size_t kTemplateSectionAlignment = 4096;
inline constexpr std::size_t kTemplatePartNameCapacity = 64;  // bytes in the header, NUL included
inline constexpr std::size_t kTemplateBodyCrcOffset = 176;    // of the body CRC (uint32) in the header

struct TemplateBuildParams {
  // Bricks with a cell within this distance of the surface keep exact distances (algo/distance_map.hpp).
  double band_m = algo::kDefaultBandM;
  // The two-way check of the cascade rasterises these at grid resolution and looks for connected regions the scan
  // lacks: it needs every occupied cell (a 4096-point subset of a 0.3 m^2 plate is one point per ~8 mm, which
  // breaks a 40 mm hole into unconnected cells and hid a one-hole difference in test_model_db). The cap only
  // guards against absurd inputs; a full 2.2 mm part has ~60-100 k cells (0.4-0.6 MB in the file).
  std::size_t max_surface_points = 1U << 21;
  // Points of the (carrier-free) scan allowed outside the grid before the part counts as cut off. Strict by default:
  // a template that misses part of its surface would penalise every complete scan of the part.
  std::size_t max_outside_points = 0;
};

// A template in memory, as teach builds it from one scan. Teach time only: allocates (~135 MB of transient work
// buffers for the full grid; the map itself is 2-4 MB).
struct TemplateModel {
  algo::GridSpec grid{};
  algo::DistanceMap map;
  // x-y mean of the occupied cell centres: c of DESIGN.md "Pose"; its depth (the full pose's c) the same mean in z.
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();
  double centroid_z_m = 0.0;
  // Occupied cells, Morton (Z-order) sorted, then subsampled evenly along that order to at most max_surface_points:
  // a run of consecutive cells is a compact patch, so any strided subset is still spread over the whole part.
  std::vector<algo::SurfaceCell> surface_cells;
  std::size_t occupied_cells = 0;
  std::size_t outside_points = 0;  // tolerated by max_outside_points, not accumulated
};

// Accumulates `points` (carrier already removed) into an occupancy grid of `grid`, builds the distance map and the
// centroid and surface points. Refuses an empty scan, a grid the distance transform cannot take, and a part that
// does not fit the grid (the message says how many points lie beyond which side).
[[nodiscard]] Expected<TemplateModel> build_template(std::span<const algo::ScanPoint> points,
                                                     const algo::GridSpec& grid,
                                                     const TemplateBuildParams& params = {});

// Who the template is, for reports (the manifest stays the authority on names and ids).
struct TemplateIdentity {
  std::string part_name;            // 1..63 bytes, no control characters
  std::uint32_t plc_id = 0;         // PART_ID register (DESIGN.md Modbus map)
  std::int64_t created_unix_s = 0;  // 0: now
};

// Writes the file atomically (temp file beside `path`, fsync, rename, fsync of the folder), streaming the sections
// from `model` without a second copy in memory. On failure the previous file at `path` is untouched and the temp
// file removed.
[[nodiscard]] Status write_template(const std::string& path, const TemplateModel& model,
                                    const TemplateIdentity& identity);

// The header of a checked file.
struct TemplateInfo {
  std::uint32_t format_version = 0;
  algo::GridSpec grid{};
  double band_m = 0.0;
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();
  std::uint64_t occupied_cells = 0;
  std::uint64_t surface_cell_count = 0;
  std::uint64_t brick_count = 0;    // algo::BrickGrid(grid).brick_count()
  std::uint64_t stored_bricks = 0;  // fine bricks in the file
  std::uint64_t file_bytes = 0;
  std::uint32_t body_crc32 = 0;  // e.g. for a manifest checksum: identifies the content without rereading it
  std::string part_name;
  std::uint32_t plc_id = 0;
  std::int64_t created_unix_s = 0;
};

// Header only (`parts list/show`): magic, version, header checksum, consistency of the sizes with each other and
// with the file length. Does not read the body, so it does not prove the maps intact: use TemplateFile to use them.
[[nodiscard]] Expected<TemplateInfo> read_template_info(const std::string& path);

// "296 x 500 x 182 cells of 2.2 mm, origin (0, 0, 0) m"
[[nodiscard]] std::string describe_grid(const algo::GridSpec& grid);

struct TemplateLoadTiming {
  double read_ms = 0.0;    // open, read into memory, header checks
  double verify_ms = 0.0;  // body checksum and range checks
};

// An open, fully checked template: owns the memory its file was read into and serves the maps in place.
// The memory is anonymous, populated when read and then made read-only (a stray write faults instead of changing a
// template): unlike a file mapping, whose clean pages the kernel may drop and fault in again from disk, it stays
// resident (with runtime.lock_memory it is also locked), so the production loop never waits for a template page.
// Move-only; the view's pointers stay valid across moves (the memory does not move).
class TemplateFile {
 public:
  // Reads `path` and checks magic, version, header checksum, sizes against the file length, that the grid is
  // `expected_grid`, then the body checksum and the ranges of the brick table and surface cells. Any failure is an
  // error naming the file and the reason, and nothing of the file is kept. Start-up only (see the timing).
  [[nodiscard]] static Expected<TemplateFile> open(const std::string& path, const algo::GridSpec& expected_grid);

  TemplateFile(TemplateFile&& other) noexcept;
  TemplateFile& operator=(TemplateFile&& other) noexcept;
  TemplateFile(const TemplateFile&) = delete;
  TemplateFile& operator=(const TemplateFile&) = delete;
  ~TemplateFile();

  // The sparse map and the occupied cells, in place in the file's memory.
  [[nodiscard]] const algo::DistanceMapView& view() const { return view_; }
  [[nodiscard]] const Eigen::Vector2d& centroid_m() const { return info_.centroid_m; }
  // Depth of c (the full pose's centre): the mean depth of the surface cells' centres, which are every occupied cell
  // unless TemplateBuildParams::max_surface_points capped them (then an even subset): TemplateModel::centroid_z_m.
  [[nodiscard]] double centroid_z_m() const { return centroid_z_m_; }
  [[nodiscard]] std::span<const algo::SurfaceCell> surface_cells() const { return surface_cells_; }
  [[nodiscard]] const std::string& part_name() const { return info_.part_name; }
  [[nodiscard]] std::uint32_t plc_id() const { return info_.plc_id; }
  [[nodiscard]] const TemplateInfo& info() const { return info_; }
  [[nodiscard]] const std::string& path() const { return path_; }
  [[nodiscard]] const TemplateLoadTiming& load_timing() const { return timing_; }

 private:
  TemplateFile() = default;
  void release();

  std::string path_;
  const std::uint8_t* memory_ = nullptr;  // mmap'ed anonymous, the file's bytes, read-only after open()
  std::size_t memory_bytes_ = 0;
  TemplateInfo info_{};
  double centroid_z_m_ = 0.0;
  algo::DistanceMapView view_{};
  std::span<const algo::SurfaceCell> surface_cells_;
  TemplateLoadTiming timing_{};
};

}  // namespace cellsight::formats
