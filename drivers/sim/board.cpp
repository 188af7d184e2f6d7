// Simulated calibration board: ray-traced plate and dots, lamp or cabin light, laser stripe, sensor noise.
#include "drivers/sim/board.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <opencv2/imgproc.hpp>

#include "drivers/sim/random.hpp"

namespace cellsight::sim {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr int kSuper = 4;              // samples per pixel side where an edge crosses the pixel
constexpr int kOutlineSamples = 24;    // per plate edge, to bound its curved (distorted) image
constexpr double kBboxMarginPx = 4.0;  // lens blur reaches beyond the plate's outline
// Cabin light as Renderer::prepare models it (lamp above and in front, part of it diffuse).
constexpr double kCabinAmbientFloor = 0.35;
const Eigen::Vector3d kCabinLightDir = Eigen::Vector3d(0.3, 0.8, 0.5).normalized();

enum Surface : int { kBackdrop = 0, kPlate = 1, kDot = 2 };

Eigen::Isometry3d cell_to_camera(const Rig& rig) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = rig.camera_pose.r_cam_world;
  t.translation() = rig.camera_pose.t_cam_world;
  return t;
}

// Points around the plate outline in the board frame.
std::vector<Eigen::Vector2d> plate_outline(const algo::BoardSpec& board) {
  const Eigen::Vector2d lo = board.plate_min_m(), hi = board.plate_max_m();
  const Eigen::Vector2d corners[4] = {lo, {hi.x(), lo.y()}, hi, {lo.x(), hi.y()}};
  std::vector<Eigen::Vector2d> out;
  for (int e = 0; e < 4; ++e) {
    for (int i = 0; i < kOutlineSamples; ++i) {
      const double t = static_cast<double>(i) / kOutlineSamples;
      out.push_back(corners[e] + t * (corners[(e + 1) % 4] - corners[e]));
    }
  }
  return out;
}

Surface surface_at(const algo::BoardSpec& board, const Eigen::Vector2d& lo, const Eigen::Vector2d& hi,
                   double dot_radius_m, const Eigen::Vector2d& uv) {
  if ((uv.array() < lo.array()).any() || (uv.array() > hi.array()).any()) return kBackdrop;
  return board.distance_to_nearest_dot_m(uv) < dot_radius_m ? kDot : kPlate;
}

// The calibration lamp's irradiance at board point p (cell frame) whose printed face looks along front_cell.
double lamp_irradiance(const BoardLook& look, const Eigen::Vector3d& lamp_pos, const Eigen::Vector3d& front_cell,
                       const Eigen::Vector3d& p) {
  const Eigen::Vector3d to_lamp = lamp_pos - p;
  const double dist = to_lamp.norm();
  const double cos_i = std::max(0.0, front_cell.dot(to_lamp) / dist);
  return look.lamp_dn * (look.lamp_diffuse_share +
                         (1.0 - look.lamp_diffuse_share) * cos_i * std::pow(look.lamp_reference_m / dist, 2));
}

// Board rotation whose printed face (-z) looks along `front` (a unit vector toward the viewers), rows downward.
Eigen::Matrix3d facing(const Eigen::Vector3d& front) {
  const Eigen::Vector3d x = Eigen::Vector3d::UnitY().cross(front).normalized();
  const Eigen::Vector3d z = -front;
  Eigen::Matrix3d r;
  r.col(0) = x;
  r.col(1) = z.cross(x);
  r.col(2) = z;
  return r;
}

