// Camera model implementation: OpenCV's distortion polynomial and its numerical inverse.
#include "algo/camera_model.hpp"

#include <cmath>

namespace cellsight::algo {

CameraPose look_at(const Eigen::Vector3d& position, const Eigen::Vector3d& target, double roll_rad) {
  const Eigen::Vector3d z_axis = (target - position).normalized();
  const Eigen::Vector3d world_down(0.0, -1.0, 0.0);
  const Eigen::Vector3d y_axis = (world_down - world_down.dot(z_axis) * z_axis).normalized();
  const Eigen::Vector3d x_axis = y_axis.cross(z_axis);
  Eigen::Matrix3d r;  // rows: camera axes in world coordinates
  r.row(0) = x_axis.transpose();
  r.row(1) = y_axis.transpose();
  r.row(2) = z_axis.transpose();
  const Eigen::Matrix3d roll = Eigen::AngleAxisd(roll_rad, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  CameraPose pose;
  pose.r_cam_world = roll * r;
  pose.t_cam_world = -pose.r_cam_world * position;
  return pose;
}

Eigen::Vector2d distort(const Intrinsics& k, const Eigen::Vector2d& n) {
  const double x = n.x(), y = n.y();
  const double r2 = x * x + y * y;
  const double radial = 1.0 + r2 * (k.k1 + r2 * (k.k2 + r2 * k.k3));
  return {x * radial + 2.0 * k.p1 * x * y + k.p2 * (r2 + 2.0 * x * x),
          y * radial + k.p1 * (r2 + 2.0 * y * y) + 2.0 * k.p2 * x * y};
}

Eigen::Vector2d undistort(const Intrinsics& k, const Eigen::Vector2d& pixel) {
  const Eigen::Vector2d target((pixel.x() - k.cx_px) / k.fx_px, (pixel.y() - k.cy_px) / k.fy_px);
  Eigen::Vector2d n = target;
  constexpr int kFixedPointIterations = 20;
  for (int i = 0; i < kFixedPointIterations; ++i) {
    const Eigen::Vector2d d = distort(k, n);
    n += target - d;  // converges for moderate distortion, like cv::undistortPoints
  }
  constexpr int kNewtonIterations = 3;
  constexpr double kStep = 1e-7;
  for (int i = 0; i < kNewtonIterations; ++i) {
    const Eigen::Vector2d residual = distort(k, n) - target;
    Eigen::Matrix2d jacobian;
    jacobian.col(0) =
        (distort(k, n + Eigen::Vector2d(kStep, 0)) - distort(k, n - Eigen::Vector2d(kStep, 0))) / (2 * kStep);
    jacobian.col(1) =
        (distort(k, n + Eigen::Vector2d(0, kStep)) - distort(k, n - Eigen::Vector2d(0, kStep))) / (2 * kStep);
    n -= jacobian.inverse() * residual;
  }
  return n;
}

}  // namespace cellsight::algo
