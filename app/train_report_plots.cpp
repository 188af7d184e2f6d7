// The pictures of the training report: the confusion matrix and the annealing curve, drawn with OpenCV.
#include "app/train_report_plots.hpp"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

#include "base/string_printf.hpp"

namespace cellsight::app {
namespace {

using base::string_printf;

constexpr double kPercent = 100.0;

}  // namespace

// ---- drawing ------------------------------------------------------------------------------------------------------

namespace {

constexpr int kFont = cv::FONT_HERSHEY_SIMPLEX;
constexpr double kTextScale = 0.45;
constexpr double kSmallTextScale = 0.38;
constexpr double kTitleScale = 0.6;
constexpr Bgr kWhite{255, 255, 255};
constexpr Bgr kBlack{0, 0, 0};
constexpr Bgr kAxisColor{60, 60, 60};
constexpr Bgr kGridColor{228, 228, 228};
constexpr Bgr kCellLineColor{200, 200, 200};
constexpr Bgr kZeroTextColor{195, 195, 195};
constexpr Bgr kDiagonalFull{70, 160, 70};  // green for the correctly recognised share
constexpr Bgr kErrorFull{60, 60, 210};     // red for scans recognised as another part
// A cell with any count gets at least this much colour, so one stray scan is visible.
constexpr double kMinShade = 0.15;

cv::Size text_size(const std::string& text, double scale, int thickness = 1) {
  int baseline = 0;
  cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  size.height += baseline;
  return size;
}

// Text with its left end at x and its vertical middle at y_mid.
void put_text(cv::Mat& image, const std::string& text, int x, int y_mid, double scale, const cv::Scalar& color,
              int thickness = 1) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  cv::putText(image, text, {x, y_mid + size.height / 2}, kFont, scale, color, thickness, cv::LINE_AA);
}

void put_text_centered(cv::Mat& image, const std::string& text, int x_mid, int y_mid, double scale,
                       const cv::Scalar& color, int thickness = 1) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, thickness, &baseline);
  put_text(image, text, x_mid - size.width / 2, y_mid, scale, color, thickness);
}

void put_text_right(cv::Mat& image, const std::string& text, int x_right, int y_mid, double scale,
                    const cv::Scalar& color) {
  int baseline = 0;
  const cv::Size size = cv::getTextSize(text, kFont, scale, 1, &baseline);
  put_text(image, text, x_right - size.width, y_mid, scale, color);
}

// Text reading bottom to top; (x_mid, y_bottom) is where its start lands. Clipped to the image.
void put_text_vertical(cv::Mat& image, const std::string& text, int x_mid, int y_bottom, double scale,
                       const cv::Scalar& color) {
  const cv::Size size = text_size(text, scale);
  cv::Mat label(size.height + 2, size.width + 2, image.type(), kWhite);
  put_text(label, text, 1, label.rows / 2, scale, color);
  cv::Mat turned;
  cv::rotate(label, turned, cv::ROTATE_90_COUNTERCLOCKWISE);
  cv::Rect where(x_mid - turned.cols / 2, y_bottom - turned.rows, turned.cols, turned.rows);
  const cv::Rect inside = where & cv::Rect(0, 0, image.cols, image.rows);
  if (inside.empty()) return;
  turned(cv::Rect(inside.x - where.x, inside.y - where.y, inside.width, inside.height)).copyTo(image(inside));
}

cv::Scalar blend(const cv::Scalar& full, double t) {
  t = std::clamp(t, 0.0, 1.0);
  const cv::Scalar white = kWhite;
  return {white[0] + (full[0] - white[0]) * t, white[1] + (full[1] - white[1]) * t,
          white[2] + (full[2] - white[2]) * t};
}

double luminance(const cv::Scalar& bgr) {
  return 0.114 * bgr[0] + 0.587 * bgr[1] + 0.299 * bgr[2];
}

// 1-2-5 tick step giving about `target` intervals over `span`.
double nice_step(double span, int target) {
  if (!(span > 0.0)) return 1.0;
  const double raw = span / target;
  const double magnitude = std::pow(10.0, std::floor(std::log10(raw)));
  const double f = raw / magnitude;
  const double nice = f < 1.5 ? 1.0 : (f < 3.0 ? 2.0 : (f < 7.0 ? 5.0 : 10.0));
  return nice * magnitude;
}

