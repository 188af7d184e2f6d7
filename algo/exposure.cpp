// Closed-loop exposure from the laser line width (thesis 6.2): log-domain model step, dead band, rate limit.
#include "algo/exposure.hpp"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <string>

namespace cellsight::algo {

namespace {

// Hysteresis of the saturation limit: released when the saturated share falls below this part of the limit.
constexpr float kSaturationReleaseShare = 0.5f;

}  // namespace

Status validate(const ExposureParams& p) {
  if (!(p.width_min_px > 0.0f) || !(p.width_max_px > p.width_min_px)) {
    return make_error("exposure: need 0 < width_min_px < width_max_px (got " + std::to_string(p.width_min_px) + ", " +
                      std::to_string(p.width_max_px) + ")");
  }
  if (!(p.dead_band_fraction >= 0.0f && p.dead_band_fraction < 1.0f)) {
    return make_error("exposure: dead_band_fraction must be in [0, 1) (got " + std::to_string(p.dead_band_fraction) +
                      ")");
  }
  if (p.exposure_min_us <= 0 || p.exposure_max_us < p.exposure_min_us) {
    return make_error("exposure: need 0 < exposure_min_us <= exposure_max_us (got " +
                      std::to_string(p.exposure_min_us) + ", " + std::to_string(p.exposure_max_us) + ")");
  }
  if (!(p.max_step_ratio > 1.0f) || !(p.probe_step_ratio >= 1.0f) || p.probe_step_ratio > p.max_step_ratio) {
    return make_error("exposure: need max_step_ratio > 1 and 1 <= probe_step_ratio <= max_step_ratio (got " +
                      std::to_string(p.max_step_ratio) + ", " + std::to_string(p.probe_step_ratio) + ")");
  }
  if (!(p.smoothing > 0.0f && p.smoothing <= 1.0f)) {
    return make_error("exposure: smoothing must be in (0, 1] (got " + std::to_string(p.smoothing) + ")");
  }
  if (!(p.model_sigma_px > 0.0f)) {
    return make_error("exposure: model_sigma_px must be > 0 (got " + std::to_string(p.model_sigma_px) + ")");
  }
  if (!(p.max_saturated_fraction > 0.0f && p.max_saturated_fraction <= 1.0f)) {
    return make_error("exposure: max_saturated_fraction must be in (0, 1] (got " +
                      std::to_string(p.max_saturated_fraction) + ")");
  }
  if (p.min_valid_rows < 1 || p.no_stripe_hold_frames < 0) {
    return make_error("exposure: need min_valid_rows >= 1 and no_stripe_hold_frames >= 0");
  }
  return {};
}

ExposureController::ExposureController(const ExposureParams& params, std::int32_t initial_exposure_us)
    : params_(params) {
  assert(validate(params).ok() && "ExposureParams must pass validate() at start-up");
  reset(initial_exposure_us);
}

void ExposureController::reset(std::int32_t exposure_us) {
  command_us_ = clamp_us(double(exposure_us));
  no_stripe_frames_ = 0;
  saturation_limited_ = false;
}

std::int32_t ExposureController::clamp_us(double exposure_us) const {
  const double lo = double(params_.exposure_min_us);
  const double hi = double(params_.exposure_max_us);
  const double v = std::isnan(exposure_us) ? lo : std::clamp(exposure_us, lo, hi);
  return std::int32_t(std::lround(v));
}

ExposureStep ExposureController::update(const StripeSummary& summary, std::int32_t frame_exposure_us) {
  const double max_step_log = std::log(double(params_.max_step_ratio));
  const double sigma2 = double(params_.model_sigma_px) * double(params_.model_sigma_px);
  const float measured = summary.median_width_px;
  const bool seen = summary.valid_rows >= params_.min_valid_rows && measured > 0.0f && std::isfinite(measured);

  if (!seen) {
    saturation_limited_ = false;
    if (summary.too_wide_rows >= params_.min_valid_rows) {
      // Nothing measurable but many blobs too wide to be a line: far over-exposed, come down at full rate.
      no_stripe_frames_ = 0;
      command_us_ = clamp_us(double(command_us_) / double(params_.max_step_ratio));
      return {command_us_, ExposureAction::kOverExposedDecrease};
    }
    // Holding first: between parts, or in a hole of the part, a jump upwards would over-expose the next stripe.
    if (no_stripe_frames_ < params_.no_stripe_hold_frames) {
      ++no_stripe_frames_;
      return {command_us_, ExposureAction::kNoStripeHold};
    }
    command_us_ = clamp_us(double(command_us_) * double(params_.probe_step_ratio));
    return {command_us_, ExposureAction::kProbe};
  }
  no_stripe_frames_ = 0;

  // The frame may predate the last command (the camera applies exposures a frame or two late). Predict the width
  // at the commanded exposure with the plant model, w^2 += 8 sigma^2 ln(command / frame), and decide on that:
  // a change in flight is neither repeated (wind-up) nor waited for (half speed per frame of delay).
  double width2 = double(measured) * measured;
  if (frame_exposure_us > 0) {
    const double frame_us = double(clamp_us(double(frame_exposure_us)));
    width2 += 8.0 * sigma2 * std::log(double(command_us_) / frame_us);
  }
  const float width = float(std::sqrt(std::max(width2, 0.0)));

  const float centre = 0.5f * (params_.width_min_px + params_.width_max_px);
  const float half_dead = 0.5f * params_.dead_band_fraction * (params_.width_max_px - params_.width_min_px);
  const float dead_lo = centre - half_dead;
  const float dead_hi = centre + half_dead;

  const float saturated = summary.saturated_fraction();
  if (saturated > params_.max_saturated_fraction) {
    saturation_limited_ = true;
  } else if (saturated < kSaturationReleaseShare * params_.max_saturated_fraction) {
    saturation_limited_ = false;
  }
  if (width < params_.width_min_px) {
    saturation_limited_ = false;  // the width band comes first: a line too thin is lost on darker parts
  }

  float target = centre;
  ExposureAction action = ExposureAction::kHold;
  if (saturation_limited_) {
    // Saturated: hold anywhere from the band's lower edge up to its centre; above the centre, aim at the lower
    // edge of the dead band (the gap between the two keeps the approach to a finite number of steps). Never
    // increase while limited, so the saturation limit and the band cannot push against each other.
    if (width > centre) {
      target = dead_lo;
      action = width > dead_hi ? ExposureAction::kDecrease : ExposureAction::kSaturationDecrease;
    }
  } else if (width < dead_lo) {
    action = ExposureAction::kIncrease;
  } else if (width > dead_hi) {
    action = ExposureAction::kDecrease;
  }
  if (action == ExposureAction::kHold) {
    return {command_us_, action};
  }

  // ln(exposure) = const + w^2 / (8 sigma^2) on the plant model (see header).
  double step_log = double(params_.smoothing) * (double(target) * target - double(width) * width) / (8.0 * sigma2);
  step_log = std::clamp(step_log, -max_step_log, max_step_log);
  command_us_ = clamp_us(double(command_us_) * std::exp(step_log));
  return {command_us_, action};
}

}  // namespace cellsight::algo
