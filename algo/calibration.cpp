// Technician calibration: board detection, Zhang intrinsics, reference pose, laser plane and conveyor scale.
#include "algo/calibration.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>

namespace cellsight::algo {
namespace {

constexpr double kMm = 1e-3;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

std::string format(const char* fmt, double a, double b = 0.0, double c = 0.0) {
  char buf[256];
  std::snprintf(buf, sizeof buf, fmt, a, b, c);
  return buf;
}

cv::Mat camera_matrix(const Intrinsics& k) {
  return (cv::Mat_<double>(3, 3) << k.fx_px, 0.0, k.cx_px, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 1.0);
}

cv::Mat distortion(const Intrinsics& k) {
  return (cv::Mat_<double>(1, 5) << k.k1, k.k2, k.p1, k.p2, k.k3);
}

std::vector<cv::Point3f> object_points(const BoardSpec& board) {
  std::vector<cv::Point3f> out;
  out.reserve(static_cast<std::size_t>(board.dot_count()));
  for (int i = 0; i < board.dot_count(); ++i) {
    const Eigen::Vector2d p = board.dot_m(i);
    out.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), 0.0F);
  }
  return out;
}

std::vector<cv::Point2f> image_points(const std::vector<Eigen::Vector2d>& dots) {
  std::vector<cv::Point2f> out;
  out.reserve(dots.size());
  for (const auto& d : dots) out.emplace_back(static_cast<float>(d.x()), static_cast<float>(d.y()));
  return out;
}

Eigen::Isometry3d to_isometry(const cv::Mat& rvec, const cv::Mat& tvec) {
  cv::Mat r;
  cv::Rodrigues(rvec, r);
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) t.linear()(i, j) = r.at<double>(i, j);
    t.translation()[i] = tvec.at<double>(i);
  }
  return t;
}

double rotation_angle_deg(const Eigen::Matrix3d& r) {
  return std::acos(std::clamp(0.5 * (r.trace() - 1.0), -1.0, 1.0)) * kRadToDeg;
}

// Reprojection RMS of one view for a given pose.
double view_rms_px(const std::vector<cv::Point3f>& object, const std::vector<cv::Point2f>& image, const cv::Mat& rvec,
                   const cv::Mat& tvec, const cv::Mat& k, const cv::Mat& d) {
  std::vector<cv::Point2f> projected;
  cv::projectPoints(object, rvec, tvec, k, d, projected);
  double sum = 0.0;
  for (std::size_t i = 0; i < image.size(); ++i) {
    const double dx = projected[i].x - image[i].x, dy = projected[i].y - image[i].y;
    sum += dx * dx + dy * dy;
  }
  return image.empty() ? 0.0 : std::sqrt(sum / static_cast<double>(image.size()));
}

bool all_finite(const std::vector<Eigen::Vector2d>& points) {
  return std::all_of(points.begin(), points.end(), [](const Eigen::Vector2d& p) { return p.allFinite(); });
}

double median_of(std::vector<double> values) {
  if (values.empty()) return 0.0;
  const auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
  std::nth_element(values.begin(), mid, values.end());
  return *mid;
}

cv::Ptr<cv::SimpleBlobDetector> dot_detector(const cv::Mat& image, const BoardSpec& board) {
  cv::SimpleBlobDetector::Params params;
  params.filterByColor = true;
  params.blobColor = 0;  // dark dots on a light plate
  params.minArea = 20.0F;
  // A dot can at most fill the share of the picture that the whole board would if it filled the frame.
  params.maxArea = static_cast<float>(static_cast<double>(image.total()) / board.dot_count());
  params.minDistBetweenBlobs = 4.0F;
  params.filterByInertia = true;
  params.minInertiaRatio = 0.1F;  // dots seen at up to ~80 degrees obliquity
  params.filterByConvexity = true;
  params.minConvexity = 0.85F;
  return cv::SimpleBlobDetector::create(params);
}

