// Occupancy grid of the thesis (6.3: 296 x 500 x 182 cells at 2.2 mm by default) and its depth image (6.4.1.4).
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <vector>

#include "algo/scan.hpp"

namespace cellsight::algo {

struct GridSpec {
  Eigen::Vector3d origin_m = Eigen::Vector3d::Zero();  // carrier-frame corner of cell (0, 0, 0)
  int nx = 296, ny = 500, nz = 182;
  double resolution_m = 0.0022;

  [[nodiscard]] std::size_t cells() const { return static_cast<std::size_t>(nx) * ny * nz; }
  [[nodiscard]] std::size_t index(int ix, int iy, int iz) const {
    return (static_cast<std::size_t>(iz) * ny + iy) * nx + ix;
  }
  // Cell containing p; false when p lies outside the grid.
  [[nodiscard]] bool cell_of(const Eigen::Vector3f& p, int& ix, int& iy, int& iz) const;
  [[nodiscard]] Eigen::Vector3d centre(int ix, int iy, int iz) const {
    return origin_m + resolution_m * Eigen::Vector3d(ix + 0.5, iy + 0.5, iz + 0.5);
  }
};

class OccupancyGrid {
 public:
  OccupancyGrid() = default;
  // Start-up only: allocates the cells, a touched-cell list for clearing in O(points), and the depth image.
  OccupancyGrid(const GridSpec& spec, std::size_t max_points);

  // Resets only the cells set since the last clear.
  void clear();
  // Marks the cells of the points; returns how many points fell outside the grid.
  std::size_t accumulate(std::span<const ScanPoint> points);

  [[nodiscard]] bool occupied(int ix, int iy, int iz) const { return cells_[spec_.index(ix, iy, iz)] != 0; }
  [[nodiscard]] const std::uint8_t* data() const { return cells_.data(); }
  [[nodiscard]] const GridSpec& spec() const { return spec_; }
  // Cells set since the last clear (also when more were set than the touched list holds).
  [[nodiscard]] std::size_t occupied_count() const { return occupied_; }

  // Depth image (thesis 6.4.1.4): ny rows x nx columns, row 0 at the top (largest y); each pixel is the front-most
  // occupied cell of its (x, y) column mapped from the grid depth (0 .. nz*resolution, 0.4 m by default) onto
  // 1..255; 0 means no occupied cell. Reuses `out` when it already has the right shape.
  void depth_image(cv::Mat& out) const;

 private:
  GridSpec spec_{};
  std::vector<std::uint8_t> cells_;
  std::vector<std::uint32_t> touched_;
  std::size_t touched_capacity_ = 0;
  std::size_t occupied_ = 0;
};

}  // namespace cellsight::algo
