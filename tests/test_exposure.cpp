// Tests of algo/exposure against an analytic stripe plant, and in closed loop with the real stripe extractor.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <random>
#include <vector>

#include "algo/exposure.hpp"
#include "algo/stripe.hpp"

namespace {

using cellsight::algo::ExposureAction;
using cellsight::algo::ExposureController;
using cellsight::algo::ExposureParams;
using cellsight::algo::ExposureStep;
using cellsight::algo::StripeSummary;

// The cell as the controller sees it: for an exposure and a surface reflectivity, the StripeSummary the
// extractor would report. Every row that sees the part has a Gaussian line of peak A = k * exposure *
// reflectivity * (row factor: surface angle, log-normal), and the extractor's width above the threshold T is
// w = 2 sigma sqrt(2 ln(A / T)); clipping at 255 leaves the flanks (hence w) alone, blooming widens sigma.
struct Plant {
  double gain_dn_per_us = 0.4;
  double threshold_dn = 16.0;
  double sigma_px = 1.2;
  double bloom_per_efold = 0.15;  // sigma *= 1 + this * ln(A / 255) above saturation
  int rows = 768;
  int part_rows = 600;           // the others see no part
  double row_spread = 0.3;       // sd of ln(row factor)
  double width_noise_px = 0.15;  // per-row measurement noise
  std::vector<double> row_factor;

  explicit Plant(std::uint32_t seed) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> n01(0.0, 1.0);
    for (int r = 0; r < part_rows; ++r) {
      row_factor.push_back(std::exp(row_spread * n01(rng)));
    }
  }

  [[nodiscard]] double width_px(double peak_dn) const {
    const double sigma = sigma_px * (1.0 + bloom_per_efold * std::log(std::max(1.0, peak_dn / 255.0)));
    return 2.0 * sigma * std::sqrt(2.0 * std::log(peak_dn / threshold_dn));
  }

  // Exposure that puts the MEDIAN row at width w (row factor 1, no blooming below saturation).
  [[nodiscard]] double exposure_for_width(double w, double reflectivity) const {
    return threshold_dn * std::exp(w * w / (8.0 * sigma_px * sigma_px)) / (gain_dn_per_us * reflectivity);
  }

  StripeSummary observe(double exposure_us, double reflectivity, std::mt19937& rng,
                        double frame_jitter_px = 0.0) const {
    std::normal_distribution<double> n01(0.0, 1.0);
    StripeSummary s;
    s.rows = rows;
    std::vector<float> widths;
    for (double f : row_factor) {
      const double peak = gain_dn_per_us * exposure_us * reflectivity * f;
      if (peak <= threshold_dn * 1.05) {
        continue;  // too dark to be detected
      }
      widths.push_back(float(width_px(peak) + width_noise_px * n01(rng) + frame_jitter_px));
      s.saturated_rows += peak >= 255.0 ? 1 : 0;
    }
    s.valid_rows = int(widths.size());
    if (!widths.empty()) {
      std::sort(widths.begin(), widths.end());
      const std::size_t n = widths.size();
      s.median_width_px = n % 2 == 1 ? widths[n / 2] : 0.5f * (widths[n / 2 - 1] + widths[n / 2]);
    }
    return s;
  }
};

bool in_band(const ExposureParams& p, float w) {
  return w >= p.width_min_px && w <= p.width_max_px;
}

// Runs the loop. reflectivity(frame); the camera applies a command `delay` frames late and reports the exposure
// each frame was really taken with. Returns per frame the median width seen and the exposure used.
struct Trace {
  std::vector<float> width;
  std::vector<double> exposure_us;
  std::vector<ExposureAction> action;
};

