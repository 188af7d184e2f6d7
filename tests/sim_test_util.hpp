// Helpers shared by the simulated-cell tests: exact (noise-free) rigs and simple hand-built scenes.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <vector>

#include "algo/decision.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"
#include "drivers/sim/renderer.hpp"
#include "drivers/sim/rig.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::test {

// The default rig with every random or smoothing disturbance switched off, so the stripe is pure geometry.
inline sim::RigParams exact_rig_params() {
  sim::RigParams p = sim::default_rig_params();
  auto& s = p.sensor;
  s.noise = false;
  s.ambient_dn = 0.0;
  s.ambient_gradient_dn = 0.0;
  s.ambient_light_dn = 0.0;
  s.halo_fraction = 0.0;
  s.speckle_contrast = 0.0;
  s.hot_pixel_fraction = 0.0;
  return p;
}

// The simulator's true sensor, as a perfect calibration would report it (for tests of later stages only; the
// calibration tests recover it from board images instead).
inline algo::SensorCalibration true_calibration(const sim::Rig& rig) {
  algo::SensorCalibration c;
  c.intrinsics = rig.params.camera.intrinsics;
  c.camera_pose = rig.camera_pose;
  c.laser_normal = rig.laser_normal_world;
  c.laser_offset_m = rig.laser_offset_m;
  c.mm_per_count = 1.0 / rig.params.conveyor.counts_per_mm;
  return c;
}

// A rectangular plate facet centred at `centre` with the given in-plane axes (carrier frame).
inline sim::Facet plate(const Eigen::Vector3d& centre, const Eigen::Vector3d& axis_u, const Eigen::Vector3d& axis_v,
                        double half_u, double half_v, bool is_part = true) {
  sim::Facet f;
  f.origin = centre;
  f.axis_u = axis_u.normalized();
  f.axis_v = axis_v.normalized();
  f.outline = {{-half_u, -half_v}, {half_u, -half_v}, {half_u, half_v}, {-half_u, half_v}};
  f.is_part = is_part;
  f.finalise();
  return f;
}

// Projects world points with OpenCV (an implementation independent of algo::project).
inline std::vector<cv::Point2d> opencv_project(const sim::Rig& rig, const std::vector<cv::Point3d>& world) {
  const auto& k = rig.params.camera.intrinsics;
  cv::Mat camera = (cv::Mat_<double>(3, 3) << k.fx_px, 0, k.cx_px, 0, k.fy_px, k.cy_px, 0, 0, 1);
  cv::Mat dist = (cv::Mat_<double>(1, 5) << k.k1, k.k2, k.p1, k.p2, k.k3);
  cv::Mat r(3, 3, CV_64F), rvec, tvec(3, 1, CV_64F);
  for (int i = 0; i < 3; ++i) {
    tvec.at<double>(i) = rig.camera_pose.t_cam_world[i];
    for (int j = 0; j < 3; ++j) r.at<double>(i, j) = rig.camera_pose.r_cam_world(i, j);
  }
  cv::Rodrigues(r, rvec);
  std::vector<cv::Point2d> out;
  cv::projectPoints(world, rvec, tvec, camera, dist, out);
  return out;
}

// Sub-pixel stripe centre of one row by centre of gravity over the window where the row exceeds `threshold`
// around its maximum (the estimator a stripe extractor would use); NaN when the row has no stripe.
inline double row_centre_of_gravity(const cv::Mat& image, int row, int threshold) {
  const auto* p = image.ptr<std::uint8_t>(row);
  int best = 0;
  for (int x = 1; x < image.cols; ++x) {
    if (p[x] > p[best]) best = x;
  }
  if (p[best] < threshold) return std::numeric_limits<double>::quiet_NaN();
  int lo = best, hi = best;
  while (lo > 0 && p[lo - 1] > 0) --lo;
  while (hi + 1 < image.cols && p[hi + 1] > 0) ++hi;
  double sum = 0, weighted = 0;
  for (int x = lo; x <= hi; ++x) {
    sum += p[x];
    weighted += p[x] * static_cast<double>(x);
  }
  return weighted / sum;
}

// Points on the surface of a catalogue part hung with its part frame at `centre`: each facet sampled on a uv lattice
// (spacing_m, offset by phase * spacing_m), column by column along u like a pass. Independent of the scanner, so a
// matcher's truth is exact; another spacing or phase is another "scan" of the same surface.
inline std::vector<algo::ScanPoint> lattice_surface_points(const sim::PartSpec& spec, const Eigen::Vector3d& centre,
                                                           double spacing_m, double phase) {
  std::vector<algo::ScanPoint> out;
  const Eigen::Isometry3d place{Eigen::Translation3d(centre)};
  for (sim::Facet f : sim::build_part(spec)) {
    f.transform(place);
    Eigen::Vector2d lo = f.outline.front();
    Eigen::Vector2d hi = lo;
    for (const auto& v : f.outline) {
      lo = lo.cwiseMin(v);
      hi = hi.cwiseMax(v);
    }
    const auto nu = static_cast<int>(std::ceil((hi.x() - lo.x()) / spacing_m));
    const auto nv = static_cast<int>(std::ceil((hi.y() - lo.y()) / spacing_m));
    for (int iu = 0; iu < nu; ++iu) {
      for (int iv = 0; iv < nv; ++iv) {
        const double u = lo.x() + (iu + phase) * spacing_m;
        const double v = lo.y() + (iv + phase) * spacing_m;
        if (!f.contains({u, v})) continue;
        const Eigen::Vector3d p = f.at({u, v});
        out.push_back({static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()), 0, 0});
      }
    }
  }
  return out;
}

// DESIGN.md "Pose": p_scan = c + R_z(theta)(p_template - c) + (x, y, 0).
inline std::vector<algo::ScanPoint> displaced_points(const std::vector<algo::ScanPoint>& points,
                                                     const Eigen::Vector2d& c, const algo::PlanarPose& pose) {
  const double cs = std::cos(pose.theta_rad);
  const double sn = std::sin(pose.theta_rad);
  std::vector<algo::ScanPoint> out = points;
  for (algo::ScanPoint& p : out) {
    const double dx = p.x - c.x();
    const double dy = p.y - c.y();
    p.x = static_cast<float>(c.x() + cs * dx - sn * dy + pose.x_m);
    p.y = static_cast<float>(c.y() + sn * dx + cs * dy + pose.y_m);
  }
  return out;
}

}  // namespace cellsight::test