std::vector<double> ticks_between(double lo, double hi, double step) {
  std::vector<double> t;
  constexpr double kSlack = 1e-9;
  constexpr int kMaxTicks = 100;  // a bad step must not flood the axis
  const double first = std::ceil(lo / step - kSlack);
  for (int i = 0; i < kMaxTicks; ++i) {
    const double v = (first + i) * step;
    if (v > hi + step * kSlack) break;
    t.push_back(std::abs(v) < step * kSlack ? 0.0 : v);
  }
  return t;
}

std::string tick_label(double v) {
  return string_printf("%g", v);
}

}  // namespace

cv::Mat render_confusion_image(const std::vector<std::string>& class_names,
                               const std::vector<std::vector<int>>& confusion, const std::string& title,
                               ConfusionLayout* layout) {
  const int k = static_cast<int>(class_names.size());
  auto count_at = [&](int i, int j) {
    const auto ui = static_cast<std::size_t>(i), uj = static_cast<std::size_t>(j);
    return ui < confusion.size() && uj < confusion[ui].size() ? std::max(confusion[ui][uj], 0) : 0;
  };
  const double scale = k > 20 ? kSmallTextScale : kTextScale;
  int max_count = 0;
  for (const auto& row : confusion) {
    for (int v : row) max_count = std::max(max_count, v);
  }
  int label_w = text_size("part", scale).width;
  for (const std::string& n : class_names) label_w = std::max(label_w, text_size(n, scale).width);
  constexpr int kMargin = 10, kAxisTitle = 22, kTitleBand = 34, kFooter = 30, kMinCell = 34, kCellPad = 14;
  const int cell = std::max(kMinCell, text_size(std::to_string(max_count), scale).width + kCellPad);
  const int recall_w = text_size("100.0 %", scale).width + 2 * kMargin;
  ConfusionLayout geo;
  geo.cell_px = cell;
  geo.origin = {kMargin + kAxisTitle + label_w + kMargin, kTitleBand + kAxisTitle + label_w + kMargin};
  const int matrix = k * cell;
  const int width =
      std::max(geo.origin.x + matrix + recall_w + kMargin, text_size(title, kTitleScale).width + 2 * kMargin);
  const int height = geo.origin.y + matrix + kFooter;
  cv::Mat image(height, width, CV_8UC3, kWhite);
  put_text(image, title, kMargin, kTitleBand / 2, kTitleScale, kBlack);

  // Axis titles and names.
  put_text_centered(image, "recognised as", geo.origin.x + matrix / 2, kTitleBand + kAxisTitle / 2, scale, kAxisColor);
  put_text_vertical(image, "true part", kMargin + kAxisTitle / 2,
                    geo.origin.y + matrix / 2 + text_size("true part", scale).width / 2, scale, kAxisColor);
  for (int i = 0; i < k; ++i) {
    const std::string& n = class_names[static_cast<std::size_t>(i)];
    put_text_right(image, n, geo.origin.x - kMargin, geo.origin.y + i * cell + cell / 2, scale, kBlack);
    put_text_vertical(image, n, geo.origin.x + i * cell + cell / 2, geo.origin.y - kMargin, scale, kBlack);
  }
  put_text_centered(image, "recall", geo.origin.x + matrix + recall_w / 2, geo.origin.y - kMargin - 6, scale,
                    kAxisColor);

  // Cells: shade by share of the row (thesis 6.4.2 measures per part), count in the middle.
  for (int i = 0; i < k; ++i) {
    int total = 0;
    for (int j = 0; j < k; ++j) total += count_at(i, j);
    for (int j = 0; j < k; ++j) {
      const int count = count_at(i, j);
      const cv::Rect r = geo.cell(i, j);
      cv::Scalar fill = kWhite;
      if (count > 0) {
        const double share = static_cast<double>(count) / total;
        fill = blend(i == j ? kDiagonalFull : kErrorFull, kMinShade + (1.0 - kMinShade) * share);
      }
      cv::rectangle(image, r, fill, cv::FILLED);
      cv::rectangle(image, r, kCellLineColor, 1);
      const cv::Scalar ink = count == 0 ? kZeroTextColor : (luminance(fill) < 140.0 ? kWhite : kBlack);
      put_text_centered(image, std::to_string(count), r.x + r.width / 2, r.y + r.height / 2, scale, ink);
    }
    const std::string recall =
        total > 0 ? string_printf("%.1f %%", kPercent * count_at(i, i) / total) : std::string("n/a");
    put_text_right(image, recall, geo.origin.x + matrix + recall_w - kMargin, geo.origin.y + i * cell + cell / 2, scale,
                   kBlack);
  }
  cv::rectangle(image, cv::Rect(geo.origin.x, geo.origin.y, matrix, matrix), kAxisColor, 1);
  put_text(image, "cell shade: share of the row's test scans (green: right part, red: another part)", kMargin,
           height - kFooter / 2, kSmallTextScale, kAxisColor);
  if (layout != nullptr) *layout = geo;
  return image;
}

