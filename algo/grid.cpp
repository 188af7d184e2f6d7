// Occupancy grid accumulation and depth image.
#include "algo/grid.hpp"

#include <algorithm>
#include <cmath>

namespace cellsight::algo {

bool GridSpec::cell_of(const Eigen::Vector3f& p, int& ix, int& iy, int& iz) const {
  // One division and three products instead of three divisions: this runs for every point of a scan, several
  // times per decision (issue 11's decision budget).
  const double inv = 1.0 / resolution_m;
  const double fx = (p.x() - origin_m.x()) * inv;
  const double fy = (p.y() - origin_m.y()) * inv;
  const double fz = (p.z() - origin_m.z()) * inv;
  if (!(fx >= 0.0 && fy >= 0.0 && fz >= 0.0 && fx < nx && fy < ny && fz < nz)) return false;  // also rejects NaN
  ix = static_cast<int>(fx);
  iy = static_cast<int>(fy);
  iz = static_cast<int>(fz);
  return true;
}

OccupancyGrid::OccupancyGrid(const GridSpec& spec, std::size_t max_points)
    : spec_(spec), cells_(spec.cells(), 0), touched_capacity_(max_points) {
  touched_.reserve(max_points);
}

void OccupancyGrid::clear() {
  if (touched_.size() >= touched_capacity_) {  // the list overflowed: wipe everything (rare, bounded)
    std::fill(cells_.begin(), cells_.end(), 0);
  } else {
    for (std::uint32_t i : touched_) cells_[i] = 0;
  }
  touched_.clear();
  occupied_ = 0;
}

std::size_t OccupancyGrid::accumulate(std::span<const ScanPoint> points) {
  std::size_t outside = 0;
  for (const ScanPoint& p : points) {
    int ix = 0, iy = 0, iz = 0;
    if (!spec_.cell_of({p.x, p.y, p.z}, ix, iy, iz)) {
      ++outside;
      continue;
    }
    const std::size_t i = spec_.index(ix, iy, iz);
    if (cells_[i] != 0) continue;
    cells_[i] = 1;
    ++occupied_;
    if (touched_.size() < touched_capacity_) touched_.push_back(static_cast<std::uint32_t>(i));
  }
  return outside;
}

void OccupancyGrid::depth_image(cv::Mat& out) const {
  out.create(spec_.ny, spec_.nx, CV_8UC1);
  out.setTo(0);
  constexpr double kFullScale = 255.0;
  // Only touched cells can be occupied: O(points) instead of a scan of all 27 M cells.
  const std::size_t plane = static_cast<std::size_t>(spec_.nx) * spec_.ny;
  auto mark = [&](std::size_t i) {
    const int iz = static_cast<int>(i / plane);
    const std::size_t rest = i % plane;
    const int iy = static_cast<int>(rest / spec_.nx), ix = static_cast<int>(rest % spec_.nx);
    const auto value = static_cast<std::uint8_t>(std::clamp(std::lround((iz + 1) * kFullScale / spec_.nz), 1L, 255L));
    std::uint8_t& px = out.at<std::uint8_t>(spec_.ny - 1 - iy, ix);
    px = std::max(px, value);
  };
  if (touched_.size() < touched_capacity_) {
    for (std::uint32_t i : touched_) mark(i);
  } else {
    for (std::size_t i = 0; i < cells_.size(); ++i) {
      if (cells_[i] != 0) mark(i);
    }
  }
}

}  // namespace cellsight::algo