template <class Reflectivity>
Trace simulate(const Plant& plant, const ExposureParams& params, std::int32_t start_us, int frames,
               Reflectivity reflectivity, int delay = 0, double jitter_px = 0.0, std::uint32_t seed = 1) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  ExposureController ctl(params, start_us);
  std::vector<std::int32_t> commands(std::size_t(delay) + 1, ctl.exposure_us());
  Trace t;
  for (int k = 0; k < frames; ++k) {
    const std::int32_t used = commands.front();  // the exposure this frame is really taken with
    const StripeSummary s = plant.observe(used, reflectivity(k), rng, jitter_px * n01(rng));
    const ExposureStep step = ctl.update(s, used);
    t.width.push_back(s.valid_rows > 0 ? s.median_width_px : 0.0f);
    t.exposure_us.push_back(used);
    t.action.push_back(step.action);
    commands.erase(commands.begin());
    commands.push_back(step.exposure_us);
  }
  return t;
}

int first_in_band_from(const Trace& t, const ExposureParams& p, int from) {
  for (int k = from; k < int(t.width.size()); ++k) {
    if (in_band(p, t.width[std::size_t(k)])) {
      return k;
    }
  }
  return -1;
}

int count_in_band(const Trace& t, const ExposureParams& p, int from, int to) {
  int n = 0;
  for (int k = from; k < to; ++k) {
    n += in_band(p, t.width[std::size_t(k)]) ? 1 : 0;
  }
  return n;
}

// Sign changes of the exposure's frame-to-frame direction (ignoring frames without a change).
int direction_changes(const Trace& t, int from) {
  int changes = 0, last = 0;
  for (std::size_t k = std::size_t(from) + 1; k < t.exposure_us.size(); ++k) {
    const double d = t.exposure_us[k] - t.exposure_us[k - 1];
    const int dir = d > 0 ? 1 : (d < 0 ? -1 : 0);
    if (dir != 0) {
      changes += (last != 0 && dir != last) ? 1 : 0;
      last = dir;
    }
  }
  return changes;
}

int frames_to_cover(double ratio, double step_ratio) {
  return int(std::ceil(std::log(ratio) / std::log(step_ratio)));
}

}  // namespace

SCENARIO("the controller brings the width into the band from far below and from far above", "[exposure]") {
  const ExposureParams params;
  const Plant plant(11);
  const double centre = 0.5 * (params.width_min_px + params.width_max_px);
  GIVEN("a matt part (reflectivity 0.15) at the shortest exposure: no stripe visible at all") {
    const double refl = 0.15;
    const Trace t = simulate(plant, params, params.exposure_min_us, 300, [&](int) { return refl; });
    THEN("after holding it probes upward, then steps into the band, and stays there") {
      // Budget: the hold, probing until the brightest rows (factor ~e^(2.5 * 0.3)) pass 1.05 T, model steps to
      // the band centre at most x max_step_ratio per frame, plus 10 frames for the smoothed final approach.
      const double visible_us =
          plant.threshold_dn * 1.05 / (plant.gain_dn_per_us * refl * std::exp(2.5 * plant.row_spread));
      const int budget =
          params.no_stripe_hold_frames + frames_to_cover(visible_us / params.exposure_min_us, params.probe_step_ratio) +
          frames_to_cover(plant.exposure_for_width(centre, refl) / visible_us, params.max_step_ratio) + 10;
      const int first = first_in_band_from(t, params, 0);
      INFO("in band at frame " << first << ", budget " << budget);
      REQUIRE(first >= 0);
      CHECK(first <= budget);
      CHECK(count_in_band(t, params, first, 300) == 300 - first);
      CHECK(t.action[0] == ExposureAction::kNoStripeHold);
      CHECK(t.action[std::size_t(params.no_stripe_hold_frames)] == ExposureAction::kProbe);
    }
  }
  GIVEN("bare metal (reflectivity 0.9) at the longest exposure: a wide, saturated, blooming line") {
    const double refl = 0.9;
    const Trace t = simulate(plant, params, params.exposure_max_us, 300, [&](int) { return refl; });
    THEN("it comes down at the rate limit into the band and stays there") {
      const int budget =
          frames_to_cover(params.exposure_max_us / plant.exposure_for_width(centre, refl), params.max_step_ratio) + 10;
      const int first = first_in_band_from(t, params, 0);
      INFO("start width " << t.width[0] << ", in band at frame " << first << ", budget " << budget);
      REQUIRE(t.width[0] > params.width_max_px);
      REQUIRE(first >= 0);
      CHECK(first <= budget);
      CHECK(count_in_band(t, params, first, 300) == 300 - first);
      CHECK(direction_changes(t, 0) == 0);  // monotone: no overshoot
    }
  }
}

