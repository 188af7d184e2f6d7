// Simulated cell: random passes, scene assembly and frame timing.
#include "drivers/sim/sim_cell.hpp"

#include <cmath>
#include <numbers>

#include "drivers/sim/random.hpp"

namespace cellsight::sim {
namespace {
constexpr double kDeg = std::numbers::pi / 180.0;
}

std::vector<Coating> default_coatings() {
  return {
      {"bare_metal", {0.30, 1.6, 7.0}, 1.0},
      {"primer", {0.55, 0.15, 20.0}, 1.0},
      {"matt_coat", {0.14, 0.02, 30.0}, 1.0},
      {"dark_coat", {0.07, 0.05, 25.0}, 0.5},
  };
}

SimCell::SimCell(const RigParams& rig, std::vector<PartSpec> catalogue, SimParams sim)
    : rig_(make_rig(rig)),
      catalogue_(std::move(catalogue)),
      sim_(std::move(sim)),
      renderer_(rig_, sim_.camera_noise_seed) {
  if (sim_.coatings.empty()) sim_.coatings = default_coatings();
}

const PartSpec* SimCell::find_part(const std::string& name) const {
  for (const auto& p : catalogue_) {
    if (p.name == name) return &p;
  }
  return nullptr;
}

Expected<PassSpec> SimCell::random_pass(const std::string& part, std::uint64_t seed) const {
  if (find_part(part) == nullptr) {
    std::string known;
    for (const auto& p : catalogue_) known += (known.empty() ? "" : ", ") + p.name;
    return make_error("unknown part '" + part + "' (the catalogue has: " + known + ")");
  }
  Rng rng(mix_seed(seed, 0x9A55));
  PassSpec pass;
  pass.part = part;
  pass.seed = seed;
  pass.pose.x_m = rng.uniform(-1.0, 1.0) * sim_.pose_xy_range_m;
  pass.pose.y_m = rng.uniform(-1.0, 1.0) * sim_.pose_xy_range_m;
  pass.pose.theta_rad = rng.uniform(-1.0, 1.0) * sim_.pose_theta_range_deg * kDeg;
  pass.pose.swing_rad = rng.uniform(-1.0, 1.0) * sim_.swing_range_deg * kDeg;
  auto pick = [&]() {
    double total = 0.0;
    for (const auto& c : sim_.coatings) total += c.weight;
    double r = rng.uniform() * total;
    Coating chosen = sim_.coatings.back();
    for (const auto& c : sim_.coatings) {
      if (r < c.weight) {
        chosen = c;
        break;
      }
      r -= c.weight;
    }
    const double jitter = 1.0 + sim_.reflectivity_jitter * rng.uniform(-1.0, 1.0);
    chosen.material.diffuse *= jitter;
    chosen.material.specular *= jitter;
    return chosen;
  };
  pass.coating_a = pick();
  pass.coating_b = pick();
  const double split = rng.uniform(-0.15, 0.15);
  if (rng.uniform() < sim_.split_probability) {
    pass.split_x_m = split;
  } else {
    pass.coating_b = pass.coating_a;
  }
  // Drawn last, so that a seed's x, y, theta, coating and split stay what they were before tilt and depth existed.
  pass.pose.tilt_rad = rng.uniform(-1.0, 1.0) * sim_.tilt_range_deg * kDeg;
  pass.pose.z_m = rng.uniform(-1.0, 1.0) * sim_.pose_z_range_m;
  return pass;
}

namespace {

Eigen::Vector3d nominal_centre_on(const CarrierParams& carrier, const PartSpec& part) {
  return {0.5 * carrier.length_m, carrier.hook_height_m - 0.5e-3 * part.height_mm, carrier.part_plane_z_m};
}

}  // namespace

Eigen::Vector3d SimCell::nominal_centre(const PartSpec& part) const {
  return nominal_centre_on(rig_.params.carrier, part);
}

Eigen::Isometry3d placement(const CarrierParams& carrier, const PartSpec& part, const PartPose& pose) {
  const Eigen::Vector3d c = nominal_centre_on(carrier, part);
  // p_C = c + R_z(theta) R_y(swing) R_x(tilt) p_part + (x, y, z): DESIGN.md's pose with the part frame centred on c.
  return Eigen::Translation3d(c + Eigen::Vector3d(pose.x_m, pose.y_m, pose.z_m)) *
         Eigen::AngleAxisd(pose.theta_rad, Eigen::Vector3d::UnitZ()) *
         Eigen::AngleAxisd(pose.swing_rad, Eigen::Vector3d::UnitY()) *
         Eigen::AngleAxisd(pose.tilt_rad, Eigen::Vector3d::UnitX());
}

Status SimCell::begin_pass(const PassSpec& pass) {
  scene_ = Scene{};
  scene_.facets = build_carrier(rig_.params.carrier);
  scene_.carrier_material = Material{rig_.params.carrier.reflectivity, 0.05, 25.0};
  pass_ = pass;
  if (pass.with_part) {
    const PartSpec* part = find_part(pass.part);
    if (part == nullptr) return make_error("unknown part '" + pass.part + "'");
    part_to_carrier_ = placement(rig_.params.carrier, *part, pass.pose);
    for (Facet f : build_part(*part)) {
      f.transform(part_to_carrier_);
      scene_.facets.push_back(std::move(f));
    }
    scene_.carrier_to_part = part_to_carrier_.inverse();
    scene_.part_material_a = pass.coating_a.material;
    scene_.part_material_b = pass.coating_b.material;
    scene_.split_x_m = pass.split_x_m;
  }
  renderer_.prepare(scene_);
  return {};
}

FrameInfo SimCell::frame_info(int index) const {
  FrameInfo info;
  info.index = index;
  info.encoder_counts = static_cast<std::int64_t>(index) * rig_.params.conveyor.trigger_every_counts;
  info.travel_m = static_cast<double>(info.encoder_counts) / rig_.params.conveyor.counts_per_mm * 1e-3;
  info.timestamp_ns = static_cast<std::int64_t>(std::llround(info.travel_m / rig_.params.conveyor.speed_m_per_s * 1e9));
  return info;
}

void SimCell::render_frame(int index, double exposure_us, cv::Mat& image, std::vector<TruthPoint>* truth,
                           bool laser_on) {
  FrameRequest request;
  request.laser_on = laser_on;
  request.travel_m = frame_info(index).travel_m;
  request.exposure_us = exposure_us;
  request.seed = mix_seed(pass_.seed, static_cast<std::uint64_t>(index) + 1);
  renderer_.render(scene_, request, image, truth);
}

}  // namespace cellsight::sim