// Sub-pixel centre of one dark dot: centroid of its relative darkness, re-centred a few times. `to_pixels` maps
// board millimetres near the dot to image pixels (from the neighbouring dots), so the window follows the dot's
// ellipse on a tilted board. The plate level is a plane fitted around the dot, not a constant: the lamp light
// falls off across the board, and a constant level would pull the centroid toward the darker side. Relative
// darkness (plate - I) / (plate - dot) is 1 inside the dot and 0 outside whatever the local light, and
// point-symmetric under symmetric blur, so the centroid is the centre of the dot's image.
Eigen::Vector2d refine_dot(const cv::Mat& image, Eigen::Vector2d centre, const Eigen::Matrix2d& to_pixels,
                           double radius_mm) {
  constexpr int kIterations = 3;
  constexpr double kWindow = 1.25;                      // radii: the blurred edge is inside, the neighbours far outside
  constexpr double kRingInner = 1.7, kRingOuter = 2.0;  // plate level around the dot (neighbours start at ~3 radii)
  constexpr double kCore = 0.5;                         // the dot's own level
  constexpr double kMinContrastDn = 10.0;
  const Eigen::Matrix2d to_board = to_pixels.inverse();
  const double reach_x = kRingOuter * radius_mm * to_pixels.row(0).norm();
  const double reach_y = kRingOuter * radius_mm * to_pixels.row(1).norm();
  for (int it = 0; it < kIterations; ++it) {
    const int x0 = std::max(0, static_cast<int>(std::floor(centre.x() - reach_x)));
    const int x1 = std::min(image.cols - 1, static_cast<int>(std::ceil(centre.x() + reach_x)));
    const int y0 = std::max(0, static_cast<int>(std::floor(centre.y() - reach_y)));
    const int y1 = std::min(image.rows - 1, static_cast<int>(std::ceil(centre.y() + reach_y)));
    if (x0 == 0 || y0 == 0 || x1 == image.cols - 1 || y1 == image.rows - 1) return centre;  // cut by the border
    auto radii = [&](int x, int y) {
      return (to_board * Eigen::Vector2d(x - centre.x(), y - centre.y())).norm() / radius_mm;
    };
    // Plate level: least-squares plane I = a + b dx + c dy over the ring, then again without the pixels
    // further than 3 sigma from the first plane (hot pixels, a stray neighbour edge).
    constexpr double kMinRingPixels = 8.0;
    auto for_ring = [&](auto&& visit) {
      for (int y = y0; y <= y1; ++y) {
        const auto* row = image.ptr<std::uint8_t>(y);
        for (int x = x0; x <= x1; ++x) {
          const double r = radii(x, y);
          if (r >= kRingInner && r <= kRingOuter) visit(Eigen::Vector3d(1.0, x - centre.x(), y - centre.y()), row[x]);
        }
      }
    };
    auto fit_plate = [&](const Eigen::Vector3d* previous, double max_residual, Eigen::Vector3d& plane) {
      Eigen::Matrix3d ata = Eigen::Matrix3d::Zero();
      Eigen::Vector3d atb = Eigen::Vector3d::Zero();
      for_ring([&](const Eigen::Vector3d& a, double value) {
        if (previous != nullptr && std::abs(value - a.dot(*previous)) > max_residual) return;
        ata += a * a.transpose();
        atb += a * value;
      });
      if (ata(0, 0) < kMinRingPixels) return false;  // at the image border: the plate cannot be judged
      plane = ata.ldlt().solve(atb);
      return true;
    };
    Eigen::Vector3d first = Eigen::Vector3d::Zero(), plane = Eigen::Vector3d::Zero();
    if (!fit_plate(nullptr, 0.0, first)) return centre;
    double sum_sq = 0.0;
    int count = 0;
    for_ring([&](const Eigen::Vector3d& a, double value) {
      sum_sq += std::pow(value - a.dot(first), 2);
      ++count;
    });
    if (!fit_plate(&first, 3.0 * std::sqrt(sum_sq / count) + 1.0, plane)) plane = first;
    double core_sum = 0.0;
    int core_count = 0;
    for (int y = y0; y <= y1; ++y) {
      const auto* row = image.ptr<std::uint8_t>(y);
      for (int x = x0; x <= x1; ++x) {
        if (radii(x, y) >= kCore) continue;
        core_sum += row[x];
        ++core_count;
      }
    }
    if (core_count == 0) return centre;
    const double dot_level = core_sum / core_count;
    if (plane.x() - dot_level < kMinContrastDn) return centre;  // no contrast: keep the detector's estimate
    double sum = 0.0, sx = 0.0, sy = 0.0;
    for (int y = y0; y <= y1; ++y) {
      const auto* row = image.ptr<std::uint8_t>(y);
      for (int x = x0; x <= x1; ++x) {
        if (radii(x, y) > kWindow) continue;
        const double plate = plane.dot(Eigen::Vector3d(1.0, x - centre.x(), y - centre.y()));
        const double w = std::clamp((plate - row[x]) / std::max(1.0, plate - dot_level), 0.0, 1.0);
        sum += w;
        sx += w * x;
        sy += w * y;
      }
    }
    if (sum <= 0.0) return centre;
    centre = {sx / sum, sy / sum};
  }
  return centre;
}

Intrinsics intrinsics_from(const cv::Mat& k, const cv::Mat& d, int width_px, int height_px) {
  Intrinsics in;
  in.width_px = width_px;
  in.height_px = height_px;
  in.fx_px = k.at<double>(0, 0);
  in.fy_px = k.at<double>(1, 1);
  in.cx_px = k.at<double>(0, 2);
  in.cy_px = k.at<double>(1, 2);
  const cv::Mat d64 = d.reshape(1, 1);
  in.k1 = d64.at<double>(0);
  in.k2 = d64.at<double>(1);
  in.p1 = d64.at<double>(2);
  in.p2 = d64.at<double>(3);
  in.k3 = d64.total() > 4 ? d64.at<double>(4) : 0.0;
  return in;
}

