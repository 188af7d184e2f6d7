// Depth images and part outlines for the screen.
#include "hmi/depth_image.hpp"

#include <algorithm>
#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "formats/template_file.hpp"

namespace cellsight::hmi {

DepthImage depth_image(std::span<const algo::ScanPoint> points) {
  DepthImage out;
  if (points.empty()) return out;
  constexpr int kMaxSide = 1200;  // a scan is at most ~650 x 400 mm; larger is clipped
  float x0 = points[0].x, x1 = x0, y0 = points[0].y, y1 = y0;
  std::vector<float> depth;
  depth.reserve(points.size());
  for (const algo::ScanPoint& p : points) {
    x0 = std::min(x0, p.x), x1 = std::max(x1, p.x), y0 = std::min(y0, p.y), y1 = std::max(y1, p.y);
    depth.push_back(p.z);
  }
  const auto lo_it = depth.begin() + static_cast<std::ptrdiff_t>(depth.size() / 50);
  const auto hi_it = depth.begin() + static_cast<std::ptrdiff_t>(depth.size() - 1 - depth.size() / 50);
  std::nth_element(depth.begin(), lo_it, depth.end());
  const float lo = *lo_it;
  std::nth_element(depth.begin(), hi_it, depth.end());
  const float hi = std::max(*hi_it, lo + 1e-4f);
  out.x0_m = x0;
  out.y1_m = y1;
  const int w = std::min(kMaxSide, static_cast<int>((x1 - x0) * out.px_per_m) + 1);
  const int h = std::min(kMaxSide, static_cast<int>((y1 - y0) * out.px_per_m) + 1);
  cv::Mat level(h, w, CV_8UC1, cv::Scalar(0));
  cv::Mat seen(h, w, CV_8UC1, cv::Scalar(0));
  for (const algo::ScanPoint& p : points) {
    const cv::Point2f at = out.pixel(p.x, p.y);
    const int c = static_cast<int>(at.x), r = static_cast<int>(at.y);
    if (c < 0 || c >= w || r < 0 || r >= h) continue;
    const float t = std::clamp((p.z - lo) / (hi - lo), 0.0f, 1.0f);
    level.at<std::uint8_t>(r, c) = static_cast<std::uint8_t>(1 + 254 * t);
    seen.at<std::uint8_t>(r, c) = 255;
  }
  // Close the gaps between profiles (1 mm, more in a thinned preview) so the picture reads as a surface.
  const int gap =
      std::clamp(static_cast<int>(std::lround(std::sqrt(static_cast<double>(w) * h / points.size()))), 1, 6);
  const cv::Mat kernel = cv::getStructuringElement(cv::MORPH_RECT, {2 * gap + 1, 2 * gap + 1});
  cv::dilate(level, level, kernel);
  cv::dilate(seen, seen, kernel);
  cv::applyColorMap(level, out.colour, cv::COLORMAP_VIRIDIS);
  out.colour.setTo(cv::Scalar(0, 0, 0), seen == 0);
  return out;
}

std::string encode_png(const cv::Mat& image) {
  std::vector<std::uint8_t> png;
  if (image.empty() || !cv::imencode(".png", image, png)) return {};
  return {png.begin(), png.end()};
}

bool load_outline(const std::string& template_path, Outline& out, std::string& error) {
  auto info = formats::read_template_info(template_path);
  if (!info) {
    error = info.error().message;
    return false;
  }
  auto file = formats::TemplateFile::open(template_path, info->grid);
  if (!file) {
    error = file.error().message;
    return false;
  }
  const algo::GridSpec& g = info->grid;
  cv::Mat mask(g.ny, g.nx, CV_8UC1, cv::Scalar(0));
  for (const algo::SurfaceCell& c : file->surface_cells()) mask.at<std::uint8_t>(c.y, c.x) = 255;
  cv::morphologyEx(mask, mask, cv::MORPH_CLOSE, cv::getStructuringElement(cv::MORPH_RECT, {3, 3}));
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(mask, contours, cv::RETR_CCOMP, cv::CHAIN_APPROX_SIMPLE);
  out.polygons.clear();
  for (const auto& contour : contours) {
    if (contour.size() < 3) continue;
    std::vector<Eigen::Vector2d> polygon;
    for (const cv::Point& p : contour) {
      polygon.emplace_back(g.origin_m.x() + (p.x + 0.5) * g.resolution_m,
                           g.origin_m.y() + (p.y + 0.5) * g.resolution_m);
    }
    out.polygons.push_back(std::move(polygon));
  }
  out.centroid_m = file->centroid_m();
  return true;
}

void draw_outline(DepthImage& image, const Outline& outline, const algo::PlanarPose& pose) {
  if (image.colour.empty()) return;
  const double c = std::cos(pose.theta_rad), s = std::sin(pose.theta_rad);
  for (const auto& polygon : outline.polygons) {
    std::vector<cv::Point> pixels;
    for (const Eigen::Vector2d& p : polygon) {
      const Eigen::Vector2d d = p - outline.centroid_m;
      const double x = outline.centroid_m.x() + c * d.x() - s * d.y() + pose.x_m;
      const double y = outline.centroid_m.y() + s * d.x() + c * d.y() + pose.y_m;
      const cv::Point2f at = image.pixel(x, y);
      pixels.emplace_back(static_cast<int>(std::lround(at.x)), static_cast<int>(std::lround(at.y)));
    }
    cv::polylines(image.colour, pixels, true, cv::Scalar(255, 255, 255), 2, cv::LINE_AA);
  }
}

}  // namespace cellsight::hmi
