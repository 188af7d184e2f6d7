// Pinhole camera with OpenCV's radial/tangential distortion (k1, k2, p1, p2, k3): projection and its inverse.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace cellsight::algo {

struct Intrinsics {
  double fx_px = 0, fy_px = 0, cx_px = 0, cy_px = 0;
  double k1 = 0, k2 = 0, p1 = 0, p2 = 0, k3 = 0;  // OpenCV's 5-coefficient model
  int width_px = 0, height_px = 0;
};

// Rigid transform world -> camera (OpenCV camera axes: x right, y down, z forward): p_cam = R * p_world + t.
struct CameraPose {
  Eigen::Matrix3d r_cam_world = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t_cam_world = Eigen::Vector3d::Zero();

  [[nodiscard]] Eigen::Vector3d to_camera(const Eigen::Vector3d& p_world) const {
    return r_cam_world * p_world + t_cam_world;
  }
  [[nodiscard]] Eigen::Vector3d centre_world() const { return -r_cam_world.transpose() * t_cam_world; }
};

// Builds the pose of a camera at `position` looking at `target` with world +y up in the image (rows grow downward),
// then rolled by roll_rad about its optical axis.
[[nodiscard]] CameraPose look_at(const Eigen::Vector3d& position, const Eigen::Vector3d& target, double roll_rad);

// Applies the distortion model to normalised coordinates (x/z, y/z).
[[nodiscard]] Eigen::Vector2d distort(const Intrinsics& k, const Eigen::Vector2d& normalised);

// Camera-frame point -> pixel (pixel centres at integer coordinates, as OpenCV). z must be > 0.
[[nodiscard]] inline Eigen::Vector2d project(const Intrinsics& k, const Eigen::Vector3d& p_cam) {
  const Eigen::Vector2d d = distort(k, Eigen::Vector2d(p_cam.x() / p_cam.z(), p_cam.y() / p_cam.z()));
  return {k.fx_px * d.x() + k.cx_px, k.fy_px * d.y() + k.cy_px};
}

// Pixel -> normalised undistorted coordinates by fixed-point iteration (as cv::undistortPoints), refined with
// Newton steps so the round trip is exact to ~1e-9 px inside the image.
[[nodiscard]] Eigen::Vector2d undistort(const Intrinsics& k, const Eigen::Vector2d& pixel);

}  // namespace cellsight::algo