// A detector finds the centre of the dot's image, which is not the image of the dot's centre: perspective (and
// distortion) shift it toward the far side of a tilted board by up to a few hundredths of a pixel, always the
// same way, which biases the principal point. Per dot: area centroid of the projected circle minus the
// projected centre, under the current camera and pose estimate (the correction of Heikkila, PAMI 2000).
void subtract_dot_bias(const Intrinsics& k, const BoardSpec& board, const Eigen::Isometry3d& board_to_camera,
                       const std::vector<Eigen::Vector2d>& measured, std::vector<cv::Point2f>& corrected) {
  constexpr int kOutline = 48;  // polygon vertices: area error ~(2 pi / 48)^2 / 6 of a bias that is itself tiny
  const double radius = 0.5 * board.dot_diameter_mm * kMm;
  corrected.resize(measured.size());
  for (std::size_t i = 0; i < measured.size(); ++i) {
    const Eigen::Vector2d c = board.dot_m(static_cast<int>(i));
    const Eigen::Vector2d centre_px = project(k, board_to_camera * Eigen::Vector3d(c.x(), c.y(), 0.0));
    double area = 0.0, cx = 0.0, cy = 0.0;
    Eigen::Vector2d prev = Eigen::Vector2d::Zero();
    for (int j = 0; j <= kOutline; ++j) {
      const double t = 2.0 * std::numbers::pi * j / kOutline;
      const Eigen::Vector3d p(c.x() + radius * std::cos(t), c.y() + radius * std::sin(t), 0.0);
      const Eigen::Vector2d q = project(k, board_to_camera * p) - centre_px;  // relative: keeps the sums small
      if (j > 0) {
        const double cross = prev.x() * q.y() - q.x() * prev.y();
        area += cross;
        cx += (prev.x() + q.x()) * cross;
        cy += (prev.y() + q.y()) * cross;
      }
      prev = q;
    }
    Eigen::Vector2d bias = Eigen::Vector2d::Zero();
    if (std::abs(area) > 1e-12) bias = Eigen::Vector2d(cx, cy) / (3.0 * area);
    const Eigen::Vector2d fixed = measured[i] - bias;
    corrected[i] = {static_cast<float>(fixed.x()), static_cast<float>(fixed.y())};
  }
}

// Index of the dot in row i, column j of the board (row-major), widened before the multiplication.
std::size_t dot_index(const BoardSpec& board, int i, int j) {
  return static_cast<std::size_t>(i) * static_cast<std::size_t>(board.cols) + static_cast<std::size_t>(j);
}

}  // namespace

// --- BoardSpec ----------------------------------------------------------------------------------------------

Eigen::Vector2d BoardSpec::dot_m(int index) const {
  const int i = index / cols, j = index % cols;
  return {(2 * j + i % 2) * spacing_mm * kMm, i * spacing_mm * kMm};
}

Eigen::Vector2d BoardSpec::field_size_m() const {
  return {(2 * (cols - 1) + (rows > 1 ? 1 : 0)) * spacing_mm * kMm, (rows - 1) * spacing_mm * kMm};
}

Eigen::Vector2d BoardSpec::plate_min_m() const {
  return 0.5 * field_size_m() - 0.5 * kMm * Eigen::Vector2d(width_mm, height_mm);
}

Eigen::Vector2d BoardSpec::plate_max_m() const {
  return 0.5 * field_size_m() + 0.5 * kMm * Eigen::Vector2d(width_mm, height_mm);
}

double BoardSpec::distance_to_nearest_dot_m(const Eigen::Vector2d& uv) const {
  const double s = spacing_mm * kMm;
  const int i0 = static_cast<int>(std::lround(uv.y() / s));
  double best = std::numeric_limits<double>::infinity();
  for (int i = std::max(0, i0 - 1); i <= std::min(rows - 1, i0 + 1); ++i) {
    const int parity = i % 2;
    const int j = std::clamp(static_cast<int>(std::lround((uv.x() / s - parity) / 2.0)), 0, cols - 1);
    for (int jj = std::max(0, j - 1); jj <= std::min(cols - 1, j + 1); ++jj) {
      best = std::min(best, (uv - Eigen::Vector2d((2 * jj + parity) * s, i * s)).norm());
    }
  }
  return best;
}

std::string validate_board(const BoardSpec& b) {
  if (b.rows < 3 || b.rows % 2 == 0) {
    return "board rows must be odd and at least 3 (an even count makes the pattern look the same turned by 180 "
           "degrees)";
  }
  if (b.cols < 2) return "board cols (dots per row) must be at least 2";
  if (!(b.spacing_mm > 0.0) || !(b.dot_diameter_mm > 0.0))
    return "board spacing_mm and dot_diameter_mm must be positive";
  // Nearest neighbours are diagonal, spacing * sqrt(2) apart; keep a clear gap so blobs never merge.
  constexpr double kMaxFill = 0.7;
  if (b.dot_diameter_mm > kMaxFill * b.spacing_mm * std::numbers::sqrt2) {
    return "board dot_diameter_mm is too large for spacing_mm (dots would nearly touch)";
  }
  const Eigen::Vector2d field = b.field_size_m() / kMm;
  if (b.width_mm < field.x() + 2.0 * b.dot_diameter_mm || b.height_mm < field.y() + 2.0 * b.dot_diameter_mm) {
    return "board plate (width_mm x height_mm) must leave a light border of at least one dot diameter around the dots";
  }
  return {};
}

// --- Detection ----------------------------------------------------------------------------------------------