// Normalised undistorted coordinates of a pixel: Newton's method on algo::distort with its analytic Jacobian,
// started from a neighbour's solution (corners a pixel apart differ little), so two or three steps suffice.
Eigen::Vector2d invert_distortion(const algo::Intrinsics& k, const Eigen::Vector2d& pixel, Eigen::Vector2d n) {
  const Eigen::Vector2d target((pixel.x() - k.cx_px) / k.fx_px, (pixel.y() - k.cy_px) / k.fy_px);
  constexpr int kMaxSteps = 8;
  constexpr double kTolerance = 1e-15;  // normalised units: ~1e-12 px
  for (int step = 0; step < kMaxSteps; ++step) {
    const Eigen::Vector2d residual = algo::distort(k, n) - target;
    if (residual.squaredNorm() < kTolerance * kTolerance) break;
    const double x = n.x(), y = n.y(), r2 = x * x + y * y;
    const double radial = 1.0 + r2 * (k.k1 + r2 * (k.k2 + r2 * k.k3));
    const double d_radial = k.k1 + r2 * (2.0 * k.k2 + 3.0 * r2 * k.k3);  // d radial / d r2
    Eigen::Matrix2d j;
    j(0, 0) = radial + 2.0 * x * x * d_radial + 2.0 * k.p1 * y + 6.0 * k.p2 * x;
    j(0, 1) = 2.0 * x * y * d_radial + 2.0 * k.p1 * x + 2.0 * k.p2 * y;
    j(1, 0) = j(0, 1);
    j(1, 1) = radial + 2.0 * y * y * d_radial + 6.0 * k.p1 * y + 2.0 * k.p2 * x;
    n -= j.inverse() * residual;
  }
  return n;
}

Eigen::Vector3d field_centre(const algo::BoardSpec& board) {
  const Eigen::Vector2d c = 0.5 * board.field_size_m();
  return {c.x(), c.y(), 0.0};
}

}  // namespace

Facet board_facet(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, double margin_m) {
  Facet f;
  f.origin = board_to_cell.translation();
  f.axis_u = board_to_cell.linear().col(0);
  f.axis_v = board_to_cell.linear().col(1);
  const Eigen::Vector2d lo = board.plate_min_m(), hi = board.plate_max_m();
  f.outline = {{lo.x() - margin_m, lo.y() - margin_m},
               {hi.x() + margin_m, lo.y() - margin_m},
               {hi.x() + margin_m, hi.y() + margin_m},
               {lo.x() - margin_m, hi.y() + margin_m}};
  const double s = board.spacing_mm * 1e-3;
  const double radius = 0.5 * board.dot_diameter_mm * 1e-3;
  // Even rows start at u = 0, odd rows at u = s; within a row dots are 2 s apart.
  f.arrays.push_back({{0.0, 0.0}, {2.0 * s, 2.0 * s}, board.cols, (board.rows + 1) / 2, radius});
  if (board.rows > 1) f.arrays.push_back({{s, s}, {2.0 * s, 2.0 * s}, board.cols, board.rows / 2, radius});
  f.is_part = true;
  f.finalise();
  return f;
}

BoardRenderer::BoardRenderer(const Rig& rig, std::uint64_t noise_seed, BoardLook look)
    : rig_(rig), look_(look), renderer_(rig, noise_seed) {
  const auto& k = rig_.params.camera.intrinsics;
  width_ = k.width_px;
  height_ = k.height_px;
  corner_rays_.resize(static_cast<std::size_t>(width_ + 1) * (height_ + 1));
  const auto stride = static_cast<std::size_t>(width_ + 1);
  for (int j = 0; j <= height_; ++j) {
    for (int i = 0; i <= width_; ++i) {
      // Pixel centres sit at integer coordinates, so pixel (x, y) spans x - 0.5 .. x + 0.5.
      const std::size_t idx = j * stride + static_cast<std::size_t>(i);
      const Eigen::Vector2d pixel(i - 0.5, j - 0.5);
      corner_rays_[idx] = i > 0   ? invert_distortion(k, pixel, corner_rays_[idx - 1])
                          : j > 0 ? invert_distortion(k, pixel, corner_rays_[idx - stride])
                                  : algo::undistort(k, pixel);
    }
  }
  corner_uv_.resize(corner_rays_.size());
  corner_valid_.resize(corner_rays_.size());
}

