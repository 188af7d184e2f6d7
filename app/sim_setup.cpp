// The simulated cell from the configuration: catalogue loading and the grid check of every part's pose extremes.
#include "app/sim_setup.hpp"

#include <numbers>
#include <sstream>

#include "app/catalogue.hpp"

namespace cellsight::app {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

}  // namespace

Expected<sim::SimCell> make_sim_cell(const Config& config) {
  auto catalogue = load_catalogue(config.catalogue_path);
  if (!catalogue) return catalogue.error();
  return sim::SimCell(config.rig, std::move(*catalogue), config.sim);
}

Status check_catalogue_fits_grid(const Config& config, const std::vector<sim::PartSpec>& parts) {
  const Eigen::Vector3d lo = config.grid.origin_m;
  const Eigen::Vector3d hi =
      lo + config.grid.resolution_m * Eigen::Vector3d(config.grid.nx, config.grid.ny, config.grid.nz);
  const double xy = config.sim.pose_xy_range_m;
  const double theta = config.sim.pose_theta_range_deg / kRadToDeg;
  const double swing = config.sim.swing_range_deg / kRadToDeg;
  const double tilt = config.sim.tilt_range_deg / kRadToDeg;
  const double z = config.sim.pose_z_range_m;
  constexpr int kPoseCorners = 64;  // x, y, theta, swing, tilt, z each at - or + its range
  for (const auto& part : parts) {
    const std::vector<sim::Facet> facets = sim::build_part(part);
    for (int corner = 0; corner < kPoseCorners; ++corner) {
      const sim::PartPose pose{(corner & 1 ? xy : -xy),       (corner & 2 ? xy : -xy),
                               (corner & 4 ? theta : -theta), (corner & 8 ? swing : -swing),
                               (corner & 16 ? tilt : -tilt),  (corner & 32 ? z : -z)};
      const Eigen::Isometry3d placement = sim::placement(config.rig.carrier, part, pose);
      for (sim::Facet f : facets) {
        f.transform(placement);
        if ((f.bounds.min().array() < lo.array()).any() || (f.bounds.max().array() > hi.array()).any()) {
          std::ostringstream why;
          why << "part " << part.name << " leaves the grid at the pose x " << pose.x_m << " m, y " << pose.y_m
              << " m, z " << pose.z_m << " m, theta " << pose.theta_rad * kRadToDeg << " deg, swing "
              << pose.swing_rad * kRadToDeg << " deg, tilt " << pose.tilt_rad * kRadToDeg << " deg";
          return make_error(why.str());
        }
      }
    }
  }
  return {};
}

}  // namespace cellsight::app