Expected<std::vector<Eigen::Vector2d>> detect_board(const cv::Mat& image, const BoardSpec& board) {
  if (const std::string why = validate_board(board); !why.empty()) return make_error(why);
  if (image.empty() || image.type() != CV_8UC1) return make_error("not a mono 8-bit image");
  const cv::Size pattern(board.cols, board.rows);
  std::vector<cv::Point2f> centres;
  bool found = false;
  try {
    auto detector = dot_detector(image, board);
    found = cv::findCirclesGrid(image, pattern, centres, cv::CALIB_CB_ASYMMETRIC_GRID, detector);
    if (!found) {  // clustering copes better with strong perspective
      found = cv::findCirclesGrid(image, pattern, centres, cv::CALIB_CB_ASYMMETRIC_GRID | cv::CALIB_CB_CLUSTERING,
                                  detector);
    }
    if (!found) {
      std::vector<cv::KeyPoint> blobs;
      detector->detect(image, blobs);
      char buf[320];
      if (static_cast<int>(blobs.size()) == board.dot_count()) {
        std::snprintf(buf, sizeof buf,
                      "no %d x %d dot board found (all %d dots seen, but not in grid order): hold the board less "
                      "steeply (under about 50 degrees) and check rows/cols match the board",
                      board.rows, board.cols, board.dot_count());
      } else {
        std::snprintf(buf, sizeof buf,
                      "no %d x %d dot board found (%zu dark dots seen, the board has %d): the whole board must be in "
                      "the picture, lit and sharp, and rows/cols must match the board",
                      board.rows, board.cols, blobs.size(), board.dot_count());
      }
      return make_error(buf);
    }
  } catch (const cv::Exception& e) {  // OpenCV reports misuse by exception; stop it here
    return make_error(std::string("board detection failed: ") + e.what());
  }
  if (static_cast<int>(centres.size()) != board.dot_count())
    return make_error("board detection returned a wrong dot count");

  std::vector<Eigen::Vector2d> dots(centres.size());
  for (std::size_t i = 0; i < centres.size(); ++i) dots[i] = {centres[i].x, centres[i].y};
  // The pattern is mirror-symmetric about its middle row; a mirrored order would put the printed face away from
  // the camera. Seen from the front, "along a row" then "down the rows" turns clockwise in the image (y down).
  const Eigen::Vector2d along = dots[1] - dots[0];
  const Eigen::Vector2d down = dots[dot_index(board, 2, 0)] - dots[0];
  if (along.x() * down.y() - along.y() * down.x() < 0.0) {
    std::vector<Eigen::Vector2d> flipped(dots.size());
    for (int i = 0; i < board.rows; ++i) {
      for (int j = 0; j < board.cols; ++j) {
        flipped[dot_index(board, i, j)] = dots[dot_index(board, board.rows - 1 - i, j)];
      }
    }
    dots.swap(flipped);
  }
  // Local board-to-image scale from the neighbours: along the row the next dot is (2 s, 0) away, in the next
  // (or previous) row the same column is (+-s, +-s) away.
  const double s = board.spacing_mm;
  auto at = [&](int i, int j) { return dots[dot_index(board, i, j)]; };
  std::vector<Eigen::Vector2d> refined(dots.size());
  for (int i = 0; i < board.rows; ++i) {
    for (int j = 0; j < board.cols; ++j) {
      const int jn = j + 1 < board.cols ? j + 1 : j - 1;
      const int in = i + 1 < board.rows ? i + 1 : i - 1;
      Eigen::Matrix2d du, dp;
      du.col(0) = Eigen::Vector2d(2.0 * (jn - j) * s, 0.0);
      du.col(1) = Eigen::Vector2d(((in % 2) - (i % 2)) * s, (in - i) * s);
      dp.col(0) = at(i, jn) - at(i, j);
      dp.col(1) = at(in, j) - at(i, j);
      refined[dot_index(board, i, j)] = refine_dot(image, at(i, j), dp * du.inverse(), 0.5 * board.dot_diameter_mm);
    }
  }
  dots.swap(refined);
  return dots;
}

// --- Intrinsics ---------------------------------------------------------------------------------------------