SCENARIO("a camera that applies exposures late neither winds the loop up nor slows it down", "[exposure]") {
  GIVEN("a fast loop (x2 per frame, sigma 1.6 = the model sigma) and exposures applied 2 frames late") {
    ExposureParams params;
    params.max_step_ratio = 2.0f;
    Plant plant(16);
    plant.sigma_px = 1.6;
    const double refl = 0.3;
    const double centre = 0.5 * (params.width_min_px + params.width_max_px);
    for (const double start_width : {2.5, 9.0}) {
      const auto start_us = std::int32_t(plant.exposure_for_width(start_width, refl));
      const Trace t = simulate(
          plant, params, start_us, 120, [&](int) { return refl; }, 2, 0.0, 3);
      THEN("from a width of " << start_width
                              << " px the approach is monotone, reaches the band within the "
                                 "rate-limit budget + the delay, and stays") {
        // Without predicting the in-flight change, each of the 2 stale frames would repeat the step: the
        // exposure overshoots and has to turn back.
        const int first = first_in_band_from(t, params, 0);
        const double ratio = plant.exposure_for_width(centre, refl) / start_us;
        const int budget = frames_to_cover(std::max(ratio, 1.0 / ratio), params.max_step_ratio) + 2 + 4;
        INFO("in band at " << first << ", budget " << budget);
        REQUIRE(first >= 0);
        CHECK(first <= budget);
        CHECK(direction_changes(t, 0) == 0);
        CHECK(count_in_band(t, params, first, 120) == 120 - first);
      }
    }
  }
}

SCENARIO("a coating change mid-run is followed within a few frames", "[exposure]") {
  const ExposureParams params;
  const Plant plant(12);
  const int frames = 900, change = 300;
  auto coat = [&](int k) { return k < change ? 0.9 : 0.15; };  // bare metal -> first matt coat
  for (const int delay : {0, 1, 2}) {
    GIVEN("reflectivity 0.9 -> 0.15 at frame 300, the camera applying exposures " << delay << " frame(s) late") {
      const Trace t = simulate(plant, params, 1000, frames, coat, delay, 0.1, 77);
      THEN("the width is back in the band within 6 frames + the delay, and in band >= 95 % of all frames") {
        // ln(0.9 / 0.15) = 1.79 to recover; at the rate limit ln 1.25 per frame that would be 8 frames, but only
        // w >= width_min is needed: w^2 must regain 8 sigma^2 ln 6 - (5.5^2 - 4^2) -> 3 steps, + slack.
        const int back = first_in_band_from(t, params, change);
        INFO("dropped to " << t.width[std::size_t(change)] << ", back in band at " << back);
        REQUIRE_FALSE(in_band(params, t.width[std::size_t(change)]));
        REQUIRE(back >= 0);
        CHECK(back - change <= 6 + delay);
        const int inside = count_in_band(t, params, 0, frames);
        INFO("in band " << inside << " of " << frames);
        CHECK(inside >= int(0.95 * frames));
        CHECK(count_in_band(t, params, back, frames) == frames - back);
      }
    }
  }
}

