// Renderer: laser-plane cut of the scene, laser shadowing, camera occlusion, Gaussian stripe and sensor noise.
#include "drivers/sim/renderer.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numbers>
#include <opencv2/imgproc.hpp>

#include "drivers/sim/random.hpp"

namespace cellsight::sim {
namespace {

constexpr double kSampleSpacingPx = 0.7;  // along the stripe; well below a pixel so the polyline is smooth
constexpr int kMaxSamplesPerSegment = 8000;
constexpr int kBoundaryBisections = 12;    // occlusion edges located to ~1e-4 of a sample step
constexpr double kDrawRadiusSigmas = 3.5;  // the Gaussian is cut where it is < 0.3 % of its peak
constexpr double kLutMax = 8.0;            // q = d^2 / (2 sigma^2) range of the exp(-q) table
constexpr int kLutPerUnit = 512;
constexpr double kFullScaleDn = 255.0;
constexpr double kOcclusionEndGuard = 1e-4;  // relative ray length near the lit point itself (~0.2 mm)
constexpr int kBackgroundExtraRows = 256;
constexpr int kBackgroundExtraCols = 64;
constexpr double kMinGrazingSine = 0.05;  // caps the stripe widening on surfaces nearly in the laser plane

double cross2(const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
  return a.x() * b.y() - a.y() * b.x();
}

// Removes [a, b] from a sorted list of disjoint intervals.
void subtract_interval(std::vector<std::pair<double, double>>& intervals,
                       std::vector<std::pair<double, double>>& scratch, double a, double b) {
  scratch.clear();
  for (const auto& [x, y] : intervals) {
    if (b <= x || a >= y) {
      scratch.emplace_back(x, y);
      continue;
    }
    if (a > x) scratch.emplace_back(x, a);
    if (b < y) scratch.emplace_back(b, y);
  }
  intervals.swap(scratch);
}

}  // namespace

const Material& material_at(const Scene& scene, const Facet& facet, const Eigen::Vector3d& p_carrier) {
  if (!facet.is_part) return scene.carrier_material;
  if (!std::isfinite(scene.split_x_m)) return scene.part_material_a;
  const double x_part = (scene.carrier_to_part * p_carrier).x();
  return x_part < scene.split_x_m ? scene.part_material_a : scene.part_material_b;
}

Renderer::Renderer(const Rig& rig, std::uint64_t noise_seed) : rig_(rig) {
  const auto& k = rig_.params.camera.intrinsics;
  const auto& s = rig_.params.sensor;
  width_ = k.width_px;
  height_ = k.height_px;
  background_stride_ = width_ + kBackgroundExtraCols;
  background_.resize(static_cast<std::size_t>(background_stride_) * (height_ + kBackgroundExtraRows));
  Rng rng(mix_seed(noise_seed, 0xB4C6));
  for (int r = 0; r < height_ + kBackgroundExtraRows; ++r) {
    for (int c = 0; c < background_stride_; ++c) {
      const double level = s.ambient_dn + s.ambient_gradient_dn * (static_cast<double>(c) / background_stride_ - 0.5) +
                           s.read_noise_dn * rng.normal();
      background_[static_cast<std::size_t>(r) * background_stride_ + c] =
          static_cast<std::uint8_t>(std::clamp(std::lround(level), 0L, 255L));
    }
  }
  const auto hot_count = static_cast<std::size_t>(s.hot_pixel_fraction * width_ * height_);
  for (std::size_t i = 0; i < hot_count; ++i) {
    const auto index = static_cast<int>(rng.below(static_cast<std::uint64_t>(width_) * height_));
    hot_pixels_.emplace_back(index, static_cast<std::uint8_t>(rng.uniform(120.0, 255.0)));
  }
  signal_.assign(static_cast<std::size_t>(width_) * height_, 0.0F);
  dirty_min_.assign(height_, width_);
  dirty_max_.assign(height_, -1);
  const int low_w = width_ / kAmbientScale, low_h = height_ / kAmbientScale;
  low_rays_world_.reserve(static_cast<std::size_t>(low_w) * low_h);
  for (int by = 0; by < low_h; ++by) {
    for (int bx = 0; bx < low_w; ++bx) {
      const Eigen::Vector2d centre(bx * kAmbientScale + 0.5 * (kAmbientScale - 1),
                                   by * kAmbientScale + 0.5 * (kAmbientScale - 1));
      const Eigen::Vector2d n = algo::undistort(k, centre);
      low_rays_world_.push_back(
          (rig_.camera_pose.r_cam_world.transpose() * Eigen::Vector3d(n.x(), n.y(), 1.0)).normalized());
    }
  }
  ambient_low_.create(low_h, low_w, CV_32F);
  gauss_lut_.resize(static_cast<std::size_t>(kLutMax * kLutPerUnit) + 2);
  for (std::size_t i = 0; i < gauss_lut_.size(); ++i) {
    gauss_lut_[i] = static_cast<float>(std::exp(-static_cast<double>(i) / kLutPerUnit));
  }
}

void Renderer::render(const Scene& scene, const FrameRequest& request, cv::Mat& image, std::vector<TruthPoint>* truth) {
  image.create(height_, width_, CV_8UC1);
  const double shift = rig_.world_shift_m(request.travel_m);
  FramePose pose;
  pose.laser_normal = rig_.laser_normal_world;
  pose.laser_offset = rig_.laser_offset_m - shift * pose.laser_normal.x();
  pose.emitter = rig_.params.laser.emitter_world_m - shift * Eigen::Vector3d::UnitX();
  pose.camera_centre = rig_.camera_centre_world - shift * Eigen::Vector3d::UnitX();
  pose.cam_t = rig_.camera_pose.t_cam_world + shift * rig_.camera_pose.r_cam_world.col(0);

  run_count_ = 0;
  segments_.clear();
  lit_.clear();
  if (request.laser_on) {
    cut_scene(scene, pose);
    shadow_segments(pose);
  }
  double specular_share = 0.0;
  for (const Segment& seg : lit_) {
    sample_segment(scene, pose, seg, request.exposure_us, truth);
    if (scene.facets[seg.facet].is_part) {
      specular_share =
          std::max(specular_share, std::min(1.0, material_at(scene, scene.facets[seg.facet], seg.p0).specular));
    }
  }
  if (rig_.params.sensor.noise) apply_speckle(request.seed);
  for (std::size_t r = 0; r < run_count_; ++r) draw_run(runs_[r].data(), runs_[r].size(), 1.0, 0.0);
  if (rig_.params.sensor.noise) add_disturbances(request.exposure_us, specular_share, request.seed);
  render_ambient(pose, request.exposure_us);
  compose(image, request.seed);
}

void Renderer::prepare(const Scene& scene) {
  const auto& carrier = rig_.params.carrier;
  const auto& sensor = rig_.params.sensor;
  map_nx_ = static_cast<int>(std::ceil(carrier.length_m / map_cell_m_));
  map_ny_ = static_cast<int>(std::ceil(carrier.height_m / map_cell_m_));
  map_z_m_.assign(static_cast<std::size_t>(map_nx_) * map_ny_, std::numeric_limits<float>::quiet_NaN());
  map_shade_.assign(map_z_m_.size(), 0.0F);
  const Eigen::Vector3d light_dir = Eigen::Vector3d(0.3, 0.8, 0.5).normalized();  // cabin lamp above, in front
  constexpr double kMinFacing = 0.15;     // facets seen edge-on from the front are left out of the map
  constexpr double kAmbientFloor = 0.35;  // share of the cabin light that is diffuse from every direction
  for (const Facet& f : scene.facets) {
    if (std::abs(f.normal.z()) < kMinFacing) continue;
    const Eigen::Vector3d nrm = f.normal.z() > 0 ? f.normal : Eigen::Vector3d(-f.normal);
    const int x0 = std::max(0, static_cast<int>(f.bounds.min().x() / map_cell_m_));
    const int x1 = std::min(map_nx_ - 1, static_cast<int>(f.bounds.max().x() / map_cell_m_));
    const int y0 = std::max(0, static_cast<int>(f.bounds.min().y() / map_cell_m_));
    const int y1 = std::min(map_ny_ - 1, static_cast<int>(f.bounds.max().y() / map_cell_m_));
    for (int iy = y0; iy <= y1; ++iy) {
      for (int ix = x0; ix <= x1; ++ix) {
        const double x = (ix + 0.5) * map_cell_m_, y = (iy + 0.5) * map_cell_m_;
        const double z =
            f.origin.z() - (f.normal.x() * (x - f.origin.x()) + f.normal.y() * (y - f.origin.y())) / f.normal.z();
        const Eigen::Vector3d p(x, y, z);
        const std::size_t cell = static_cast<std::size_t>(iy) * map_nx_ + ix;
        if (!std::isnan(map_z_m_[cell]) && map_z_m_[cell] >= z) continue;
        if (!f.contains(f.to_uv(p))) continue;
        const double diffuse = material_at(scene, f, p).diffuse;
        map_z_m_[cell] = static_cast<float>(z);
        map_shade_[cell] =
            static_cast<float>(sensor.ambient_light_dn * diffuse *
                               (kAmbientFloor + (1.0 - kAmbientFloor) * std::max(0.0, nrm.dot(light_dir))));
      }
    }
  }
  prepared_ = &scene;
}

void Renderer::render_ambient(const FramePose& pose, double exposure_us) {
  ambient_low_.setTo(0.0F);
  if (prepared_ != nullptr && !map_z_m_.empty()) {
    const double scale = exposure_us / rig_.params.sensor.reference_exposure_us;
    const Eigen::Vector3d& c = pose.camera_centre;
    const double z_start = rig_.params.carrier.part_plane_z_m;
    auto* out = ambient_low_.ptr<float>(0);
    for (std::size_t i = 0; i < low_rays_world_.size(); ++i) {
      const Eigen::Vector3d& d = low_rays_world_[i];
      // Where the ray meets the surface map: a few fixed-point steps on the height, so raised features
      // appear with the right parallax.
      double z = z_start;
      std::size_t hit = SIZE_MAX;
      constexpr int kHeightIterations = 3;
      for (int it = 0; it < kHeightIterations; ++it) {
        const double t = (z - c.z()) / d.z();
        const double x = c.x() + t * d.x(), y = c.y() + t * d.y();
        const int ix = static_cast<int>(std::floor(x / map_cell_m_));
        const int iy = static_cast<int>(std::floor(y / map_cell_m_));
        if (ix < 0 || iy < 0 || ix >= map_nx_ || iy >= map_ny_) break;
        const std::size_t cell = static_cast<std::size_t>(iy) * map_nx_ + ix;
        if (std::isnan(map_z_m_[cell])) break;
        hit = cell;
        if (std::abs(map_z_m_[cell] - z) < 1e-4) break;
        z = map_z_m_[cell];
      }
      if (hit != SIZE_MAX) out[i] = static_cast<float>(map_shade_[hit] * scale);
    }
  }
  add_halo();
  ambient_low_.convertTo(ambient_low8_, CV_8U);
  cv::resize(ambient_low8_, ambient_full_, cv::Size(width_, height_), 0, 0, cv::INTER_LINEAR);
}

void Renderer::apply_speckle(std::uint64_t seed) {
  const double contrast = rig_.params.sensor.speckle_contrast;
  if (contrast <= 0.0) return;
  Rng rng(mix_seed(seed, 0x5BEC));
  // AR(1) along the stripe: speckle grains span a few samples; unit variance in the log domain.
  constexpr double kCorrelation = 0.7;
  const double innovation = std::sqrt(1.0 - kCorrelation * kCorrelation);
  for (std::size_t r = 0; r < run_count_; ++r) {
    double state = rng.normal();
    for (Sample& s : runs_[r]) {
      state = kCorrelation * state + innovation * rng.normal();
      s.peak_dn *= std::exp(contrast * state - 0.5 * contrast * contrast);
    }
  }
}

void Renderer::add_halo() {
  const double fraction = rig_.params.sensor.halo_fraction;
  if (fraction <= 0.0) return;
  constexpr std::size_t kEvery = 5;  // samples are ~0.7 px apart; a low-resolution pixel is 8 px
  constexpr double kMaxScatterDn = 1500.0;
  const int low_w = ambient_low_.cols, low_h = ambient_low_.rows;
  for (std::size_t r = 0; r < run_count_; ++r) {
    for (std::size_t i = 0; i < runs_[r].size(); i += kEvery) {
      const Sample& s = runs_[r][i];
      const double fx = (s.pixel.x() - 0.5 * (kAmbientScale - 1)) / kAmbientScale;
      const double fy = (s.pixel.y() - 0.5 * (kAmbientScale - 1)) / kAmbientScale;
      const int x0 = static_cast<int>(std::floor(fx)), y0 = static_cast<int>(std::floor(fy));
      const double wx = fx - x0, wy = fy - y0;
      // Tuned at 4 px per low-resolution pixel; a coarser map gathers proportionally more samples per pixel.
      const auto amount = static_cast<float>(fraction * std::min(s.peak_dn, kMaxScatterDn) * 4.0 / kAmbientScale);
      for (int dy = 0; dy < 2; ++dy) {
        for (int dx = 0; dx < 2; ++dx) {
          const int x = x0 + dx, y = y0 + dy;
          if (x < 0 || y < 0 || x >= low_w || y >= low_h) continue;
          ambient_low_.at<float>(y, x) += amount * static_cast<float>((dx ? wx : 1 - wx) * (dy ? wy : 1 - wy));
        }
      }
    }
  }
}

void Renderer::cut_scene(const Scene& scene, const FramePose& pose) {
  segments_.clear();
  const Eigen::Vector3d& n = pose.laser_normal;
  std::vector<double>& crossings = crossings_;
  for (int fi = 0; fi < static_cast<int>(scene.facets.size()); ++fi) {
    const Facet& f = scene.facets[fi];
    // Skip facets entirely on one side of the laser plane.
    double lo = 1e300, hi = -1e300;
    for (int corner = 0; corner < 8; ++corner) {
      const double d = n.dot(f.bounds.corner(static_cast<Eigen::AlignedBox3d::CornerType>(corner))) - pose.laser_offset;
      lo = std::min(lo, d);
      hi = std::max(hi, d);
    }
    if (lo > 0.0 || hi < 0.0) continue;
    const double alpha = n.dot(f.axis_u), beta = n.dot(f.axis_v);
    const double norm2 = alpha * alpha + beta * beta;
    if (norm2 < 1e-12) continue;  // facet parallel to the laser plane
    const double gamma = pose.laser_offset - n.dot(f.origin);
    const Eigen::Vector2d uv0 = gamma / norm2 * Eigen::Vector2d(alpha, beta);
    const Eigen::Vector2d dir = Eigen::Vector2d(-beta, alpha) / std::sqrt(norm2);

    crossings.clear();
    const auto& poly = f.outline;
    for (std::size_t i = 0; i < poly.size(); ++i) {
      const Eigen::Vector2d& a = poly[i];
      const Eigen::Vector2d e = poly[(i + 1) % poly.size()] - a;
      const double denom = cross2(dir, e);
      if (std::abs(denom) < 1e-15) continue;
      const Eigen::Vector2d w = a - uv0;
      const double s = cross2(w, dir) / denom;
      if (s < 0.0 || s >= 1.0) continue;  // half-open edges: a vertex on the line counts once
      crossings.push_back(cross2(w, e) / denom);
    }
    std::sort(crossings.begin(), crossings.end());
    intervals_.clear();
    for (std::size_t i = 0; i + 1 < crossings.size(); i += 2) intervals_.emplace_back(crossings[i], crossings[i + 1]);

    auto cut_circle = [&](const Eigen::Vector2d& c, double r) {
      const Eigen::Vector2d rel = c - uv0;
      const double tc = rel.dot(dir);
      const double perp2 = rel.squaredNorm() - tc * tc;
      if (perp2 >= r * r) return;
      const double h = std::sqrt(r * r - perp2);
      subtract_interval(intervals_, scratch_intervals_, tc - h, tc + h);
    };
    for (const auto& c : f.circles) cut_circle(c.centre, c.radius);
    for (const auto& a : f.arrays) {
      for (int iv = 0; iv < a.count_v; ++iv) {
        for (int iu = 0; iu < a.count_u; ++iu) {
          cut_circle(a.first_centre + Eigen::Vector2d(iu * a.pitch.x(), iv * a.pitch.y()), a.radius);
        }
      }
    }
    for (const auto& r : f.rects) {  // slab clip of the line against the rectangle
      double t0 = -1e300, t1 = 1e300;
      bool miss = false;
      for (int axis = 0; axis < 2; ++axis) {
        if (std::abs(dir[axis]) < 1e-15) {
          if (uv0[axis] <= r.min[axis] || uv0[axis] >= r.max[axis]) miss = true;
          continue;
        }
        double a = (r.min[axis] - uv0[axis]) / dir[axis];
        double b = (r.max[axis] - uv0[axis]) / dir[axis];
        if (a > b) std::swap(a, b);
        t0 = std::max(t0, a);
        t1 = std::min(t1, b);
      }
      if (!miss && t0 < t1) subtract_interval(intervals_, scratch_intervals_, t0, t1);
    }
    for (const auto& [a, b] : intervals_) {
      if (b - a < 1e-7) continue;
      segments_.push_back({f.at(uv0 + a * dir), f.at(uv0 + b * dir), fi});
    }
  }
}

void Renderer::shadow_segments(const FramePose& pose) {
  // 2D problem inside the laser plane, seen from the emitter: a point is lit when no other cut lies between it
  // and the emitter. Coordinates: q.x along the fan's axis (toward the scene), q.y up.
  const Eigen::Vector3d& n = pose.laser_normal;
  const Eigen::Vector3d b2 = (Eigen::Vector3d::UnitY() - n.y() * n).normalized();
  const Eigen::Vector3d b1 = b2.cross(n);
  const double toward_scene = b1.dot(Eigen::Vector3d(0, 0, -1)) >= 0 ? 1.0 : -1.0;
  auto to2d = [&](const Eigen::Vector3d& p) {
    const Eigen::Vector3d d = p - pose.emitter;
    return Eigen::Vector2d(toward_scene * d.dot(b1), d.dot(b2));
  };
  const std::size_t count = segments_.size();
  q0_.resize(count);
  q1_.resize(count);
  phi_.resize(count);
  for (std::size_t i = 0; i < count; ++i) {
    q0_[i] = to2d(segments_[i].p0);
    q1_[i] = to2d(segments_[i].p1);
    const double a = std::atan2(q0_[i].y(), q0_[i].x());
    const double b = std::atan2(q1_[i].y(), q1_[i].x());
    phi_[i] = {std::min(a, b), std::max(a, b)};
  }
  lit_.clear();
  for (std::size_t i = 0; i < count; ++i) {
    const Eigen::Vector2d e = q1_[i] - q0_[i];
    intervals_.clear();
    intervals_.emplace_back(0.0, 1.0);
    for (std::size_t j = 0; j < count && !intervals_.empty(); ++j) {
      if (j == i) continue;
      const double lo = std::max(phi_[i].first, phi_[j].first);
      const double hi = std::min(phi_[i].second, phi_[j].second);
      if (hi - lo < 1e-12) continue;
      const double mid = 0.5 * (lo + hi);
      const Eigen::Vector2d ray(std::cos(mid), std::sin(mid));
      const double den_i = cross2(ray, e);
      const Eigen::Vector2d ej = q1_[j] - q0_[j];
      const double den_j = cross2(ray, ej);
      if (std::abs(den_i) < 1e-15 || std::abs(den_j) < 1e-15) continue;
      const double range_i = cross2(q0_[i], e) / den_i;
      const double range_j = cross2(q0_[j], ej) / den_j;
      if (range_j >= range_i * (1.0 - 1e-9) - 1e-9) continue;  // j is behind i: no shadow
      auto t_at = [&](double phi) {
        const Eigen::Vector2d r(std::cos(phi), std::sin(phi));
        return cross2(q0_[i], r) / cross2(r, e);
      };
      const double ta = t_at(lo), tb = t_at(hi);
      subtract_interval(intervals_, scratch_intervals_, std::min(ta, tb), std::max(ta, tb));
    }
    const Segment& s = segments_[i];
    for (const auto& [a, b] : intervals_) {
      if (b - a < 1e-9) continue;
      lit_.push_back({s.p0 + a * (s.p1 - s.p0), s.p0 + b * (s.p1 - s.p0), s.facet});
    }
  }
}

bool Renderer::visible(const Scene& scene, const FramePose& pose, const Eigen::Vector3d& p, int facet) const {
  const Eigen::Vector3d pc = rig_.camera_pose.r_cam_world * p + pose.cam_t;
  if (pc.z() <= 0.0) return false;
  const Eigen::Vector2d px = algo::project(rig_.params.camera.intrinsics, pc);
  if (px.x() < -0.5 || px.y() < -0.5 || px.x() > width_ - 0.5 || px.y() > height_ - 0.5) return false;
  const Facet& own = scene.facets[facet];
  // Zero-thickness sheet: lit on one side, it can only be seen from that side.
  if (own.normal.dot(pose.emitter - p) * own.normal.dot(pose.camera_centre - p) <= 0.0) return false;
  const Eigen::Vector3d& c = pose.camera_centre;
  const Eigen::Vector3d ray = p - c;
  const Eigen::Vector3d box_min = c.cwiseMin(p), box_max = c.cwiseMax(p);
  for (int j = 0; j < static_cast<int>(scene.facets.size()); ++j) {
    if (j == facet) continue;
    const Facet& f = scene.facets[j];
    if ((f.bounds.min().array() > box_max.array()).any() || (f.bounds.max().array() < box_min.array()).any()) continue;
    const double denom = f.normal.dot(ray);
    if (std::abs(denom) < 1e-15) continue;
    const double t = f.normal.dot(f.origin - c) / denom;
    if (t <= 0.0 || t >= 1.0 - kOcclusionEndGuard) continue;
    if (f.contains(f.to_uv(c + t * ray))) return false;
  }
  return true;
}

Renderer::Sample Renderer::shade(const Scene& scene, const FramePose& pose, const Eigen::Vector3d& p, int facet,
                                 double exposure_us) const {
  const auto& k = rig_.params.camera.intrinsics;
  const auto& s = rig_.params.sensor;
  const Facet& f = scene.facets[facet];
  const Material& m = material_at(scene, f, p);
  const Eigen::Vector3d to_emitter = pose.emitter - p;
  const double emitter_distance = to_emitter.norm();
  const Eigen::Vector3d l = to_emitter / emitter_distance;
  const Eigen::Vector3d v = (pose.camera_centre - p).normalized();
  const Eigen::Vector3d nrm = f.normal.dot(l) >= 0.0 ? f.normal : Eigen::Vector3d(-f.normal);
  const double cos_i = nrm.dot(l);
  const Eigen::Vector3d mirror = 2.0 * cos_i * nrm - l;
  const double off_mirror = std::acos(std::clamp(mirror.dot(v), -1.0, 1.0));
  const double lobe = m.lobe_deg * std::numbers::pi / 180.0;
  const double reflect = m.diffuse * cos_i + m.specular * std::exp(-off_mirror * off_mirror / (2.0 * lobe * lobe));
  // The fan spreads in one direction only, so irradiance falls as 1/r; normalised at the aim point.
  const double reference_distance = (rig_.params.laser.emitter_world_m - rig_.params.camera.aim_world_m).norm();
  const double peak = s.gain_dn_per_us * exposure_us * reflect * reference_distance / emitter_distance;

  Sample out;
  const Eigen::Vector3d pc = rig_.camera_pose.r_cam_world * p + pose.cam_t;
  out.pixel = algo::project(k, pc);
  // The lit band on the surface is the sheet thickness stretched by how obliquely the surface cuts the plane.
  const Eigen::Vector3d& ln = pose.laser_normal;
  const Eigen::Vector3d along_band = ln - ln.dot(f.normal) * f.normal;
  const double sine = std::max(kMinGrazingSine, along_band.norm());
  const double band_m = rig_.params.laser.sheet_sigma_mm * 1e-3 / sine;
  const Eigen::Vector3d band_end = p + band_m * along_band.normalized();
  const double band_px = (algo::project(k, rig_.camera_pose.r_cam_world * band_end + pose.cam_t) - out.pixel).norm();
  const double bloom = 1.0 + s.bloom_per_log * std::log(std::max(1.0, peak / kFullScaleDn));
  out.sigma_px = std::hypot(s.optics_sigma_px, band_px) * bloom;
  out.peak_dn = peak;
  out.visible = true;
  return out;
}

void Renderer::sample_segment(const Scene& scene, const FramePose& pose, const Segment& seg, double exposure_us,
                              std::vector<TruthPoint>* truth) {
  const auto& k = rig_.params.camera.intrinsics;
  const Eigen::Matrix3d& r = rig_.camera_pose.r_cam_world;
  const Eigen::Vector3d c0 = r * seg.p0 + pose.cam_t, c1 = r * seg.p1 + pose.cam_t;
  if (c0.z() <= 0.0 && c1.z() <= 0.0) return;
  const double length_px = (algo::project(k, c0) - algo::project(k, c1)).norm();
  const int n = std::clamp(static_cast<int>(std::ceil(length_px / kSampleSpacingPx)) + 1, 2, kMaxSamplesPerSegment);
  const bool is_part = scene.facets[seg.facet].is_part;

  auto point_at = [&](double t) -> Eigen::Vector3d { return seg.p0 + t * (seg.p1 - seg.p0); };
  auto open_run = [&]() -> std::vector<Sample>& {
    if (run_count_ == runs_.size()) runs_.emplace_back();
    std::vector<Sample>& run = runs_[run_count_++];
    run.clear();
    return run;
  };
  auto emit = [&](std::vector<Sample>& run, const Eigen::Vector3d& p) {
    run.push_back(shade(scene, pose, p, seg.facet, exposure_us));
    if (truth != nullptr) truth->push_back({p, run.back().pixel, is_part, run.back().peak_dn});
  };
  // Locates the visibility change between t_in (visible) and t_out (hidden).
  auto boundary = [&](double t_in, double t_out) {
    for (int i = 0; i < kBoundaryBisections; ++i) {
      const double mid = 0.5 * (t_in + t_out);
      (visible(scene, pose, point_at(mid), seg.facet) ? t_in : t_out) = mid;
    }
    return t_in;
  };

  std::vector<Sample>* run = nullptr;
  bool previous_visible = false;
  double previous_t = 0.0;
  for (int i = 0; i < n; ++i) {
    const double t = static_cast<double>(i) / (n - 1);
    const Eigen::Vector3d p = point_at(t);
    const bool now_visible = visible(scene, pose, p, seg.facet);
    if (now_visible && !previous_visible) {
      run = &open_run();
      if (i > 0) emit(*run, point_at(boundary(t, previous_t)));
    }
    if (now_visible) {
      emit(*run, p);
    } else if (previous_visible) {
      emit(*run, point_at(boundary(previous_t, t)));
      run = nullptr;
    }
    previous_visible = now_visible;
    previous_t = t;
  }
}

void Renderer::draw_segment(const Sample& a, const Sample& b, double gain, double du_px) {
  const Eigen::Vector2d pa = a.pixel + Eigen::Vector2d(du_px, 0.0);
  const Eigen::Vector2d pb = b.pixel + Eigen::Vector2d(du_px, 0.0);
  const double radius = kDrawRadiusSigmas * std::max(a.sigma_px, b.sigma_px);
  const int x0 = std::max(0, static_cast<int>(std::floor(std::min(pa.x(), pb.x()) - radius)));
  const int x1 = std::min(width_ - 1, static_cast<int>(std::ceil(std::max(pa.x(), pb.x()) + radius)));
  const int y0 = std::max(0, static_cast<int>(std::floor(std::min(pa.y(), pb.y()) - radius)));
  const int y1 = std::min(height_ - 1, static_cast<int>(std::ceil(std::max(pa.y(), pb.y()) + radius)));
  if (x0 > x1 || y0 > y1) return;
  const Eigen::Vector2d ab = pb - pa;
  const double len2 = ab.squaredNorm();
  const double inv_len2 = len2 > 1e-18 ? 1.0 / len2 : 0.0;
  for (int y = y0; y <= y1; ++y) {
    float* row = signal_.data() + static_cast<std::size_t>(y) * width_;
    bool touched = false;
    for (int x = x0; x <= x1; ++x) {
      const double px = x - pa.x(), py = y - pa.y();
      const double t = std::clamp((px * ab.x() + py * ab.y()) * inv_len2, 0.0, 1.0);
      const double dx = px - t * ab.x(), dy = py - t * ab.y();
      const double sigma = a.sigma_px + t * (b.sigma_px - a.sigma_px);
      const double q = (dx * dx + dy * dy) / (2.0 * sigma * sigma);
      if (q >= kLutMax) continue;
      const double fi = q * kLutPerUnit;
      const auto i = static_cast<std::size_t>(fi);
      const double w = fi - static_cast<double>(i);
      const double g = gauss_lut_[i] + w * (gauss_lut_[i + 1] - gauss_lut_[i]);
      const auto value = static_cast<float>(gain * (a.peak_dn + t * (b.peak_dn - a.peak_dn)) * g);
      if (value > row[x]) row[x] = value;
      touched = true;
    }
    if (touched) {
      dirty_min_[y] = std::min(dirty_min_[y], x0);
      dirty_max_[y] = std::max(dirty_max_[y], x1);
    }
  }
}

void Renderer::draw_run(const Sample* samples, std::size_t count, double gain, double du_px) {
  if (count == 1) draw_segment(samples[0], samples[0], gain, du_px);
  for (std::size_t i = 1; i < count; ++i) draw_segment(samples[i - 1], samples[i], gain, du_px);
}

void Renderer::draw_blob(double u, double v, double peak_dn, double sigma_px) {
  Sample s;
  s.pixel = {u, v};
  s.peak_dn = peak_dn;
  s.sigma_px = sigma_px;
  s.visible = true;
  draw_segment(s, s, 1.0, 0.0);
}

void Renderer::add_disturbances(double exposure_us, double specular_share, std::uint64_t seed) {
  if (run_count_ == 0 || specular_share <= 0.0) return;
  const auto& s = rig_.params.sensor;
  Rng rng(mix_seed(seed, 0x5B1C));
  // Glints: small saturated spots near the stripe on bare metal (edges, scratches, burrs).
  const int spikes = rng.poisson(s.spikes_per_frame * specular_share);
  const double brightness = std::max(0.3, exposure_us / 1500.0);
  for (int i = 0; i < spikes; ++i) {
    const auto& run = runs_[rng.below(run_count_)];
    if (run.empty()) continue;
    const Sample& at = run[rng.below(run.size())];
    draw_blob(at.pixel.x() + 20.0 * rng.normal(), at.pixel.y() + 4.0 * rng.normal(),
              rng.uniform(150.0, 900.0) * brightness, rng.uniform(0.5, 0.9));
  }
  // Ghost: the stripe reflected off a neighbouring surface, a weaker copy beside a stretch of the real one.
  if (rng.uniform() < s.ghost_probability * specular_share) {
    const auto& run = runs_[rng.below(run_count_)];
    constexpr std::size_t kMinGhostSamples = 30;
    if (run.size() >= kMinGhostSamples) {
      const std::size_t length = std::min<std::size_t>(run.size(), 20 + rng.below(100));
      const std::size_t first = rng.below(run.size() - length + 1);
      const double du = (rng.uniform() < 0.5 ? -1.0 : 1.0) * rng.uniform(6.0, 40.0);
      draw_run(run.data() + first, length, rng.uniform(0.15, 0.6), du);
    }
  }
}

void Renderer::compose(cv::Mat& image, std::uint64_t seed) {
  const auto& s = rig_.params.sensor;
  Rng rng(mix_seed(seed, 0xC0DE));
  const auto row_offset = static_cast<int>(rng.below(kBackgroundExtraRows));
  const auto col_offset = static_cast<int>(rng.below(kBackgroundExtraCols));
  for (int y = 0; y < height_; ++y) {
    std::uint8_t* dst = image.ptr<std::uint8_t>(y);
    if (s.noise) {
      std::memcpy(dst, background_.data() + static_cast<std::size_t>(y + row_offset) * background_stride_ + col_offset,
                  static_cast<std::size_t>(width_));
    } else {
      for (int x = 0; x < width_; ++x) {
        dst[x] = static_cast<std::uint8_t>(std::clamp(
            std::lround(s.ambient_dn + s.ambient_gradient_dn * (static_cast<double>(x) / width_ - 0.5)), 0L, 255L));
      }
    }
    const std::uint8_t* ambient = ambient_full_.ptr<std::uint8_t>(y);
    for (int x = 0; x < width_; ++x) {  // saturating add, written so the compiler vectorises it
      const unsigned sum = static_cast<unsigned>(dst[x]) + ambient[x];
      dst[x] = static_cast<std::uint8_t>(sum > 255U ? 255U : sum);
    }
    if (dirty_max_[y] < 0) continue;
    float* row = signal_.data() + static_cast<std::size_t>(y) * width_;
    for (int x = dirty_min_[y]; x <= dirty_max_[y]; ++x) {
      const double light = row[x];
      if (light <= 0.0F) continue;
      double value = dst[x] + light;
      if (s.noise) value += std::sqrt(s.shot_noise_dn_per_dn * light) * rng.normal();
      dst[x] = static_cast<std::uint8_t>(std::clamp(std::lround(value), 0L, 255L));
      row[x] = 0.0F;
    }
    dirty_min_[y] = width_;
    dirty_max_[y] = -1;
  }
  if (s.noise) {
    for (const auto& [index, value] : hot_pixels_) {
      std::uint8_t& px = image.data[static_cast<std::size_t>(index / width_) * image.step + index % width_];
      px = std::max(px, value);
    }
  }
}

}  // namespace cellsight::sim
