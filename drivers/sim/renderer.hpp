// Renders the camera frame a real cell would take at one conveyor position: laser stripe on part and carrier.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <limits>
#include <opencv2/core.hpp>
#include <vector>

#include "drivers/sim/rig.hpp"
#include "drivers/sim/scene.hpp"

namespace cellsight::sim {

// Surface response to the laser: a diffuse share and a specular lobe (bare metal: small diffuse, strong lobe).
struct Material {
  double diffuse = 0.5;
  double specular = 0.0;
  double lobe_deg = 10.0;
};

// What the laser can light in one pass: facets in carrier coordinates and their materials.
struct Scene {
  std::vector<Facet> facets;
  Material carrier_material{};
  Material part_material_a{};  // part-frame x below split_x_m
  Material part_material_b{};  // part-frame x at or above split_x_m (a coating boundary mid-part)
  double split_x_m = std::numeric_limits<double>::infinity();
  Eigen::Isometry3d carrier_to_part = Eigen::Isometry3d::Identity();
};

// One point of the stripe the camera sees: ground truth for reconstruction tests.
struct TruthPoint {
  Eigen::Vector3d p_carrier_m;
  Eigen::Vector2d pixel;
  bool is_part;
  double peak_dn = 0.0;  // stripe peak there at this frame's exposure, before clipping and noise
};

struct FrameRequest {
  double travel_m = 0.0;
  double exposure_us = 1000.0;
  std::uint64_t seed = 0;  // per-frame disturbance seed (noise, glints, ghosts)
  bool laser_on = true;    // off: only the cabin light and the sensor's own noise
};

class Renderer {
 public:
  // Builds the fixed-pattern background (read noise texture, hot pixels) once from noise_seed.
  Renderer(const Rig& rig, std::uint64_t noise_seed);

  // Precomputes what does not change during a pass (the cabin light on the part and carrier, as a height and
  // shade map in carrier x, y). Call once per scene; render() uses the last prepared scene's map.
  void prepare(const Scene& scene);

  // Renders into `image` (CV_8UC1, width x height of the camera; reallocated only if the shape differs).
  // `truth`, when given, receives every visible stripe point (spacing ~0.7 px along the stripe).
  void render(const Scene& scene, const FrameRequest& request, cv::Mat& image,
              std::vector<TruthPoint>* truth = nullptr);

  [[nodiscard]] const Rig& rig() const { return rig_; }

 private:
  struct Segment {  // a lit piece of the laser-plane cut, in carrier coordinates
    Eigen::Vector3d p0, p1;
    int facet;
  };
  struct Sample {
    Eigen::Vector2d pixel;
    double peak_dn, sigma_px;
    bool visible;
  };
  struct FramePose {  // rig expressed in carrier coordinates for this travel
    Eigen::Vector3d laser_normal, emitter, camera_centre, cam_t;
    double laser_offset;
  };

  void cut_scene(const Scene& scene, const FramePose& pose);
  void shadow_segments(const FramePose& pose);
  void sample_segment(const Scene& scene, const FramePose& pose, const Segment& seg, double exposure_us,
                      std::vector<TruthPoint>* truth);
  [[nodiscard]] bool visible(const Scene& scene, const FramePose& pose, const Eigen::Vector3d& p, int facet) const;
  [[nodiscard]] Sample shade(const Scene& scene, const FramePose& pose, const Eigen::Vector3d& p, int facet,
                             double exposure_us) const;
  void draw_run(const Sample* samples, std::size_t count, double gain, double du_px);
  void draw_segment(const Sample& a, const Sample& b, double gain, double du_px);
  void draw_blob(double u, double v, double peak_dn, double sigma_px);
  void add_disturbances(double exposure_us, double specular_share, std::uint64_t seed);
  void compose(cv::Mat& image, std::uint64_t seed);
  void render_ambient(const FramePose& pose, double exposure_us);
  void apply_speckle(std::uint64_t seed);
  void add_halo();

  Rig rig_;
  int width_ = 0, height_ = 0;
  // Background with read noise and the cabin's ambient gradient, larger than a frame: each frame copies a
  // randomly offset window, so per-pixel noise costs a memcpy instead of a random draw.
  std::vector<std::uint8_t> background_;
  int background_stride_ = 0;
  std::vector<std::pair<int, std::uint8_t>> hot_pixels_;  // fixed defects of this sensor
  std::vector<float> signal_;                             // stripe light, DN, max-blended
  std::vector<int> dirty_min_, dirty_max_;                // per row, columns touched in signal_
  std::vector<float> gauss_lut_;                          // exp(-q) for q in [0, kLutMax)
  // Per-frame scratch, kept between frames so steady-state rendering does not allocate.
  std::vector<Segment> segments_, lit_;
  std::vector<std::pair<double, double>> intervals_, scratch_intervals_;
  std::vector<double> crossings_;
  std::vector<Eigen::Vector2d> q0_, q1_;  // segment ends in the laser plane, seen from the emitter
  std::vector<std::pair<double, double>> phi_;
  std::vector<Sample> samples_;
  std::vector<std::vector<Sample>> runs_;
  std::size_t run_count_ = 0;
  // Cabin light: map of the frontmost surface per (x, y) cell of the carrier, and a low-resolution frame of it.
  static constexpr int kAmbientScale = 8;  // frame pixels per low-resolution pixel (cabin light is smooth)
  double map_cell_m_ = 0.002;
  int map_nx_ = 0, map_ny_ = 0;
  std::vector<float> map_z_m_, map_shade_;  // shade: DN at the reference exposure; z NaN where empty
  const Scene* prepared_ = nullptr;
  std::vector<Eigen::Vector3d> low_rays_world_;  // per low-resolution pixel, viewing direction
  cv::Mat ambient_low_, ambient_low8_, ambient_full_;
};

// Material of a point: the part's coating can change at split_x_m (part frame); the carrier has its own.
[[nodiscard]] const Material& material_at(const Scene& scene, const Facet& facet, const Eigen::Vector3d& p_carrier);

}  // namespace cellsight::sim
