// Scan builder: the per-frame streaming part of reconstruction.
#include "algo/scan_builder.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace cellsight::algo {

ScanBuilder::ScanBuilder(const ScanBuilderParams& params, const SensorCalibration& calibration)
    : params_(params),
      triangulator_(calibration),
      profile_(calibration.intrinsics.height_px),
      exposure_(params.exposure, params.exposure.exposure_min_us),
      scan_(params.max_points),
      column_v_(static_cast<std::size_t>(calibration.intrinsics.width_px), 0.0F),
      candidate_(static_cast<std::size_t>(calibration.intrinsics.height_px), 0),
      row_lo_(candidate_.size(), 0),
      row_hi_(candidate_.size(), -1) {}

void ScanBuilder::begin_pass(std::int64_t start_counts, std::int32_t exposure_us) {
  scan_.clear();
  stats_ = PassStats{};
  start_counts_ = start_counts;
  exposure_.reset(exposure_us);
}

FrameOutcome ScanBuilder::add_frame(const std::uint8_t* pixels, int width, int height, int stride,
                                    std::int32_t frame_exposure_us, std::int64_t encoder_counts) {
  FrameOutcome out;
  ++stats_.frames;
  out.stripe = extract_stripe(pixels, width, height, stride, params_.stripe, profile_);
  if (out.stripe != StripeResult::kOk) {
    out.exposure = {exposure_.exposure_us(), ExposureAction::kHold};
    return out;
  }
  const StripeSummary& summary = profile_.summary();
  out.exposure = exposure_.update(summary, frame_exposure_us);
  out.median_width_px = summary.median_width_px;
  if (summary.valid_rows >= params_.exposure.min_valid_rows) {
    ++stats_.frames_with_stripe;
    out.width_in_band = summary.median_width_px >= params_.exposure.width_min_px &&
                        summary.median_width_px <= params_.exposure.width_max_px;
    stats_.frames_in_band += out.width_in_band ? 1 : 0;
  }
  const double travel_m = triangulator_.travel_m(encoder_counts - start_counts_);
  // Group usable rows into runs of continuous centres; only runs long enough become points.
  auto usable = [&](int v) {
    const StripeStatus s = profile_.row(v).status;
    return s == StripeStatus::kValid || s == StripeStatus::kSaturated;
  };
  int run_start = -1;
  for (int v = 0; v <= profile_.rows(); ++v) {
    const bool continues =
        v < profile_.rows() && usable(v) && run_start >= 0 &&
        std::abs(profile_.row(v).centre_px - profile_.row(v - 1).centre_px) <= params_.run_continuity_px;
    if (continues) continue;
    if (run_start >= 0) emit_run(run_start, v - 1, travel_m, out);
    run_start = v < profile_.rows() && usable(v) ? v : -1;
  }
  column_pass(pixels, width, height, stride, travel_m, out);
  stats_.points = scan_.size();
  stats_.dropped_points = scan_.dropped();
  return out;
}

void ScanBuilder::emit_run(int first, int last, double travel_m, FrameOutcome& out) {
  const int length = last - first + 1;
  if (length < params_.min_run_rows) {
    stats_.short_run_rows += static_cast<std::size_t>(length);
    for (int v = first; v <= last; ++v) candidate_[static_cast<std::size_t>(v)] = 1;  // the column pass looks again
    return;
  }
  double peak_sum = 0.0;
  for (int v = first; v <= last; ++v) peak_sum += profile_.row(v).peak;
  const double taper_dn = params_.end_taper_ratio * peak_sum / length;
  while (first < last && profile_.row(first).peak < taper_dn) {
    ++first;
    ++stats_.tapered_rows;
  }
  while (last > first && profile_.row(last).peak < taper_dn) {
    --last;
    ++stats_.tapered_rows;
  }
  const auto frame_index = static_cast<std::uint16_t>(std::min(stats_.frames - 1, 65535));
  for (int v = first; v <= last; ++v) {
    const Eigen::Vector3f p =
        triangulator_.carrier_point(profile_.row(v).centre_px, v, travel_m, params_.carrier_start_offset_m);
    if (!std::isfinite(p.x())) continue;
    if (scan_.push({p.x(), p.y(), p.z(), frame_index, static_cast<std::uint16_t>(v)})) ++out.points_added;
  }
}

