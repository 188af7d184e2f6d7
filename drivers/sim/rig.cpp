// Rig geometry derived from the configured placement.
#include "drivers/sim/rig.hpp"

#include <cmath>
#include <numbers>

namespace cellsight::sim {

int Rig::frames_per_pass() const {
  return static_cast<int>(std::ceil(params.carrier.length_m / travel_per_frame_m() - 1e-9));
}

Rig make_rig(const RigParams& params) {
  Rig rig;
  rig.params = params;
  const auto& cam = params.camera;
  const double angle = cam.triangulation_angle_deg * std::numbers::pi / 180.0;
  // The camera sits beside the laser plane (+x, downstream) and in front of the carrier (+z).
  const Eigen::Vector3d position =
      cam.aim_world_m + cam.distance_m * Eigen::Vector3d(std::sin(angle), 0.0, std::cos(angle));
  rig.camera_pose = algo::look_at(position, cam.aim_world_m, cam.roll_deg * std::numbers::pi / 180.0);
  rig.camera_centre_world = position;
  const double norm = params.laser.normal_world.norm();
  rig.laser_normal_world = params.laser.normal_world / norm;
  rig.laser_offset_m = params.laser.offset_m / norm;
  return rig;
}

RigParams default_rig_params() {
  RigParams p;
  auto& k = p.camera.intrinsics;
  k.width_px = 1024;
  k.height_px = 768;
  k.fx_px = 1100.0;
  k.fy_px = 1100.0;
  k.cx_px = 515.3;
  k.cy_px = 381.7;
  k.k1 = -0.085;
  k.k2 = 0.045;
  k.p1 = 4e-4;
  k.p2 = -3e-4;
  k.k3 = 0.0;
  return p;
}

}  // namespace cellsight::sim
