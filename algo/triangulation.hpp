// Laser triangulation (thesis eq. 3.1-3.3): stripe pixel -> camera ray -> laser plane -> cell frame -> carrier frame.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "algo/sensor_model.hpp"

namespace cellsight::algo {

// Precomputes, for every pixel, where its (undistorted) ray meets the laser plane, so a stripe point costs one
// linear interpolation instead of an iterative undistortion. Exact at pixel columns; between them the error is the
// curvature of the ray-plane map over half a pixel (< 0.002 mm for the cell's geometry, measured in the tests).
class Triangulator {
 public:
  Triangulator() = default;
  // Start-up only: allocates width x height x 3 floats.
  explicit Triangulator(const SensorCalibration& calibration);

  // Cell-frame point seen at sub-pixel column u of integer row v; NaN components when the ray misses the plane
  // (or u is outside the image).
  [[nodiscard]] Eigen::Vector3f cell_point(float u, int v) const {
    const float nan = std::numeric_limits<float>::quiet_NaN();
    if (!(u >= 0.0F) || u > static_cast<float>(width_ - 1) || v < 0 || v >= height_) return {nan, nan, nan};
    const int u0 = std::min(static_cast<int>(u), width_ - 2);
    const float w = u - static_cast<float>(u0);
    const float* a = &table_[(static_cast<std::size_t>(v) * width_ + u0) * 3];
    return {a[0] + w * (a[3] - a[0]), a[1] + w * (a[4] - a[1]), a[2] + w * (a[5] - a[2])};
  }

  // Same at a sub-pixel row too (bilinear between rows): for stripe pieces that run along the rows.
  [[nodiscard]] Eigen::Vector3f cell_point(float u, float v) const {
    if (!(v >= 0.0F) || v > static_cast<float>(height_ - 1)) return cell_point(u, -1);
    const int v0 = std::min(static_cast<int>(v), height_ - 2);
    const float w = v - static_cast<float>(v0);
    return (1.0F - w) * cell_point(u, v0) + w * cell_point(u, v0 + 1);
  }

  // Carrier-frame point: p_carrier = p_cell - (travel - start_offset) e_x (DESIGN.md, carrier rides the conveyor).
  [[nodiscard]] Eigen::Vector3f carrier_point(float u, int v, double travel_m, double start_offset_m) const {
    Eigen::Vector3f p = cell_point(u, v);
    p.x() -= static_cast<float>(travel_m - start_offset_m);
    return p;
  }

  [[nodiscard]] double travel_m(std::int64_t encoder_counts) const {
    return static_cast<double>(encoder_counts) * mm_per_count_ * 1e-3;
  }
  [[nodiscard]] int width() const { return width_; }
  [[nodiscard]] int height() const { return height_; }

 private:
  int width_ = 0, height_ = 0;
  double mm_per_count_ = 0.0;
  std::vector<float> table_;  // per pixel x, y, z (cell frame, metres)
};

// The exact ray/plane intersection for one pixel (used to build the table, and by tests as the reference).
[[nodiscard]] Eigen::Vector3d intersect_laser(const SensorCalibration& calibration, const Eigen::Vector2d& pixel);

}  // namespace cellsight::algo