Expected<CameraCalibrationResult> calibrate_intrinsics(const std::vector<std::vector<Eigen::Vector2d>>& views,
                                                       const BoardSpec& board, int width_px, int height_px,
                                                       const CameraCalibrationOptions& options) {
  if (const std::string why = validate_board(board); !why.empty()) return make_error(why);
  if (static_cast<int>(views.size()) < options.min_views) {
    char buf[256];
    std::snprintf(
        buf, sizeof buf,
        "only %zu board views; at least %d are needed: take more pictures with the board tilted 20-40 degrees "
        "in different directions and reaching every part of the image",
        views.size(), options.min_views);
    return make_error(buf);
  }
  if (width_px <= 0 || height_px <= 0) return make_error("image size unknown");
  const std::vector<cv::Point3f> object = object_points(board);
  std::vector<std::vector<cv::Point3f>> objects;
  std::vector<std::vector<cv::Point2f>> images;
  constexpr int kCoverageCols = 8, kCoverageRows = 6;
  std::vector<bool> covered(std::size_t{kCoverageCols} * kCoverageRows, false);
  for (std::size_t v = 0; v < views.size(); ++v) {
    if (static_cast<int>(views[v].size()) != board.dot_count() || !all_finite(views[v])) {
      char buf[160];
      std::snprintf(buf, sizeof buf, "view %zu has %zu dots, the board has %d: detect the board again", v + 1,
                    views[v].size(), board.dot_count());
      return make_error(buf);
    }
    for (const auto& d : views[v]) {
      const int cx = std::clamp(static_cast<int>(d.x() * kCoverageCols / width_px), 0, kCoverageCols - 1);
      const int cy = std::clamp(static_cast<int>(d.y() * kCoverageRows / height_px), 0, kCoverageRows - 1);
      covered[static_cast<std::size_t>(cy) * kCoverageCols + static_cast<std::size_t>(cx)] = true;
    }
    objects.push_back(object);
    images.push_back(image_points(views[v]));
  }

  cv::Mat k, d;
  std::vector<cv::Mat> rvecs, tvecs;
  double rms = 0.0;
  // Zhang's calibration on the measured centres, then again on centres freed of the dot bias that the first
  // estimate predicts (a second round changes the result by far less than its noise).
  constexpr int kRounds = 2;
  try {
    const cv::TermCriteria criteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 200, 1e-12);
    for (int round = 0; round < kRounds; ++round) {
      if (round > 0) {
        const Intrinsics estimate = intrinsics_from(k, d, width_px, height_px);
        for (std::size_t v = 0; v < views.size(); ++v) {
          subtract_dot_bias(estimate, board, to_isometry(rvecs[v], tvecs[v]), views[v], images[v]);
        }
      }
      rms = cv::calibrateCamera(objects, images, cv::Size(width_px, height_px), k, d, rvecs, tvecs, 0, criteria);
    }
  } catch (const cv::Exception& e) {
    return make_error(std::string("camera calibration failed, the views are too similar: tilt the board 20-40 degrees "
                                  "left, right, up and down between views (") +
                      e.what() + ")");
  }
  CameraCalibrationResult out;
  out.intrinsics = intrinsics_from(k, d, width_px, height_px);
  const auto& in = out.intrinsics;
  out.rms_px = rms;
  if (!std::isfinite(rms) || !(in.fx_px > 0.0) || !(in.fy_px > 0.0)) {
    return make_error(
        "camera calibration did not converge: the views are too similar; tilt the board more between views");
  }
  for (std::size_t v = 0; v < views.size(); ++v) {
    out.view_rms_px.push_back(view_rms_px(object, images[v], rvecs[v], tvecs[v], k, d));
    out.board_to_camera.push_back(to_isometry(rvecs[v], tvecs[v]));
  }
  for (std::size_t a = 0; a < out.board_to_camera.size(); ++a) {
    for (std::size_t b = a + 1; b < out.board_to_camera.size(); ++b) {
      const Eigen::Vector3d na = out.board_to_camera[a].linear().col(2), nb = out.board_to_camera[b].linear().col(2);
      out.tilt_spread_deg = std::max(out.tilt_spread_deg, std::acos(std::clamp(na.dot(nb), -1.0, 1.0)) * kRadToDeg);
    }
  }
  out.coverage =
      static_cast<double>(std::count(covered.begin(), covered.end(), true)) / static_cast<double>(covered.size());
  if (out.tilt_spread_deg < options.min_tilt_spread_deg) {
    return make_error(
        format("the board views are nearly parallel (normals within %.1f deg, need %.0f): tilt the board "
               "20-40 degrees left, right, up and down between views",
               out.tilt_spread_deg, options.min_tilt_spread_deg));
  }
  if (rms > options.max_rms_px) {
    std::size_t worst = 0;
    for (std::size_t v = 1; v < out.view_rms_px.size(); ++v) {
      if (out.view_rms_px[v] > out.view_rms_px[worst]) worst = v;
    }
    return make_error(
        format("reprojection error %.3f px is above the limit %.2f px (worst: view %.0f): retake blurred "
               "or badly lit views, check the board is flat and its dimensions are right",
               rms, options.max_rms_px, static_cast<double>(worst + 1)));
  }
  if (out.coverage < options.min_coverage) {
    out.warnings.push_back(
        format("the dots reached only %.0f %% of the image: hold the board near the edges and "
               "corners too, or the distortion is poorly known there",
               100.0 * out.coverage));
  }
  return out;
}

// --- Poses --------------------------------------------------------------------------------------------------

Expected<BoardPose> solve_board_pose(const Intrinsics& intrinsics, const BoardSpec& board,
                                     const std::vector<Eigen::Vector2d>& dots) {
  if (static_cast<int>(dots.size()) != board.dot_count() || !all_finite(dots)) {
    return make_error("board pose: wrong number of dots (detect the board again)");
  }
  const std::vector<cv::Point3f> object = object_points(board);
  std::vector<cv::Point2f> image = image_points(dots);
  const cv::Mat k = camera_matrix(intrinsics), d = distortion(intrinsics);
  cv::Mat rvec, tvec;
  try {
    if (!cv::solvePnP(object, image, k, d, rvec, tvec, false, cv::SOLVEPNP_IPPE)) {
      return make_error("board pose could not be solved (solvePnP failed)");
    }
    cv::solvePnPRefineLM(object, image, k, d, rvec, tvec);
    subtract_dot_bias(intrinsics, board, to_isometry(rvec, tvec), dots, image);  // as in calibrate_intrinsics
    cv::solvePnPRefineLM(object, image, k, d, rvec, tvec);
  } catch (const cv::Exception& e) {
    return make_error(std::string("board pose failed: ") + e.what());
  }
  BoardPose out;
  out.board_to_camera = to_isometry(rvec, tvec);
  out.rms_px = view_rms_px(object, image, rvec, tvec, k, d);
  if (out.board_to_camera.linear().col(2).z() <= 0.0 || out.board_to_camera.translation().z() <= 0.0) {
    return make_error(
        "board pose puts the printed face away from the camera: the board is seen from behind or mirrored");
  }
  return out;
}

