// The simulated cell's physical set-up: camera, laser, conveyor, carrier and sensor response (all from config).
#pragma once

#include <Eigen/Core>
#include <cstdint>

#include "algo/camera_model.hpp"

namespace cellsight::sim {

// Frames: the world (cell) frame W is fixed to the cabin; the carrier frame C rides on the conveyor.
// Both have x along conveyor travel, y up, z toward the camera; they differ by the travel along x:
//   p_W = p_C + (travel_m - carrier.start_offset_m) * e_x
// so at travel 0 the laser plane (x_W ~ 0) cuts the carrier at x_C = start_offset_m, and the carrier moves +x.
struct CameraPlacement {
  algo::Intrinsics intrinsics{};
  double distance_m = 1.8;                // from the aim point to the camera centre
  double triangulation_angle_deg = 30.0;  // between the optical axis and the laser plane
  Eigen::Vector3d aim_world_m{0.0, 0.55, 0.12};
  double roll_deg = 0.0;
};

struct LaserPlacement {
  Eigen::Vector3d normal_world{1.0, 0.0, 0.0};  // laser plane n . p = offset_m (n normalised on use)
  double offset_m = 0.0;
  Eigen::Vector3d emitter_world_m{0.0, 0.55, 1.5};  // the line projector, lies in the plane
  double sheet_sigma_mm = 0.4;                      // Gaussian half-thickness of the light sheet
};

struct ConveyorParams {
  double speed_m_per_s = 0.01;
  double counts_per_mm = 10.0;             // encoder resolution
  std::int32_t trigger_every_counts = 22;  // one frame per 2.2 mm = one grid cell
};

struct CarrierParams {
  double length_m = 0.65;        // extent along x that one pass scans (the carrier's pitch on the line)
  double height_m = 1.06;        // top of the carrier frame
  double start_offset_m = 0.65;  // x_C under the laser at travel 0
  double plane_z_m = 0.05;       // the carrier's members all lie in this plane, behind the part
  double bar_width_m = 0.03;
  double hanger_spacing_m = 0.30;  // two straps the part hangs from, centred on the carrier
  double hook_height_m = 0.95;     // the part's top edge hangs here (nominal)
  double part_plane_z_m = 0.10;    // the part's sheet hangs in this plane (nominal)
  double reflectivity = 0.2;       // old, many times coated steel
};

// Sensor response and image disturbances.
struct SensorParams {
  double gain_dn_per_us = 0.55;    // stripe peak per microsecond of exposure at reflectivity 1, normal incidence
  double optics_sigma_px = 1.0;    // blur of the lens + sensor
  double bloom_per_log = 0.35;     // sigma growth per natural-log unit of over-exposure
  double ambient_dn = 6.0;         // dark-cabin background level (sensor offset + stray light)
  double ambient_light_dn = 40.0;  // cabin light on a white diffuse surface at the reference exposure
  double reference_exposure_us = 1500.0;
  double speckle_contrast = 0.2;     // laser speckle: relative intensity ripple along the stripe
  double halo_fraction = 0.03;       // light scattered around the stripe by the surface
  double ambient_gradient_dn = 3.0;  // left-to-right unevenness of the background
  double read_noise_dn = 1.8;
  double shot_noise_dn_per_dn = 0.25;  // variance per DN of signal (sensor gain)
  double hot_pixel_fraction = 2e-5;
  double spikes_per_frame = 1.5;    // glints on bare metal (scaled by the specular share of the coating)
  double ghost_probability = 0.08;  // per frame, a secondary reflection of a stripe run (bare metal)
  bool noise = true;                // false: no random disturbance at all (exact tests)
};

struct RigParams {
  CameraPlacement camera{};
  LaserPlacement laser{};
  ConveyorParams conveyor{};
  CarrierParams carrier{};
  SensorParams sensor{};
};

// Derived geometry used by the renderer.
struct Rig {
  RigParams params{};
  algo::CameraPose camera_pose{};  // world -> camera
  Eigen::Vector3d camera_centre_world{};
  Eigen::Vector3d laser_normal_world{};
  double laser_offset_m = 0.0;

  [[nodiscard]] double travel_per_frame_m() const {
    return params.conveyor.trigger_every_counts / params.conveyor.counts_per_mm * 1e-3;
  }
  [[nodiscard]] int frames_per_pass() const;
  // Carrier-frame x shift for a given travel: p_W = p_C + shift * e_x.
  [[nodiscard]] double world_shift_m(double travel_m) const { return travel_m - params.carrier.start_offset_m; }
};

[[nodiscard]] Rig make_rig(const RigParams& params);
[[nodiscard]] RigParams default_rig_params();

}  // namespace cellsight::sim
