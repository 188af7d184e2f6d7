// Closed-loop exposure from the laser line width: keeps the stripe width in a band as reflectivity changes
// (thesis 6.2: parts lose reflectivity after the first coat; the exposure follows the line width).
#pragma once

#include <cstdint>

#include "algo/result.hpp"
#include "algo/stripe.hpp"

namespace cellsight::algo {

struct ExposureParams {
  // Target band of the per-frame median StripeRow::width_px (width above background + threshold_dn).
  float width_min_px = 4.0f;
  float width_max_px = 7.0f;
  // Inner share of the band where the exposure is held (the dead band), centred in the band. Outside it the
  // controller aims at the band centre; inside it does nothing, so measurement noise cannot make it hunt.
  float dead_band_fraction = 0.5f;
  std::int32_t exposure_min_us = 20;
  std::int32_t exposure_max_us = 20000;
  // Largest change per frame, as a ratio (1.25: at most x1.25 or /1.25).
  float max_step_ratio = 1.25f;
  // Share of the model correction applied per frame, (0, 1]: 1 would jump to the target on the nominal plant,
  // smaller values trade speed for robustness to a wrong model (blooming, other sigma).
  float smoothing = 0.7f;
  // Stripe sigma of the plant model (see update()). Choose the LARGEST expected sigma: the loop gain is then
  // smoothing * (sigma / model_sigma)^2 <= smoothing, which converges without overshoot.
  float model_sigma_px = 1.6f;
  // More than this share of the valid rows saturated -> saturation-limited: a width above the band centre is
  // brought down to the lower edge of the dead band even though it is in the band (saturated centres are less
  // precise), and the exposure is not increased while the width is still in the band. Released below half of
  // this share (hysteresis) or when the width falls below the band.
  float max_saturated_fraction = 0.3f;
  // Fewer valid rows than this -> "no stripe seen".
  int min_valid_rows = 20;
  // No stripe: hold the exposure this many frames (a gap in the part, nothing in the laser yet), then probe
  // upward by probe_step_ratio per frame (a matt part too dark to be seen at all), up to exposure_max_us.
  int no_stripe_hold_frames = 10;
  float probe_step_ratio = 1.1f;
};

// Start-up check of the parameters; the message says which value is wrong.
[[nodiscard]] Status validate(const ExposureParams& params);

enum class ExposureAction : std::uint8_t {
  kHold = 0,             // width inside the dead band (saturation-limited: from the band bottom to its centre)
  kIncrease,             // width below the dead band
  kDecrease,             // width above the dead band
  kSaturationDecrease,   // width fine but too many saturated rows
  kNoStripeHold,         // no stripe: holding
  kProbe,                // no stripe for a while: probing upward
  kOverExposedDecrease,  // no usable stripe but many over-wide blobs: grossly over-exposed
};

[[nodiscard]] constexpr const char* to_string(ExposureAction action) {
  switch (action) {
    case ExposureAction::kHold: return "hold";
    case ExposureAction::kIncrease: return "increase";
    case ExposureAction::kDecrease: return "decrease";
    case ExposureAction::kSaturationDecrease: return "saturation decrease";
    case ExposureAction::kNoStripeHold: return "no stripe: hold";
    case ExposureAction::kProbe: return "no stripe: probe";
    case ExposureAction::kOverExposedDecrease: return "over-exposed: decrease";
  }
  return "unknown";
}

struct ExposureStep {
  std::int32_t exposure_us = 0;  // what to set for the next frame
  ExposureAction action = ExposureAction::kHold;
};

// Deterministic, allocation-free, one update per frame. The parameters must pass validate() (start-up).
//
// Plant model (the stripe of StripeRow::width_px): a Gaussian line of sigma s and peak A = k * exposure *
// reflectivity is w = 2 s sqrt(2 ln(A / T)) wide above the level T, so ln(exposure) = const + w^2 / (8 s^2).
// The update therefore works on ln(exposure): delta = smoothing * (w_target^2 - w^2) / (8 model_sigma^2),
// rate-limited to +-ln(max_step_ratio) per frame and applied to the last command. A camera applies a new exposure
// a frame or two late, so w is first predicted at the last command from the width measured at the exposure the
// frame was really taken with: w^2 += 8 model_sigma^2 ln(command / frame exposure) (a Smith predictor on the
// model). A change in flight is thus neither repeated (wind-up, overshoot) nor waited for.
class ExposureController {
 public:
  ExposureController(const ExposureParams& params, std::int32_t initial_exposure_us);

  // frame_exposure_us: the exposure of the frame `summary` comes from (drivers::Frame::exposure_us); <= 0 means
  // unknown, taken as the last command (no change in flight).
  [[nodiscard]] ExposureStep update(const StripeSummary& summary, std::int32_t frame_exposure_us);

  [[nodiscard]] std::int32_t exposure_us() const { return command_us_; }
  [[nodiscard]] bool saturation_limited() const { return saturation_limited_; }
  // Restart from a known exposure (new part type, operator change); clears the no-stripe and saturation state.
  void reset(std::int32_t exposure_us);

 private:
  [[nodiscard]] std::int32_t clamp_us(double exposure_us) const;

  ExposureParams params_;
  std::int32_t command_us_ = 0;
  int no_stripe_frames_ = 0;
  bool saturation_limited_ = false;
};

}  // namespace cellsight::algo