namespace {

constexpr double kMinColumnPeakShare = 0.15;  // as the row extractor's min_relative_strength
constexpr int kColumnWindowRows = 8;
constexpr float kColumnContinuityPx = 1.5F;
constexpr int kColumnMarginPx = 48;  // around a row's stripe centre, where its slanted piece can run

// The sub-pixel row of the line's crossing of column c within rows top..bottom of a band (first..last the band's
// candidate rows): a narrow peak well above the column's own background, its vertical centre of gravity. NaN when
// the column holds none.
float column_crossing_row(const std::uint8_t* pixels, int stride, int c, int top, int bottom, int first, int last,
                          double min_peak, int max_extent_rows) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  int best = top;
  for (int r = top; r <= bottom; ++r) {
    if (pixels[static_cast<std::size_t>(r) * stride + c] > pixels[static_cast<std::size_t>(best) * stride + c])
      best = r;
  }
  if (best < first - 2 || best > last + 2) return nan;  // the peak belongs to rows the row pass measured
  const double local_bg = std::min(pixels[static_cast<std::size_t>(top) * stride + c],
                                   pixels[static_cast<std::size_t>(bottom) * stride + c]);
  const double peak = pixels[static_cast<std::size_t>(best) * stride + c];
  if (peak - local_bg < min_peak) return nan;
  const double half = local_bg + 0.5 * (peak - local_bg);
  int lo = best, hi = best;
  while (lo > top && pixels[static_cast<std::size_t>(lo - 1) * stride + c] >= half) --lo;
  while (hi < bottom && pixels[static_cast<std::size_t>(hi + 1) * stride + c] >= half) ++hi;
  if (lo == top || hi == bottom || hi - lo + 1 > max_extent_rows) return nan;  // a blob, or cut off
  double sum = 0.0, weighted = 0.0;
  for (int r = std::max(top, lo - 2); r <= std::min(bottom, hi + 2); ++r) {
    const double value = std::max(0.0, pixels[static_cast<std::size_t>(r) * stride + c] - local_bg);
    sum += value;
    weighted += value * r;
  }
  return sum > 0.0 ? static_cast<float>(weighted / sum) : nan;
}

}  // namespace

void ScanBuilder::column_pass(const std::uint8_t* pixels, int width, int height, int stride, double travel_m,
                              FrameOutcome& out) {
  if (width != static_cast<int>(column_v_.size()) || height != static_cast<int>(candidate_.size())) return;
  const double min_peak = column_min_peak();
  select_column_rows(pixels, width, stride, min_peak);

  // Each band: candidate rows +-window. In every column of a band, a narrow peak well above the column's own
  // background is a crossing of the line; its vertical centre of gravity is the sub-pixel row.
  int v = 0;
  while (v < height) {
    if (candidate_[static_cast<std::size_t>(v)] == 0) {
      ++v;
      continue;
    }
    int band_last = v;
    while (band_last + 1 < height &&
           (candidate_[static_cast<std::size_t>(band_last) + 1] != 0 ||
            (band_last + 1 < height - 1 && candidate_[static_cast<std::size_t>(band_last) + 2] != 0))) {
      ++band_last;
    }
    const int top = std::max(0, v - kColumnWindowRows), bottom = std::min(height - 1, band_last + kColumnWindowRows);
    int c_lo = width, c_hi = -1;
    for (int r = v; r <= band_last; ++r) {
      if (candidate_[static_cast<std::size_t>(r)] == 0) continue;
      c_lo = std::min<int>(c_lo, row_lo_[static_cast<std::size_t>(r)]);
      c_hi = std::max<int>(c_hi, row_hi_[static_cast<std::size_t>(r)]);
    }
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int c = std::max(0, c_lo); c <= std::min(width - 1, c_hi + 1); ++c)
      column_v_[static_cast<std::size_t>(c)] = nan;
    for (int c = c_lo; c <= c_hi; ++c) {
      column_v_[static_cast<std::size_t>(c)] =
          column_crossing_row(pixels, stride, c, top, bottom, v, band_last, min_peak, params_.max_column_extent_rows);
    }
    emit_column_runs(c_lo, c_hi, width, travel_m, out);
    v = band_last + 1;
  }
  std::fill(candidate_.begin(), candidate_.end(), 0);
}

