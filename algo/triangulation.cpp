// Triangulation table and exact ray/plane intersection.
#include "algo/triangulation.hpp"

namespace cellsight::algo {

Eigen::Vector3d intersect_laser(const SensorCalibration& c, const Eigen::Vector2d& pixel) {
  // thesis eq. 3.1-3.3: ray r = T + k V from the camera centre T; solve A x + B y + C z = d for k.
  const Eigen::Vector2d n = undistort(c.intrinsics, pixel);
  const Eigen::Vector3d dir = c.camera_pose.r_cam_world.transpose() * Eigen::Vector3d(n.x(), n.y(), 1.0);
  const Eigen::Vector3d centre = c.camera_pose.centre_world();
  const double denom = c.laser_normal.dot(dir);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  if (std::abs(denom) < 1e-12) return {nan, nan, nan};
  const double k = (c.laser_offset_m - c.laser_normal.dot(centre)) / denom;
  if (k <= 0.0) return {nan, nan, nan};  // the plane is behind the camera along this ray
  return centre + k * dir;
}

Triangulator::Triangulator(const SensorCalibration& calibration)
    : width_(calibration.intrinsics.width_px),
      height_(calibration.intrinsics.height_px),
      mm_per_count_(calibration.mm_per_count) {
  SensorCalibration c = calibration;
  c.laser_offset_m /= c.laser_normal.norm();
  c.laser_normal.normalize();
  table_.resize(static_cast<std::size_t>(width_) * height_ * 3);
  for (int v = 0; v < height_; ++v) {
    for (int u = 0; u < width_; ++u) {
      const Eigen::Vector3d p = intersect_laser(c, Eigen::Vector2d(u, v));
      float* out = &table_[(static_cast<std::size_t>(v) * width_ + u) * 3];
      out[0] = static_cast<float>(p.x());
      out[1] = static_cast<float>(p.y());
      out[2] = static_cast<float>(p.z());
    }
  }
}

}  // namespace cellsight::algo