std::vector<Eigen::Vector2d> BoardRenderer::project_dots(const algo::BoardSpec& board,
                                                         const Eigen::Isometry3d& board_to_cell) const {
  const Eigen::Isometry3d to_cam = cell_to_camera(rig_) * board_to_cell;
  std::vector<Eigen::Vector2d> out;
  for (int i = 0; i < board.dot_count(); ++i) {
    const Eigen::Vector2d uv = board.dot_m(i);
    out.push_back(algo::project(rig_.params.camera.intrinsics, to_cam * Eigen::Vector3d(uv.x(), uv.y(), 0.0)));
  }
  return out;
}

bool BoardRenderer::fully_visible(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell,
                                  double margin_px) const {
  const Eigen::Isometry3d to_cam = cell_to_camera(rig_) * board_to_cell;
  if (to_cam.linear().col(2).dot(to_cam.translation()) <= 0.0) return false;  // seen from behind
  for (const Eigen::Vector2d& uv : plate_outline(board)) {
    const Eigen::Vector3d p = to_cam * Eigen::Vector3d(uv.x(), uv.y(), 0.0);
    if (p.z() <= 0.0) return false;
    const Eigen::Vector2d px = algo::project(rig_.params.camera.intrinsics, p);
    if (px.x() < margin_px || px.y() < margin_px || px.x() > width_ - 1 - margin_px ||
        px.y() > height_ - 1 - margin_px) {
      return false;
    }
  }
  return true;
}

// One view of the board for shade(): its plane in camera coordinates, the image box the plate can cover, the
// plate's and the dots' extent.
struct BoardRenderer::View {
  Eigen::Vector3d n_cam;  // the board's normal, camera frame
  Eigen::Matrix3d h;      // normalised image point (x, y, 1) -> board (u, v, 1), up to scale
  int x0 = 0, x1 = 0, y0 = 0, y1 = 0;
  Eigen::Vector2d lo, hi;  // the plate, board frame
  double dot_r = 0.0;

  // False when the plate is out of sight: printed face away from the camera, or outside the image.
  [[nodiscard]] bool set(const algo::BoardSpec& board, const Eigen::Isometry3d& to_cam, const algo::Intrinsics& k,
                         int width, int height) {
    const Eigen::Matrix3d& r = to_cam.linear();
    const Eigen::Vector3d& t = to_cam.translation();
    n_cam = r.col(2);
    const double plane_d = n_cam.dot(t);  // board plane in camera coordinates: n . p = plane_d
    if (plane_d <= 0.0) return false;     // printed face away from the camera: nothing of it is seen
    // Normalised image point (x, y, 1) ~ [r1 r2 t] (u, v, 1): a homography, inverted once per view.
    Eigen::Matrix3d m;
    m.col(0) = r.col(0);
    m.col(1) = r.col(1);
    m.col(2) = t;
    h = m.inverse();
    lo = board.plate_min_m();
    hi = board.plate_max_m();
    dot_r = 0.5 * board.dot_diameter_mm * 1e-3;
    return bound_plate(board, to_cam, k, width, height);
  }

  // Image region of the plate (bounded through the distortion by sampling its outline). False when it is empty.
  [[nodiscard]] bool bound_plate(const algo::BoardSpec& board, const Eigen::Isometry3d& to_cam,
                                 const algo::Intrinsics& k, int width, int height) {
    double x_lo = width, x_hi = -1.0, y_lo = height, y_hi = -1.0;
    bool whole_image = false;
    for (const Eigen::Vector2d& uv : plate_outline(board)) {
      const Eigen::Vector3d p = to_cam * Eigen::Vector3d(uv.x(), uv.y(), 0.0);
      if (p.z() <= 0.0) {
        whole_image = true;
        break;
      }
      const Eigen::Vector2d px = algo::project(k, p);
      x_lo = std::min(x_lo, px.x());
      x_hi = std::max(x_hi, px.x());
      y_lo = std::min(y_lo, px.y());
      y_hi = std::max(y_hi, px.y());
    }
    x0 = 0;
    x1 = width - 1;
    y0 = 0;
    y1 = height - 1;
    if (whole_image) return true;
    x0 = std::max(0, static_cast<int>(std::floor(x_lo - kBboxMarginPx)));
    x1 = std::min(width - 1, static_cast<int>(std::ceil(x_hi + kBboxMarginPx)));
    y0 = std::max(0, static_cast<int>(std::floor(y_lo - kBboxMarginPx)));
    y1 = std::min(height - 1, static_cast<int>(std::ceil(y_hi + kBboxMarginPx)));
    return x0 <= x1 && y0 <= y1;
  }