Eigen::Isometry3d fixture_board_to_cell(const Eigen::Vector3d& origin_cell_m) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear().col(0) = Eigen::Vector3d::UnitX();
  t.linear().col(1) = -Eigen::Vector3d::UnitY();
  t.linear().col(2) = -Eigen::Vector3d::UnitZ();
  t.translation() = origin_cell_m;
  return t;
}

Expected<ReferencePose> camera_pose_from_reference(const Intrinsics& intrinsics, const BoardSpec& board,
                                                   const std::vector<Eigen::Vector2d>& dots,
                                                   const Eigen::Isometry3d& board_to_cell, double max_rms_px) {
  auto pose = solve_board_pose(intrinsics, board, dots);
  if (!pose) return pose.error();
  if (pose->rms_px > max_rms_px) {
    return make_error(
        format("reference view reprojection error %.3f px is above %.2f px: retake the reference picture "
               "(board flat in the fixture, sharp, evenly lit)",
               pose->rms_px, max_rms_px));
  }
  // cell -> camera = (board -> camera) * (cell -> board)
  const Eigen::Isometry3d cell_to_camera = pose->board_to_camera * board_to_cell.inverse();
  ReferencePose out;
  out.camera_pose.r_cam_world = cell_to_camera.linear();
  out.camera_pose.t_cam_world = cell_to_camera.translation();
  out.rms_px = pose->rms_px;
  return out;
}

// --- Laser plane --------------------------------------------------------------------------------------------

std::vector<Eigen::Vector2d> laser_line_centres(const cv::Mat& image, const LaserLineOptions& options) {
  std::vector<Eigen::Vector2d> out;
  if (image.empty() || image.type() != CV_8UC1 || image.cols < 3) return out;
  constexpr int kBackgroundNear = 8, kBackgroundFar = 16;  // px from the peak: outside the stripe and its blur
  const int w = image.cols;
  for (int y = 0; y < image.rows; ++y) {
    const auto* p = image.ptr<std::uint8_t>(y);
    // The peak of a [1 2 1] smoothed row: a lone hot pixel loses half its height, a stripe a few percent.
    int best = 1, best_value = -1;
    for (int x = 1; x + 1 < w; ++x) {
      const int v = p[x - 1] + 2 * p[x] + p[x + 1];
      if (v > best_value) {
        best_value = v;
        best = x;
      }
    }
    double bg_sum = 0.0;
    int bg_count = 0;
    for (int side : {-1, 1}) {
      for (int d = kBackgroundNear; d <= kBackgroundFar; ++d) {
        const int x = best + side * d;
        if (x < 0 || x >= w) continue;
        bg_sum += p[x];
        ++bg_count;
      }
    }
    if (bg_count == 0) continue;
    const double background = bg_sum / bg_count;
    if (best_value / 4.0 - background < options.min_contrast_dn) continue;
    const int x0 = best - options.half_window_px, x1 = best + options.half_window_px;
    if (x0 < 0 || x1 >= w) continue;  // cut by the image border: the centre would be biased
    double sum = 0.0, sx = 0.0, sxx = 0.0;
    for (int x = x0; x <= x1; ++x) {
      const double weight = std::max(0.0, p[x] - background);
      sum += weight;
      sx += weight * x;
      sxx += weight * x * x;
    }
    if (sum <= 0.0) continue;
    const double centre = sx / sum;
    const double sigma = std::sqrt(std::max(0.0, sxx / sum - centre * centre));
    if (sigma < options.min_sigma_px || sigma > options.max_sigma_px) continue;
    out.emplace_back(centre, y);
  }
  return out;
}

PlaneFit fit_plane(const std::vector<Eigen::Vector3d>& points) {
  PlaneFit fit;
  if (points.size() < 3) return fit;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  for (const auto& p : points) centroid += p;
  centroid /= static_cast<double>(points.size());
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const auto& p : points) scatter += (p - centroid) * (p - centroid).transpose();
  scatter /= static_cast<double>(points.size());
  // Eigenvalues come in increasing order: the first eigenvector is the direction of least spread.
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(scatter);
  Eigen::Vector3d n = eigen.eigenvectors().col(0);
  if (n.x() < 0.0) n = -n;
  fit.normal = n.normalized();
  fit.offset = fit.normal.dot(centroid);
  const Eigen::Vector3d variance = eigen.eigenvalues().cwiseMax(0.0);
  fit.spread = Eigen::Vector3d(variance.z(), variance.y(), variance.x()).cwiseSqrt();
  return fit;
}