SCENARIO("once in the band the exposure does not hunt", "[exposure]") {
  const ExposureParams params;
  const Plant plant(13);
  GIVEN("a steady part seen with per-row noise only, the camera applying exposures a frame late") {
    const Trace t = simulate(
        plant, params, 200, 400, [](int) { return 0.5; }, 1, 0.0, 98);
    const int first = first_in_band_from(t, params, 0);
    REQUIRE(first >= 0);
    THEN("from the first frame in the band the exposure never turns back and settles for good") {
      CHECK(direction_changes(t, first) == 0);
      int changes = 0;
      for (std::size_t k = std::size_t(first) + 1; k < t.exposure_us.size(); ++k) {
        changes += t.exposure_us[k] != t.exposure_us[k - 1] ? 1 : 0;
      }
      INFO("exposure changes after entering the band: " << changes);
      CHECK(changes <= 3);  // the last steps into the dead band, then nothing
    }
  }
  GIVEN("a steady part whose median width also jitters 0.2 px rms from frame to frame (geometry)") {
    const Trace t = simulate(
        plant, params, 2000, 700, [](int) { return 0.5; }, 1, 0.2, 99);
    const int first = first_in_band_from(t, params, 0);
    REQUIRE(first >= 0);
    REQUIRE(first < 50);
    THEN("over 650 frames the direction changes at most 3 times and the width stays in the band") {
      // The dead band is +-0.75 px: a 0.2 px jitter leaves it (> 3.75 sigma from the centre) only by chance,
      // and each such step is undone at most once. A limit cycle would change direction every few frames.
      const int changes = direction_changes(t, 50);
      INFO("direction changes " << changes);
      CHECK(changes <= 3);
      CHECK(count_in_band(t, params, 50, 700) >= int(0.99 * 650));
    }
  }
}

SCENARIO("many saturated rows reduce the exposure even with the width in the band", "[exposure]") {
  GIVEN("a sharp line (sigma 0.8) whose width is in the upper half of the band only when most rows saturate") {
    ExposureParams params;
    Plant plant(14);
    plant.sigma_px = 0.8;
    plant.bloom_per_efold = 0.0;
    plant.gain_dn_per_us = 4.0;  // a bright laser: the start below stays inside the exposure limits
    const double refl = 0.5;
    const auto start_us = std::int32_t(plant.exposure_for_width(5.9, refl));  // inside the dead band
    REQUIRE(start_us < params.exposure_max_us);
    WHEN("the saturation limit is active (default 30 %)") {
      const Trace t = simulate(plant, params, start_us, 200, [&](int) { return refl; });
      THEN("it steps down to the lower half of the band, never leaves the band, and then holds") {
        REQUIRE(in_band(params, t.width[0]));
        CHECK(t.action[0] == ExposureAction::kSaturationDecrease);
        CHECK(t.exposure_us.back() < 0.5 * start_us);
        const double centre = 0.5 * (params.width_min_px + params.width_max_px);
        CHECK(t.width.back() <= centre);
        CHECK(count_in_band(t, params, 0, 200) == 200);
        CHECK(direction_changes(t, 0) == 0);
        CHECK(t.exposure_us[100] == t.exposure_us.back());
      }
    }
    WHEN("the limit is disabled (max_saturated_fraction = 1)") {
      params.max_saturated_fraction = 1.0f;
      const Trace t = simulate(plant, params, start_us, 50, [&](int) { return refl; });
      THEN("the same start is simply held") {
        CHECK(t.exposure_us.back() == start_us);
      }
    }
  }
}

SCENARIO("without a stripe the controller holds then probes upward slowly and over-wide blobs bring it down",
         "[exposure]") {
  const ExposureParams params;
  GIVEN("frames with no valid row at all") {
    ExposureController ctl(params, 1000);
    const StripeSummary empty{768, 0, 0, 0, 0, 0.0f};
    THEN("the exposure is held for no_stripe_hold_frames frames, then grows by probe_step_ratio per frame") {
      for (int k = 0; k < params.no_stripe_hold_frames; ++k) {
        const ExposureStep s = ctl.update(empty, 1000);
        CHECK(s.exposure_us == 1000);
        CHECK(s.action == ExposureAction::kNoStripeHold);
      }
      double expected = 1000.0;
      for (int k = 0; k < 200; ++k) {
        const ExposureStep s = ctl.update(empty, ctl.exposure_us());
        expected = std::min(double(params.exposure_max_us), expected * params.probe_step_ratio);
        CHECK(s.action == ExposureAction::kProbe);
        CHECK(std::abs(s.exposure_us - expected) <= 1.0 + 1e-3 * expected);  // rounding to whole us per step
      }
      CHECK(ctl.exposure_us() == params.exposure_max_us);
    }
  }
  GIVEN("frames where every candidate was rejected as too wide (grossly over-exposed)") {
    ExposureController ctl(params, 8000);
    const StripeSummary blobs{768, 0, 0, 0, 500, 0.0f};
    THEN("the exposure comes down at the full rate") {
      const ExposureStep s = ctl.update(blobs, 8000);
      CHECK(s.action == ExposureAction::kOverExposedDecrease);
      CHECK(s.exposure_us == std::lround(8000 / params.max_step_ratio));
    }
  }
}