  // Where the ray of a normalised image point meets the board (u, v); false when it never does.
  bool to_board(const Eigen::Vector2d& ray, Eigen::Vector2d& uv) const {
    if (n_cam.dot(Eigen::Vector3d(ray.x(), ray.y(), 1.0)) <= 0.0) return false;  // the ray never meets the plane
    const Eigen::Vector3d q = h * Eigen::Vector3d(ray.x(), ray.y(), 1.0);
    uv = q.head<2>() / q.z();
    return true;
  }
};

void BoardRenderer::shade(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, bool lamp,
                          double exposure_us) {
  const double backdrop = lamp ? look_.backdrop_dn : 0.0;
  light_.create(height_, width_, CV_32F);
  light_.setTo(backdrop);
  View view;
  if (!view.set(board, cell_to_camera(rig_) * board_to_cell, rig_.params.camera.intrinsics, width_, height_)) return;
  map_corners_to_board(view);

  const Eigen::Vector3d front_cell = -board_to_cell.linear().col(2);
  const Eigen::Vector3d lamp_pos = rig_.camera_centre_world + look_.lamp_offset_m;
  const double cabin_scale = exposure_us / rig_.params.sensor.reference_exposure_us;
  const double cabin_irradiance =
      rig_.params.sensor.ambient_light_dn * cabin_scale *
      (kCabinAmbientFloor + (1.0 - kCabinAmbientFloor) * std::max(0.0, front_cell.dot(kCabinLightDir)));
  const int stride = width_ + 1;
  for (int y = view.y0; y <= view.y1; ++y) {
    auto* out = light_.ptr<float>(y);
    for (int x = view.x0; x <= view.x1; ++x) {
      const std::size_t c00 = static_cast<std::size_t>(y) * stride + x, c10 = c00 + 1, c01 = c00 + stride,
                        c11 = c01 + 1;
      if (!(corner_valid_[c00] && corner_valid_[c10] && corner_valid_[c01] && corner_valid_[c11])) continue;
      const Eigen::Vector2d centre = 0.25 * (corner_uv_[c00] + corner_uv_[c10] + corner_uv_[c01] + corner_uv_[c11]);
      const std::array<double, 3> share = pixel_shares(board, view, c00, centre);
      double irradiance = cabin_irradiance;
      if (lamp) {
        const Eigen::Vector3d p = board_to_cell * Eigen::Vector3d(centre.x(), centre.y(), 0.0);
        irradiance = lamp_irradiance(look_, lamp_pos, front_cell, p);
      }
      out[x] = static_cast<float>(share[kBackdrop] * backdrop + irradiance * (share[kPlate] * look_.plate_reflectance +
                                                                              share[kDot] * look_.dot_reflectance));
    }
  }
}

void BoardRenderer::map_corners_to_board(const View& view) {
  const int stride = width_ + 1;
  for (int j = view.y0; j <= view.y1 + 1; ++j) {
    for (int i = view.x0; i <= view.x1 + 1; ++i) {
      const auto idx = static_cast<std::size_t>(j) * stride + i;
      corner_valid_[idx] = view.to_board(corner_rays_[idx], corner_uv_[idx]) ? 1 : 0;
    }
  }
}