cv::Point2d PlotAxes::to_px(double x, double y) const {
  const double fx = x_max > x_min ? (x - x_min) / (x_max - x_min) : 0.0;
  double fy = 0.0;
  if (log_y) {
    const double lo = std::log10(y_min), hi = std::log10(y_max);
    fy = hi > lo && y > 0.0 ? (std::log10(y) - lo) / (hi - lo) : 0.0;
  } else {
    fy = y_max > y_min ? (y - y_min) / (y_max - y_min) : 0.0;
  }
  return {area.x + fx * (area.width - 1), area.y + (area.height - 1) * (1.0 - fy)};
}

namespace {

cv::Point px(const PlotAxes& axes, double x, double y) {
  const cv::Point2d p = axes.to_px(x, y);
  return {static_cast<int>(std::lround(p.x)), static_cast<int>(std::lround(p.y))};
}

// Horizontal then vertical segments: the value holds until the next step ("best so far").
void draw_steps(cv::Mat& image, const PlotAxes& axes, const std::vector<cv::Point2d>& points, const cv::Scalar& color,
                int thickness) {
  for (std::size_t i = 0; i + 1 < points.size(); ++i) {
    const cv::Point a = px(axes, points[i].x, points[i].y);
    const cv::Point corner = px(axes, points[i + 1].x, points[i].y);
    const cv::Point b = px(axes, points[i + 1].x, points[i + 1].y);
    cv::line(image, a, corner, color, thickness, cv::LINE_AA);
    cv::line(image, corner, b, color, thickness, cv::LINE_AA);
  }
}

void draw_x_axis(cv::Mat& image, const PlotAxes& axes, const std::vector<double>& ticks, bool labels) {
  const int bottom = axes.area.y + axes.area.height - 1;
  for (double t : ticks) {
    const int x = px(axes, t, axes.y_min).x;
    cv::line(image, {x, axes.area.y}, {x, bottom}, kGridColor, 1);
    cv::line(image, {x, bottom}, {x, bottom + 5}, kAxisColor, 1);
    if (labels) put_text_centered(image, tick_label(t), x, bottom + 16, kTextScale, kAxisColor);
  }
}

void draw_y_ticks(cv::Mat& image, const PlotAxes& axes, const std::vector<double>& ticks, bool right, bool grid,
                  const std::string& suffix) {
  const int side = right ? axes.area.x + axes.area.width - 1 : axes.area.x;
  for (double t : ticks) {
    const int y = px(axes, axes.x_min, t).y;
    if (grid) cv::line(image, {axes.area.x, y}, {axes.area.x + axes.area.width - 1, y}, kGridColor, 1);
    cv::line(image, {side, y}, {right ? side + 5 : side - 5, y}, kAxisColor, 1);
    if (right) {
      put_text(image, tick_label(t) + suffix, side + 8, y, kTextScale, kAxisColor);
    } else {
      put_text_right(image, tick_label(t) + suffix, side - 8, y, kTextScale, kAxisColor);
    }
  }
}

// A legend row: a sample mark and a label per entry, left to right from x at height y_mid.
struct LegendEntry {
  std::string label;
  cv::Scalar color;
  enum class Mark : std::uint8_t { kLine, kDot, kRing } mark;
};
void draw_legend(cv::Mat& image, const std::vector<LegendEntry>& entries, int x, int y_mid) {
  constexpr int kSample = 22, kGap = 8, kSpacing = 24;
  for (const LegendEntry& e : entries) {
    switch (e.mark) {
      case LegendEntry::Mark::kLine: cv::line(image, {x, y_mid}, {x + kSample, y_mid}, e.color, 2, cv::LINE_AA); break;
      case LegendEntry::Mark::kDot:
        cv::circle(image, {x + kSample / 2, y_mid}, 3, e.color, cv::FILLED, cv::LINE_AA);
        break;
      case LegendEntry::Mark::kRing: cv::circle(image, {x + kSample / 2, y_mid}, 3, e.color, 1, cv::LINE_AA); break;
    }
    put_text(image, e.label, x + kSample + kGap, y_mid, kTextScale, kBlack);
    x += kSample + kGap + text_size(e.label, kTextScale).width + kSpacing;
  }
}

}  // namespace