namespace {

// Fits a plane, then drops points further than reject_sigmas robust deviations and refits until nothing changes;
// returns which points are kept.
std::vector<bool> robust_plane_inliers(const std::vector<Eigen::Vector3d>& points, double reject_sigmas) {
  constexpr int kMaxRounds = 5;
  constexpr double kMinThresholdM = 0.05 * kMm;  // never reject below the stripe's own noise level
  std::vector<bool> keep(points.size(), true);
  for (int round = 0; round < kMaxRounds; ++round) {
    std::vector<Eigen::Vector3d> kept;
    for (std::size_t i = 0; i < points.size(); ++i) {
      if (keep[i]) kept.push_back(points[i]);
    }
    const PlaneFit fit = fit_plane(kept);
    std::vector<double> abs_residual;
    abs_residual.reserve(kept.size());
    for (const auto& p : kept) abs_residual.push_back(std::abs(fit.normal.dot(p) - fit.offset));
    const double sigma = 1.4826 * median_of(abs_residual);
    const double threshold = std::max(kMinThresholdM, reject_sigmas * sigma);
    bool changed = false;
    for (std::size_t i = 0; i < points.size(); ++i) {
      const bool now = std::abs(fit.normal.dot(points[i]) - fit.offset) <= threshold;
      if (now != keep[i]) changed = true;
      keep[i] = now;
    }
    if (!changed) break;
  }
  return keep;
}

}  // namespace

Expected<LaserPlaneResult> calibrate_laser_plane(const Intrinsics& intrinsics, const CameraPose& camera_pose,
                                                 const BoardSpec& board, const std::vector<LaserView>& views,
                                                 const LaserCalibrationOptions& options) {
  if (const std::string why = validate_board(board); !why.empty()) return make_error(why);
  if (views.size() < 2) {
    return make_error(
        format("%.0f laser view: the plane needs at least 2 board poses that cut the laser at different "
               "depths or tilts",
               static_cast<double>(views.size())));
  }
  const double margin_m = options.dot_margin_mm * kMm;
  const double keep_out_m = 0.5 * board.dot_diameter_mm * kMm + margin_m;
  const Eigen::Vector2d plate_lo = board.plate_min_m() + Eigen::Vector2d::Constant(margin_m);
  const Eigen::Vector2d plate_hi = board.plate_max_m() - Eigen::Vector2d::Constant(margin_m);
  const Eigen::Matrix3d r_world_cam = camera_pose.r_cam_world.transpose();

  std::vector<Eigen::Vector3d> points;
  std::vector<int> view_of;
  LaserPlaneResult out;
  for (std::size_t v = 0; v < views.size(); ++v) {
    auto pose = solve_board_pose(intrinsics, board, views[v].dots);
    if (!pose) return make_error("laser view " + std::to_string(v + 1) + ": " + pose.error().message);
    const Eigen::Matrix3d& r = pose->board_to_camera.linear();
    const Eigen::Vector3d& t = pose->board_to_camera.translation();
    const Eigen::Vector3d normal_cam = r.col(2);
    int count = 0;
    for (const Eigen::Vector2d& px : views[v].stripe_px) {
      // thesis eqs. 3.1-3.3: the viewing ray through the pixel meets a known plane (here the board's).
      const Eigen::Vector2d n = undistort(intrinsics, px);
      const Eigen::Vector3d ray(n.x(), n.y(), 1.0);
      const double denom = normal_cam.dot(ray);
      if (std::abs(denom) < 1e-9) continue;
      const Eigen::Vector3d p_cam = (normal_cam.dot(t) / denom) * ray;
      const Eigen::Vector2d uv = (r.transpose() * (p_cam - t)).head<2>();
      if ((uv.array() < plate_lo.array()).any() || (uv.array() > plate_hi.array()).any()) continue;
      if (board.distance_to_nearest_dot_m(uv) < keep_out_m) continue;  // a dark dot: stripe missing or biased
      points.push_back(r_world_cam * (p_cam - camera_pose.t_cam_world));
      view_of.push_back(static_cast<int>(v));
      ++count;
    }
    if (count < options.min_points_per_view) {
      char buf[320];
      std::snprintf(buf, sizeof buf,
                    "laser view %zu: only %d stripe points on the board (need %d): the laser line must cross the "
                    "board's dots; check the laser is on and the stripe is neither saturated nor too dark",
                    v + 1, count, options.min_points_per_view);
      return make_error(buf);
    }
  }

  const std::vector<bool> keep = robust_plane_inliers(points, options.reject_sigmas);
  std::vector<Eigen::Vector3d> kept;
  out.points_per_view.assign(views.size(), 0);
  double sum_sq = 0.0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    if (!keep[i]) continue;
    kept.push_back(points[i]);
    ++out.points_per_view[static_cast<std::size_t>(view_of[i])];
  }
  const PlaneFit fit = fit_plane(kept);
  for (const auto& p : kept) sum_sq += std::pow(fit.normal.dot(p) - fit.offset, 2);
  out.normal = fit.normal;
  out.offset_m = fit.offset;
  out.points_used = static_cast<int>(kept.size());
  out.points_rejected = static_cast<int>(points.size() - kept.size());
  out.residual_rms_mm = kept.empty() ? 0.0 : std::sqrt(sum_sq / static_cast<double>(kept.size())) / kMm;
  out.spread_mm = fit.spread.y() / kMm;
  if (out.spread_mm < options.min_spread_mm) {
    return make_error(
        format("the stripe points of all views lie on nearly one line (spread %.1f mm, need %.0f mm): the "
               "board poses are parallel and in the same place; move the board to different depths and "
               "tilt it differently for each view",
               out.spread_mm, options.min_spread_mm));
  }
  if (out.residual_rms_mm > options.max_residual_mm) {
    return make_error(
        format("the stripe points are %.3f mm RMS from one plane (limit %.2f mm): check the board is flat, "
               "the laser line is sharp and there are no reflections on the board",
               out.residual_rms_mm, options.max_residual_mm));
  }
  return out;
}