std::array<double, 3> BoardRenderer::pixel_shares(const algo::BoardSpec& board, const View& view, std::size_t c00,
                                                  const Eigen::Vector2d& centre) const {
  const std::size_t stride = static_cast<std::size_t>(width_) + 1;
  const std::size_t c10 = c00 + 1, c01 = c00 + stride, c11 = c01 + 1;
  double radius = 0.0;
  for (std::size_t c : {c00, c10, c01, c11}) radius = std::max(radius, (corner_uv_[c] - centre).norm());
  radius *= 1.01;  // the pixel's footprint is (very nearly) the quad of its corners, inside this circle

  // Exact when no edge is near, else 4 x 4 samples.
  std::array<double, 3> share = {0.0, 0.0, 0.0};
  const Eigen::Vector2d& lo = view.lo;
  const Eigen::Vector2d& hi = view.hi;
  const double inside = std::min({centre.x() - lo.x(), hi.x() - centre.x(), centre.y() - lo.y(), hi.y() - centre.y()});
  if (inside >= radius) {
    const double d = board.distance_to_nearest_dot_m(centre);
    if (d >= view.dot_r + radius) {
      share[kPlate] = 1.0;
      return share;
    }
    if (d <= view.dot_r - radius) {
      share[kDot] = 1.0;
      return share;
    }
  } else if (inside < -radius) {
    share[kBackdrop] = 1.0;
    return share;
  }
  const Eigen::Vector2d& r00 = corner_rays_[c00];
  const Eigen::Vector2d& r10 = corner_rays_[c10];
  const Eigen::Vector2d& r01 = corner_rays_[c01];
  const Eigen::Vector2d& r11 = corner_rays_[c11];
  constexpr double kWeight = 1.0 / (kSuper * kSuper);
  for (int sy = 0; sy < kSuper; ++sy) {
    const double b = (sy + 0.5) / kSuper;
    for (int sx = 0; sx < kSuper; ++sx) {
      const double a = (sx + 0.5) / kSuper;
      const Eigen::Vector2d ray = (1 - a) * (1 - b) * r00 + a * (1 - b) * r10 + (1 - a) * b * r01 + a * b * r11;
      Eigen::Vector2d uv;
      const Surface s = view.to_board(ray, uv) ? surface_at(board, lo, hi, view.dot_r, uv) : kBackdrop;
      share[s] += kWeight;
    }
  }
  return share;
}

void BoardRenderer::add_noise_and_quantise(const cv::Mat& background, std::uint64_t seed, cv::Mat& image) {
  const auto& s = rig_.params.sensor;
  cv::GaussianBlur(light_, blurred_, cv::Size(0, 0), s.optics_sigma_px);
  image.create(height_, width_, CV_8UC1);
  Rng rng(mix_seed(seed, 0xB0A2D));
  for (int y = 0; y < height_; ++y) {
    const auto* bg = background.ptr<std::uint8_t>(y);
    const auto* light = blurred_.ptr<float>(y);
    auto* dst = image.ptr<std::uint8_t>(y);
    for (int x = 0; x < width_; ++x) {
      double value = bg[x] + static_cast<double>(light[x]);
      if (s.noise && light[x] > 0.0F) value += std::sqrt(s.shot_noise_dn_per_dn * light[x]) * rng.normal();
      dst[x] = static_cast<std::uint8_t>(std::clamp(std::lround(value), 0L, 255L));
    }
  }
}

void BoardRenderer::render(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell, std::uint64_t seed,
                           cv::Mat& image) {
  // The sensor's own frame (dark level, read noise, hot pixels) from the production renderer, then the board.
  FrameRequest request;
  request.travel_m = rig_.params.carrier.start_offset_m;  // carrier frame == cell frame
  request.exposure_us = rig_.params.sensor.reference_exposure_us;
  request.seed = seed;
  request.laser_on = false;
  renderer_.render(Scene{}, request, background_);
  shade(board, board_to_cell, true, request.exposure_us);
  add_noise_and_quantise(background_, seed, image);
}