namespace {

// The annealing image: size, margins and the two panels' rows (pixels).
constexpr int kWidth = 1000, kHeight = 720, kLeft = 80, kRight = 80;
constexpr int kTopY = 62, kTopH = 380, kBottomY = 506, kBottomH = 150;

// The axes of both panels and their tick steps, from the curve.
struct AnnealingScales {
  AnnealingPlotLayout geo;
  std::vector<double> x_ticks;
  double y_step = 1.0;                      // accuracy ticks, %
  double decade_lo = 0.0, decade_hi = 1.0;  // temperature axis, log10
  double features_step = 1.0;
};

AnnealingScales annealing_scales(const std::vector<algo::AnnealingStep>& curve) {
  constexpr int kTargetTicks = 8;
  AnnealingScales scales;
  AnnealingPlotLayout& geo = scales.geo;
  // x: iterations, from 0 to the last step (at least 1 so a one-point curve has an axis).
  const double last = curve.empty() ? 1.0 : std::max(1.0, static_cast<double>(curve.back().iteration));
  const double x_step = nice_step(last, kTargetTicks);
  scales.x_ticks = ticks_between(0.0, last, x_step);

  // Accuracy panel in percent: from a round value below the lowest point to 100.
  double lo = kPercent;
  for (const algo::AnnealingStep& s : curve) {
    lo = std::min({lo, s.candidate_accuracy * kPercent, s.current_accuracy * kPercent, s.best_accuracy * kPercent});
  }
  lo = std::clamp(lo, 0.0, kPercent - 1.0);
  const double y_step = nice_step(kPercent - lo, 5);
  scales.y_step = y_step;
  double y_min = std::floor(lo / y_step) * y_step;
  if (lo - y_min < 0.02 * (kPercent - y_min)) y_min -= y_step;
  y_min = std::max(0.0, y_min);
  geo.accuracy = {cv::Rect(kLeft, kTopY, kWidth - kLeft - kRight, kTopH),
                  0.0,
                  last,
                  y_min,
                  kPercent + 0.03 * (kPercent - y_min),
                  false};

  // Temperature panel, log scale over whole decades.
  double t_lo = std::numeric_limits<double>::infinity(), t_hi = 0.0;
  int max_active = 1;
  for (const algo::AnnealingStep& s : curve) {
    if (s.temperature > 0.0) {
      t_lo = std::min(t_lo, s.temperature);
      t_hi = std::max(t_hi, s.temperature);
    }
    max_active = std::max(max_active, s.candidate_active);
  }
  if (!(t_hi > 0.0)) t_lo = t_hi = 1.0;
  double d_lo = std::floor(std::log10(t_lo)), d_hi = std::ceil(std::log10(t_hi));
  if (d_hi <= d_lo) d_hi = d_lo + 1.0;
  scales.decade_lo = d_lo;
  scales.decade_hi = d_hi;
  const cv::Rect bottom(kLeft, kBottomY, kWidth - kLeft - kRight, kBottomH);
  geo.temperature = {bottom, 0.0, last, std::pow(10.0, d_lo), std::pow(10.0, d_hi), true};
  const double f_step = nice_step(max_active, 4);
  scales.features_step = f_step;
  geo.features = {bottom, 0.0, last, 0.0, std::ceil((max_active + 1) / f_step) * f_step, false};  // headroom
  return scales;
}

// CV accuracy of every candidate with the current and best lines.
void draw_accuracy_panel(cv::Mat& image, const std::vector<algo::AnnealingStep>& curve, const AnnealingScales& scales) {
  // Accuracy panel.
  const PlotAxes& acc = scales.geo.accuracy;
  draw_x_axis(image, acc, scales.x_ticks, true);
  draw_y_ticks(image, acc, ticks_between(acc.y_min, kPercent, scales.y_step), false, true, "");
  put_text_vertical(image, "CV accuracy [%]", 18, acc.area.y + acc.area.height / 2 + 60, kTextScale, kBlack);
  draw_legend(image,
              {{"candidate (accepted)", kAcceptedPointColor, LegendEntry::Mark::kDot},
               {"candidate (rejected)", kRejectedPointColor, LegendEntry::Mark::kRing},
               {"current", kCurrentLineColor, LegendEntry::Mark::kLine},
               {"best so far", kBestLineColor, LegendEntry::Mark::kLine}},
              kLeft, kTopY - 14);
  std::vector<cv::Point2d> current, best;
  for (const algo::AnnealingStep& s : curve) {
    current.emplace_back(s.iteration, s.current_accuracy * kPercent);
    best.emplace_back(s.iteration, s.best_accuracy * kPercent);
  }
  // Current line under the candidates (an accepted candidate is the new current), best line on top.
  draw_steps(image, acc, current, kCurrentLineColor, 1);
  for (const algo::AnnealingStep& s : curve) {
    const cv::Point p = px(acc, s.iteration, s.candidate_accuracy * kPercent);
    if (s.accepted) {
      cv::circle(image, p, 3, kAcceptedPointColor, cv::FILLED, cv::LINE_AA);
    } else {
      cv::circle(image, p, 3, kRejectedPointColor, 1, cv::LINE_AA);
    }
  }
  draw_steps(image, acc, best, kBestLineColor, 2);
  cv::rectangle(image, acc.area, kAxisColor, 1);
  if (curve.empty()) {
    put_text_centered(image, "no annealing steps recorded", acc.area.x + acc.area.width / 2,
                      acc.area.y + acc.area.height / 2, kTitleScale, kAxisColor);
  }
}

// Temperature (log, left axis) and the active features of each candidate (right axis).
void draw_temperature_panel(cv::Mat& image, const std::vector<algo::AnnealingStep>& curve,
                            const AnnealingScales& scales) {
  // Temperature and active-feature panel.
  const AnnealingPlotLayout& geo = scales.geo;
  const PlotAxes& temp = geo.temperature;
  std::vector<cv::Point2d> temperature, active;
  for (const algo::AnnealingStep& s : curve) {
    temperature.emplace_back(s.iteration, s.temperature);
    active.emplace_back(s.iteration, s.candidate_active);
  }
  draw_x_axis(image, temp, scales.x_ticks, true);
  std::vector<double> decades;
  for (int d = static_cast<int>(scales.decade_lo); d <= static_cast<int>(scales.decade_hi); ++d)
    decades.push_back(std::pow(10.0, d));
  draw_y_ticks(image, temp, decades, false, true, "");
  draw_y_ticks(image, geo.features, ticks_between(0.0, geo.features.y_max, scales.features_step), true, false, "");
  put_text_vertical(image, "temperature", 18, temp.area.y + temp.area.height / 2 + 40, kTextScale, kBlack);
  put_text_vertical(image, "active features", kWidth - 14, temp.area.y + temp.area.height / 2 + 55, kTextScale, kBlack);
  draw_legend(image,
              {{"temperature (left, log scale)", kTemperatureLineColor, LegendEntry::Mark::kLine},
               {"active features of the candidate (right)", kFeaturesLineColor, LegendEntry::Mark::kLine}},
              kLeft, kBottomY - 14);
  draw_steps(image, geo.features, active, kFeaturesLineColor, 1);
  for (std::size_t i = 0; i + 1 < temperature.size(); ++i) {
    cv::line(image, px(temp, temperature[i].x, temperature[i].y), px(temp, temperature[i + 1].x, temperature[i + 1].y),
             kTemperatureLineColor, 2, cv::LINE_AA);
  }
  cv::rectangle(image, temp.area, kAxisColor, 1);
  put_text_centered(image, "annealing iteration (one candidate feature set per iteration)", kWidth / 2,
                    kBottomY + kBottomH + 40, kTextScale, kBlack);
}

}  // namespace

cv::Mat render_annealing_image(const algo::ClassifierReport& report, const std::string& title,
                               AnnealingPlotLayout* layout) {
  cv::Mat image(kHeight, kWidth, CV_8UC3, kWhite);
  put_text(image, title, 10, 22, kTitleScale, kBlack);
  const AnnealingScales scales = annealing_scales(report.curve);
  draw_accuracy_panel(image, report.curve, scales);
  draw_temperature_panel(image, report.curve, scales);
  if (layout != nullptr) *layout = scales.geo;
  return image;
}

}  // namespace cellsight::app
