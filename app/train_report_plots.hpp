// The pictures of the training report: the confusion matrix of the test split and the annealing curve of the
// feature selection, as BGR images (write_training_report saves them as PNG).
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "algo/training.hpp"

namespace cellsight::app {

// Where render_confusion_image put the cells (for tests and anyone annotating the image).
struct ConfusionLayout {
  cv::Point origin;  // top-left corner of cell [0][0]
  int cell_px = 0;
  [[nodiscard]] cv::Rect cell(int true_class, int predicted_class) const {
    return {origin.x + predicted_class * cell_px, origin.y + true_class * cell_px, cell_px, cell_px};
  }
};
// BGR image: rows = true class, columns = predicted class, names on both axes, the count in every cell, cells
// shaded by their share of the row (green on the diagonal, red off it, white when empty), recall per row at the
// right.
[[nodiscard]] cv::Mat render_confusion_image(const std::vector<std::string>& class_names,
                                             const std::vector<std::vector<int>>& confusion, const std::string& title,
                                             ConfusionLayout* layout = nullptr);

// A plot panel: data coordinates -> pixels.
struct PlotAxes {
  cv::Rect area;
  double x_min = 0.0, x_max = 1.0, y_min = 0.0, y_max = 1.0;
  bool log_y = false;
  [[nodiscard]] cv::Point2d to_px(double x, double y) const;
};
struct AnnealingPlotLayout {
  PlotAxes accuracy;     // x: iteration, y: accuracy in %
  PlotAxes temperature;  // x: iteration, y: temperature (log scale)
  PlotAxes features;     // same area as temperature, y: active features of the candidate (right axis)
};
// BGR image, two panels sharing the iteration axis: top, the CV accuracy of every candidate (filled dot accepted,
// ring rejected) with the current and best accuracy lines; bottom, the temperature (log, left axis) and the number
// of active features of each candidate (right axis). Ticks, axis labels and legends included.
[[nodiscard]] cv::Mat render_annealing_image(const algo::ClassifierReport& report, const std::string& title,
                                             AnnealingPlotLayout* layout = nullptr);

// A colour as OpenCV stores it (blue, green, red); constexpr, unlike cv::Scalar.
struct Bgr {
  std::uint8_t b = 0, g = 0, r = 0;
  // NOLINTNEXTLINE(google-explicit-constructor): used wherever OpenCV takes a colour
  operator cv::Scalar() const { return {static_cast<double>(b), static_cast<double>(g), static_cast<double>(r)}; }
};
// Colours of the plots, shared with the tests that look for them.
inline constexpr Bgr kBestLineColor{40, 150, 40};
inline constexpr Bgr kCurrentLineColor{0, 140, 255};
inline constexpr Bgr kAcceptedPointColor{190, 110, 30};
inline constexpr Bgr kRejectedPointColor{150, 150, 150};
inline constexpr Bgr kTemperatureLineColor{40, 40, 190};
inline constexpr Bgr kFeaturesLineColor{150, 90, 150};

}  // namespace cellsight::app