void BoardRenderer::render_laser(const algo::BoardSpec& board, const Eigen::Isometry3d& board_to_cell,
                                 double exposure_us, std::uint64_t seed, cv::Mat& image) {
  Scene scene;
  scene.facets.push_back(board_facet(board, board_to_cell));
  scene.part_material_a = Material{look_.plate_reflectance, 0.0, 10.0};
  scene.part_material_b = scene.part_material_a;
  FrameRequest request;
  request.travel_m = rig_.params.carrier.start_offset_m;
  request.exposure_us = exposure_us;
  request.seed = seed;
  request.laser_on = true;
  renderer_.render(scene, request, background_);
  shade(board, board_to_cell, false, exposure_us);
  add_noise_and_quantise(background_, mix_seed(seed, 1), image);
}

// --- Simulated technician -----------------------------------------------------------------------------------

std::vector<Eigen::Isometry3d> plan_camera_views(const BoardRenderer& renderer, const algo::BoardSpec& board) {
  struct Spec {
    double u, v;  // where the board's centre should appear, share of the image width / height
    double distance_m;
    double tilt_x_deg, tilt_y_deg, roll_deg;
  };
  // Tilted 35-50 degrees in every direction and pushed toward each edge and corner: strong perspective pins the
  // principal point and the focal length, the spread over the image the distortion (Zhang's method needs
  // non-parallel views; ten of them keep the principal point to ~0.2 px with this sensor's noise).
  static constexpr Spec kSpecs[] = {
      {0.25, 0.25, 1.35, 40.0, -35.0, 6.0},   {0.75, 0.25, 1.35, 38.0, 40.0, -5.0},
      {0.25, 0.75, 1.35, -40.0, -35.0, 10.0}, {0.75, 0.75, 1.35, -38.0, 40.0, -3.0},
      {0.50, 0.50, 1.25, 5.0, 50.0, 0.0},     {0.50, 0.50, 1.60, 50.0, -5.0, 15.0},
      {0.20, 0.50, 1.40, 10.0, -48.0, -10.0}, {0.80, 0.50, 1.40, -12.0, 48.0, 4.0},
      {0.50, 0.22, 1.40, 48.0, 10.0, -8.0},   {0.50, 0.78, 1.40, -48.0, -10.0, 8.0},
  };
  const Rig& rig = renderer.rig();
  const auto& k = rig.params.camera.intrinsics;
  const Eigen::Isometry3d camera_to_cell = cell_to_camera(rig).inverse();
  std::vector<Eigen::Isometry3d> out;
  for (const Spec& s : kSpecs) {
    double pull = 1.0;  // moves the aim toward the image centre until the whole plate is in the picture
    constexpr int kAttempts = 12;
    for (int attempt = 0; attempt < kAttempts; ++attempt, pull *= 0.85) {
      const Eigen::Vector2d target(k.width_px * (0.5 + pull * (s.u - 0.5)), k.height_px * (0.5 + pull * (s.v - 0.5)));
      const Eigen::Vector2d n = algo::undistort(k, target);
      const Eigen::Vector3d dir = Eigen::Vector3d(n.x(), n.y(), 1.0).normalized();
      Eigen::Matrix3d base;
      base.col(2) = dir;
      base.col(0) = (Eigen::Vector3d::UnitX() - dir.x() * dir).normalized();
      base.col(1) = dir.cross(base.col(0));
      const Eigen::Matrix3d r = base * Eigen::AngleAxisd(s.tilt_x_deg * kDeg, Eigen::Vector3d::UnitX()) *
                                Eigen::AngleAxisd(s.tilt_y_deg * kDeg, Eigen::Vector3d::UnitY()) *
                                Eigen::AngleAxisd(s.roll_deg * kDeg, Eigen::Vector3d::UnitZ());
      Eigen::Isometry3d board_to_camera = Eigen::Isometry3d::Identity();
      board_to_camera.linear() = r;
      board_to_camera.translation() = s.distance_m * dir - r * field_centre(board);
      const Eigen::Isometry3d board_to_cell = camera_to_cell * board_to_camera;
      constexpr double kMarginPx = 8.0;
      if (renderer.fully_visible(board, board_to_cell, kMarginPx)) {
        out.push_back(board_to_cell);
        break;
      }
    }
  }
  return out;
}