double ScanBuilder::column_min_peak() const {
  double peak_sum = 0.0;
  int peak_rows = 0;
  for (int v = 0; v < profile_.rows(); ++v) {
    const StripeRow& row = profile_.row(v);
    if (row.status == StripeStatus::kValid || row.status == StripeStatus::kSaturated) {
      peak_sum += row.peak;
      ++peak_rows;
    }
  }
  const double typical_peak = peak_rows > 0 ? peak_sum / peak_rows : 0.0;
  return std::max<double>(params_.stripe.threshold_dn, kMinColumnPeakShare * typical_peak);
}

void ScanBuilder::select_column_rows(const std::uint8_t* pixels, int width, int stride, double min_peak) {
  // Rows the row pass could not measure well: a stripe wider than a row profile should be, rows that only held
  // short broken runs (a line slanting more than ~60 deg from vertical changes column by > 2 px per row), and
  // bright rows with no accepted stripe (a line along the row, rejected as too wide). The rows emit_run marked in
  // candidate_ keep their range from the row centre.
  for (int v = 0; v < profile_.rows(); ++v) {
    const StripeRow& row = profile_.row(v);
    const bool usable = row.status == StripeStatus::kValid || row.status == StripeStatus::kSaturated;
    int lo = width, hi = -1;
    if ((usable && row.width_px > params_.wide_row_px) || candidate_[static_cast<std::size_t>(v)] != 0) {
      lo = static_cast<int>(row.centre_px) - kColumnMarginPx;
      hi = static_cast<int>(row.centre_px) + kColumnMarginPx;
    } else if (row.status == StripeStatus::kNoStripe && row.peak >= 2.0 * min_peak) {
      // Bright but rejected (a line along the row is "too wide"): where is the light?
      const std::uint8_t* line = pixels + static_cast<std::size_t>(v) * static_cast<std::size_t>(stride);
      const double half = 0.5 * row.peak;
      for (int c = 0; c < width; ++c) {
        if (line[c] >= half) {
          lo = std::min(lo, c);
          hi = c;
        }
      }
      if (hi - lo < params_.min_column_run) hi = -1;  // a spike or a hot pixel: nothing to re-read
    }
    row_lo_[static_cast<std::size_t>(v)] = static_cast<std::int16_t>(std::clamp(lo, 0, width));
    row_hi_[static_cast<std::size_t>(v)] = static_cast<std::int16_t>(std::clamp(hi, -1, width - 1));
    candidate_[static_cast<std::size_t>(v)] = hi >= lo ? 1 : 0;
  }
}

void ScanBuilder::emit_column_runs(int c_lo, int c_hi, int width, double travel_m, FrameOutcome& out) {
  // Runs of columns whose rows continue smoothly become points; isolated columns (glints) do not.
  const auto frame_index = static_cast<std::uint16_t>(std::min(stats_.frames - 1, 65535));
  const float nan = std::numeric_limits<float>::quiet_NaN();
  int run_start = -1;
  for (int c = std::max(0, c_lo); c <= std::min(width, c_hi + 1); ++c) {
    const float here = c < width ? column_v_[static_cast<std::size_t>(c)] : nan;
    const bool continues = run_start >= 0 && !std::isnan(here) &&
                           std::abs(here - column_v_[static_cast<std::size_t>(c - 1)]) <= kColumnContinuityPx;
    if (continues) continue;
    if (run_start >= 0 && c - run_start >= params_.min_column_run) {
      for (int k = run_start; k < c; ++k) {
        const float vk = column_v_[static_cast<std::size_t>(k)];
        Eigen::Vector3f p = triangulator_.cell_point(static_cast<float>(k), vk);
        p.x() -= static_cast<float>(travel_m - params_.carrier_start_offset_m);
        if (!std::isfinite(p.x())) continue;
        if (scan_.push({p.x(), p.y(), p.z(), frame_index, static_cast<std::uint16_t>(std::lround(vk))})) {
          ++out.points_added;
          ++stats_.column_points;
        }
      }
    }
    run_start = std::isnan(here) ? -1 : c;
  }
}

}  // namespace cellsight::algo
