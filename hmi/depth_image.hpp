// Depth images of scans for the screen (Review entries, the live page): seen from the camera, 1 px per mm, coloured
// by depth between the scan's 2nd and 98th percentile, unseen black; optionally with a taught part's outline drawn
// where the decision placed it. Rendered on the screen's threads, never the loop's.
#pragma once

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <span>
#include <string>
#include <vector>

#include "algo/decision.hpp"
#include "algo/scan.hpp"

namespace cellsight::hmi {

struct DepthImage {
  cv::Mat colour;                  // CV_8UC3, empty when there were no points
  float x0_m = 0.0f, y1_m = 0.0f;  // carrier-frame x of column 0, y of row 0 (y grows upwards, rows downwards)
  double px_per_m = 1000.0;
  [[nodiscard]] cv::Point2f pixel(double x_m, double y_m) const {
    return {static_cast<float>((x_m - x0_m) * px_per_m), static_cast<float>((y1_m - y_m) * px_per_m)};
  }
};

[[nodiscard]] DepthImage depth_image(std::span<const algo::ScanPoint> points);
[[nodiscard]] std::string encode_png(const cv::Mat& image);  // empty on failure

// A taught part's silhouette seen from the camera: closed polygons in carrier-frame metres (template frame) and
// the template's x-y centroid c (the pose's centre).
struct Outline {
  std::vector<std::vector<Eigen::Vector2d>> polygons;
  Eigen::Vector2d centroid_m = Eigen::Vector2d::Zero();
};

// From a template file's occupied cells (formats::TemplateFile); an error names the file.
[[nodiscard]] bool load_outline(const std::string& template_path, Outline& out, std::string& error);

// Draws `outline` moved by the decision's planar pose (DESIGN.md "Pose": p = c + R(theta)(p_t - c) + (x, y)).
void draw_outline(DepthImage& image, const Outline& outline, const algo::PlanarPose& pose);

}  // namespace cellsight::hmi