Eigen::Vector3d plan_reference_origin(const Rig& rig, const algo::BoardSpec& board) {
  const Eigen::Vector3d& aim = rig.params.camera.aim_world_m;
  const Eigen::Vector2d field = board.field_size_m();
  // Board x = cell +x and board y = cell -y: dot 0 is the top-left dot, half the field left of and above the aim.
  return {aim.x() - 0.5 * field.x(), aim.y() + 0.5 * field.y(), aim.z()};
}

std::vector<Eigen::Isometry3d> plan_laser_views(const Rig& rig, const algo::BoardSpec& board) {
  struct Spec {
    double dy_m, dz_m, yaw_deg, pitch_deg;
  };
  // Different depths and tilts: each board cuts the laser plane along a different line.
  static constexpr Spec kSpecs[] = {{0.00, -0.10, 15.0, 10.0}, {0.04, 0.05, -12.0, -15.0}, {-0.04, 0.20, 5.0, 20.0}};
  const Eigen::Vector3d& aim = rig.params.camera.aim_world_m;
  const Eigen::Vector3d& n = rig.laser_normal_world;
  const Eigen::Vector3d& emitter = rig.params.laser.emitter_world_m;
  std::vector<Eigen::Isometry3d> out;
  for (const Spec& s : kSpecs) {
    Eigen::Vector3d c(0.0, aim.y() + s.dy_m, aim.z() + s.dz_m);
    c.x() = (rig.laser_offset_m - n.y() * c.y() - n.z() * c.z()) / n.x();  // the board's middle on the laser plane
    const Eigen::Vector3d halfway =
        ((rig.camera_centre_world - c).normalized() + (emitter - c).normalized()).normalized();
    const Eigen::Vector3d front = Eigen::AngleAxisd(s.yaw_deg * kDeg, Eigen::Vector3d::UnitY()) *
                                  (Eigen::AngleAxisd(s.pitch_deg * kDeg, Eigen::Vector3d::UnitX()) * halfway);
    Eigen::Isometry3d board_to_cell = Eigen::Isometry3d::Identity();
    board_to_cell.linear() = facing(front);
    board_to_cell.translation() = c - board_to_cell.linear() * field_centre(board);
    out.push_back(board_to_cell);
  }
  return out;
}

std::vector<CarrierView> plan_conveyor_views(const Rig& rig, const algo::BoardSpec& board, int count, double step_mm) {
  const auto& conveyor = rig.params.conveyor;
  const Eigen::Vector3d& aim = rig.params.camera.aim_world_m;
  constexpr double kClampYawDeg = 2.0;  // clamped by hand: not quite square to the conveyor
  Eigen::Isometry3d at_zero = Eigen::Isometry3d::Identity();
  at_zero.linear() =
      facing(Eigen::AngleAxisd(kClampYawDeg * kDeg, Eigen::Vector3d::UnitY()) * Eigen::Vector3d::UnitZ());
  const Eigen::Vector3d centre(aim.x() - 0.5 * (count - 1) * step_mm * 1e-3, aim.y(),
                               rig.params.carrier.part_plane_z_m);
  at_zero.translation() = centre - at_zero.linear() * field_centre(board);
  std::vector<CarrierView> out;
  for (int i = 0; i < count; ++i) {
    CarrierView v;
    v.encoder_counts = std::llround(i * step_mm * conveyor.counts_per_mm);
    // p_W = p_C + (travel - start_offset) e_x: the carrier, and the board on it, move by the travel.
    const double travel_m = static_cast<double>(v.encoder_counts) / conveyor.counts_per_mm * 1e-3;
    v.board_to_cell = Eigen::Translation3d(travel_m * Eigen::Vector3d::UnitX()) * at_zero;
    out.push_back(v);
  }
  return out;
}

}  // namespace cellsight::sim
