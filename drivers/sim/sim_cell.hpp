// The simulated cell: a catalogue of parts, random passes with known poses, and the frames of each pass.
#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "base/result.hpp"
#include "drivers/sim/renderer.hpp"
#include "drivers/sim/rig.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::sim {

struct Coating {
  std::string name;
  Material material;
  double weight = 1.0;  // relative frequency in random passes
};

struct SimParams {
  double pose_xy_range_m = 0.05;      // uniform in +- range
  double pose_theta_range_deg = 5.0;  // in-plane rotation, about z
  double swing_range_deg = 3.0;       // about the hook's vertical axis
  double tilt_range_deg = 1.5;        // about the horizontal x axis (the part's bottom toward or away from the camera)
  double pose_z_range_m = 0.005;      // depth of the hook (the carrier's distance from the sensor), uniform in +-
  double reflectivity_jitter = 0.15;  // relative, per pass
  double split_probability = 0.0;     // chance of a coating boundary across the part in a pass
  std::vector<Coating> coatings;
  std::uint64_t camera_noise_seed = 1;  // the simulated sensor's fixed pattern (hot pixels, noise texture)
};

// Pose of the part on the carrier for one pass, relative to its nominal hanging position (DESIGN.md "Pose"):
// p = c0 + R_z(theta) R_y(swing) R_x(tilt) p_part + (x, y, z), c0 the nominal centre (see placement()).
struct PartPose {
  double x_m = 0, y_m = 0, theta_rad = 0;  // theta counter-clockwise seen from the camera (+z)
  double swing_rad = 0;                    // about the vertical axis y
  double tilt_rad = 0;                     // about the horizontal axis x
  double z_m = 0;                          // depth, toward the camera positive
};

struct PassSpec {
  std::string part;
  std::uint64_t seed = 0;
  PartPose pose;
  Coating coating_a, coating_b;  // b applies from split_x_m (part frame) on
  double split_x_m = std::numeric_limits<double>::infinity();
  bool with_part = true;  // false: an empty-carrier pass (support calibration)
};

struct FrameInfo {
  int index = 0;
  double travel_m = 0;
  std::int64_t encoder_counts = 0;
  std::int64_t timestamp_ns = 0;
};

class SimCell {
 public:
  SimCell(const RigParams& rig, std::vector<PartSpec> catalogue, SimParams sim);

  [[nodiscard]] const std::vector<PartSpec>& catalogue() const { return catalogue_; }
  [[nodiscard]] const PartSpec* find_part(const std::string& name) const;
  [[nodiscard]] const Rig& rig() const { return rig_; }
  [[nodiscard]] const SimParams& params() const { return sim_; }

  // A pass of `part` with pose and coating drawn from `seed` (the same seed always gives the same pass).
  [[nodiscard]] Expected<PassSpec> random_pass(const std::string& part, std::uint64_t seed) const;
  // Builds the scene of a pass; fails for an unknown part.
  Status begin_pass(const PassSpec& pass);

  [[nodiscard]] int frame_count() const { return rig_.frames_per_pass(); }
  [[nodiscard]] FrameInfo frame_info(int index) const;
  void render_frame(int index, double exposure_us, cv::Mat& image, std::vector<TruthPoint>* truth = nullptr,
                    bool laser_on = true);

  [[nodiscard]] const PassSpec& pass() const { return pass_; }
  [[nodiscard]] const Scene& scene() const { return scene_; }
  // Part frame -> carrier frame for the current pass, and the nominal centre c of DESIGN.md's pose.
  [[nodiscard]] const Eigen::Isometry3d& part_to_carrier() const { return part_to_carrier_; }
  [[nodiscard]] Eigen::Vector3d nominal_centre(const PartSpec& part) const;

 private:
  Rig rig_;
  std::vector<PartSpec> catalogue_;
  SimParams sim_;
  Renderer renderer_;
  PassSpec pass_;
  Scene scene_;
  Eigen::Isometry3d part_to_carrier_ = Eigen::Isometry3d::Identity();
};

// Part frame -> carrier frame of `part` hanging on `carrier` at `pose` (what SimCell::begin_pass places it with).
[[nodiscard]] Eigen::Isometry3d placement(const CarrierParams& carrier, const PartSpec& part, const PartPose& pose);

// Coatings used when the configuration names none: bare metal, primer, matt top coat, dark coat.
[[nodiscard]] std::vector<Coating> default_coatings();

}  // namespace cellsight::sim