SCENARIO("the exposure never leaves its limits nor exceeds the step limit whatever it is fed", "[exposure]") {
  GIVEN("10000 frames of random and degenerate summaries (NaN, negative, huge widths, random counts)") {
    ExposureParams params;
    params.exposure_min_us = 50;
    params.exposure_max_us = 5000;
    ExposureController ctl(params, 100000);  // out of range on purpose: clamped
    REQUIRE(ctl.exposure_us() == params.exposure_max_us);
    std::mt19937 rng(2024);
    std::uniform_real_distribution<float> u01(0.0f, 1.0f);
    std::int32_t last = ctl.exposure_us();
    bool ok = true;
    for (int k = 0; k < 10000; ++k) {
      StripeSummary s;
      s.rows = 768;
      s.valid_rows = int(768 * u01(rng));
      s.saturated_rows = int(float(s.valid_rows) * u01(rng));
      s.too_wide_rows = u01(rng) < 0.1f ? 700 : 0;
      const float pick = u01(rng);
      s.median_width_px =
          pick < 0.05f ? std::nanf("") : (pick < 0.1f ? -3.0f : (pick < 0.15f ? 1e9f : 15.0f * u01(rng)));
      // The frame exposure is sometimes the last command, sometimes stale or garbage (<= 0: unknown).
      const float f = u01(rng);
      const std::int32_t frame_us = f < 0.7f ? last : (f < 0.9f ? std::int32_t(20000 * u01(rng)) : -5);
      const ExposureStep step = ctl.update(s, frame_us);
      const bool in_limits = step.exposure_us >= params.exposure_min_us && step.exposure_us <= params.exposure_max_us;
      // Rate limit: every command is within one step of the previous one (+- 0.5 us of rounding).
      const double step_max = double(last) * params.max_step_ratio + 0.5;
      const double step_min = double(last) / params.max_step_ratio - 0.5;
      const bool rate_ok = step.exposure_us <= step_max && step.exposure_us >= step_min;
      if (!in_limits || !rate_ok) {
        INFO("frame " << k << " exposure " << step.exposure_us << " frame " << frame_us << " last " << last
                      << " action " << cellsight::algo::to_string(step.action));
        CHECK(in_limits);
        CHECK(rate_ok);
        ok = false;
        break;
      }
      last = step.exposure_us;
    }
    THEN("every command was inside [min, max] and within one step of the previous command") {
      CHECK(ok);
    }
  }
}

SCENARIO("the controller is deterministic and its parameters are validated", "[exposure]") {
  GIVEN("two controllers fed the same frames") {
    const ExposureParams params;
    const Plant plant(15);
    const Trace a = simulate(
        plant, params, 300, 200, [](int k) { return k < 100 ? 0.9 : 0.2; }, 1, 0.2, 5);
    const Trace b = simulate(
        plant, params, 300, 200, [](int k) { return k < 100 ? 0.9 : 0.2; }, 1, 0.2, 5);
    THEN("they command identical exposures") {
      CHECK(a.exposure_us == b.exposure_us);
    }
  }
  GIVEN("parameter sets") {
    THEN("the defaults pass and each broken value is named in the error") {
      CHECK(cellsight::algo::validate(ExposureParams{}).ok());
      ExposureParams p;
      p.width_max_px = p.width_min_px;
      auto st = cellsight::algo::validate(p);
      REQUIRE_FALSE(st.ok());
      CHECK_THAT(st.error().message, Catch::Contains("width_max_px"));
      p = ExposureParams{};
      p.max_step_ratio = 1.0f;
      st = cellsight::algo::validate(p);
      REQUIRE_FALSE(st.ok());
      CHECK_THAT(st.error().message, Catch::Contains("max_step_ratio"));
      p = ExposureParams{};
      p.exposure_min_us = 0;
      CHECK_FALSE(cellsight::algo::validate(p).ok());
      p = ExposureParams{};
      p.smoothing = 1.5f;
      CHECK_FALSE(cellsight::algo::validate(p).ok());
    }
  }
}