// --- Conveyor -----------------------------------------------------------------------------------------------

Expected<ConveyorResult> calibrate_conveyor(const Intrinsics& intrinsics, const CameraPose& camera_pose,
                                            const BoardSpec& board, const std::vector<ConveyorView>& views,
                                            const ConveyorCalibrationOptions& options) {
  if (const std::string why = validate_board(board); !why.empty()) return make_error(why);
  if (views.size() < 2) {
    return make_error("the conveyor scale needs the board on the carrier at 2 or more encoder counts");
  }
  Eigen::Isometry3d cell_to_camera = Eigen::Isometry3d::Identity();
  cell_to_camera.linear() = camera_pose.r_cam_world;
  cell_to_camera.translation() = camera_pose.t_cam_world;
  const Eigen::Isometry3d camera_to_cell = cell_to_camera.inverse();
  std::vector<Eigen::Isometry3d> poses;
  for (std::size_t v = 0; v < views.size(); ++v) {
    auto pose = solve_board_pose(intrinsics, board, views[v].dots);
    if (!pose) return make_error("conveyor view " + std::to_string(v + 1) + ": " + pose.error().message);
    poses.push_back(camera_to_cell * pose->board_to_camera);
  }
  // Straight-line fit p(c) = p_mean + v (c - c_mean), least squares per axis.
  double c_mean = 0.0;
  Eigen::Vector3d p_mean = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < views.size(); ++i) {
    c_mean += static_cast<double>(views[i].encoder_counts);
    p_mean += poses[i].translation();
  }
  c_mean /= static_cast<double>(views.size());
  p_mean /= static_cast<double>(views.size());
  double scc = 0.0;
  Eigen::Vector3d scp = Eigen::Vector3d::Zero();
  for (std::size_t i = 0; i < views.size(); ++i) {
    const double dc = static_cast<double>(views[i].encoder_counts) - c_mean;
    scc += dc * dc;
    scp += dc * (poses[i].translation() - p_mean);
  }
  if (scc <= 0.0) return make_error("all conveyor views have the same encoder count: move the carrier between views");
  const Eigen::Vector3d velocity_m = scp / scc;  // metres per count
  const auto [c_min, c_max] = std::minmax_element(
      views.begin(), views.end(),
      [](const ConveyorView& a, const ConveyorView& b) { return a.encoder_counts < b.encoder_counts; });
  ConveyorResult out;
  out.travel_mm = velocity_m.norm() * static_cast<double>(c_max->encoder_counts - c_min->encoder_counts) / kMm;
  if (out.travel_mm < options.min_travel_mm) {
    return make_error(
        format("the carrier moved only %.1f mm between the first and last view (need %.0f mm): move it "
               "about 200 mm",
               out.travel_mm, options.min_travel_mm));
  }
  out.mm_per_count = velocity_m.norm() / kMm;
  out.direction = velocity_m.normalized();
  out.angle_to_x_deg = std::acos(std::clamp(out.direction.x(), -1.0, 1.0)) * kRadToDeg;
  if (out.direction.x() < 0.0) {
    return make_error(
        "the encoder counts down while the carrier moves downstream (+x): swap the encoder A and B lines "
        "(gpio.encoder_a_line / encoder_b_line) and repeat");
  }
  double sum_sq = 0.0;
  for (std::size_t i = 0; i < views.size(); ++i) {
    const Eigen::Vector3d fitted = p_mean + velocity_m * (static_cast<double>(views[i].encoder_counts) - c_mean);
    sum_sq += (poses[i].translation() - fitted).squaredNorm();
    out.max_rotation_deg =
        std::max(out.max_rotation_deg, rotation_angle_deg(poses[i].linear() * poses[0].linear().transpose()));
  }
  out.residual_rms_mm = std::sqrt(sum_sq / static_cast<double>(views.size())) / kMm;
  if (out.angle_to_x_deg > options.warn_angle_deg) {
    out.warnings.push_back(
        format("the carrier moves %.2f deg away from the cell x axis (direction y %.4f, z %.4f): check the "
               "reference fixture is square to the conveyor",
               out.angle_to_x_deg, out.direction.y(), out.direction.z()));
  }
  if (out.max_rotation_deg > options.warn_rotation_deg) {
    out.warnings.push_back(
        format("the board turned by %.2f deg between views: clamp it rigidly to the carrier", out.max_rotation_deg));
  }
  return out;
}

}  // namespace cellsight::algo