// ---- closed loop with the real extractor ----------------------------------------------------------------------

namespace {

// Renders a frame of the analytic cell: a slanted Gaussian line (point-sampled), ambient light, read and shot
// noise, clipping at 255 with blooming, empty rows above and below the part, and occasional hot pixels.
void render_frame(std::vector<std::uint8_t>& img, int width, int height, double peak_dn, std::mt19937& rng) {
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  for (int r = 0; r < height; ++r) {
    std::uint8_t* row = img.data() + std::size_t(r) * width;
    const bool part = r >= height / 10 && r < height - height / 10;
    // Surface angle varies along the part: +-40 % brightness.
    const double a = peak_dn * (1.0 + 0.4 * std::sin(0.05 * r));
    const double sigma = 1.2 * (1.0 + 0.15 * std::log(std::max(1.0, a / 255.0)));
    const double c = 0.3 * width + 0.2 * r;
    for (int x = 0; x < width; ++x) {
      double v = 6.0;
      if (part) {
        const double d = (x - c) / sigma;
        v += a * std::exp(-0.5 * d * d);
      }
      v += std::sqrt(4.0 + std::max(0.0, v) / 16.0) * n01(rng);
      row[x] = std::uint8_t(std::clamp(std::lround(v), 0L, 255L));
    }
    if (u01(rng) < 0.02) {
      row[std::size_t(u01(rng) * (width - 1))] = 255;
    }
  }
}

}  // namespace

SCENARIO("closed loop with the real extractor holds the width in the band across a coating change", "[exposure]") {
  GIVEN("a rendered part, bare metal (0.9) for 80 frames then matt coat (0.15) for 120, a 1-frame exposure delay") {
    const int width = 256, height = 200, frames = 200, change = 80;
    const double gain_dn_per_us = 0.4;
    ExposureParams params;
    params.min_valid_rows = 20;
    const cellsight::algo::StripeParams stripe_params;
    cellsight::algo::StripeProfile profile(height);
    ExposureController ctl(params, 800);
    std::vector<std::uint8_t> img(std::size_t(width) * height);
    std::mt19937 rng(4242);
    std::int32_t applied = ctl.exposure_us(), pending = applied;
    int inside = 0, out_after_change = 0;
    for (int k = 0; k < frames; ++k) {
      const double refl = k < change ? 0.9 : 0.15;
      render_frame(img, width, height, gain_dn_per_us * applied * refl, rng);
      REQUIRE(cellsight::algo::extract_stripe(img.data(), width, height, width, stripe_params, profile) ==
              cellsight::algo::StripeResult::kOk);
      const StripeSummary& s = profile.summary();
      const bool ok = s.valid_rows >= params.min_valid_rows && in_band(params, s.median_width_px);
      inside += ok ? 1 : 0;
      out_after_change += (!ok && k >= change) ? 1 : 0;
      const ExposureStep step = ctl.update(s, applied);
      applied = pending;  // the camera takes the new value one frame late
      pending = step.exposure_us;
    }
    THEN(">= 95 % of the frames have their median width in the band; the change costs only a few frames") {
      INFO("in band " << inside << " of " << frames << ", out after the change " << out_after_change);
      CHECK(inside >= int(0.95 * frames));
      CHECK(out_after_change <= 8);
    }
  }
}
