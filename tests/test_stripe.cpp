// Tests of algo/stripe against analytic Gaussian stripes with known sub-pixel centres and widths.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <cstring>
#include <numbers>
#include <random>
#include <vector>

#include "algo/stripe.hpp"
#include "tests/support/alloc_counter.hpp"

namespace {

using cellsight::algo::extract_stripe;
using cellsight::algo::StripeKernel;
using cellsight::algo::StripeParams;
using cellsight::algo::StripeProfile;
using cellsight::algo::StripeResult;
using cellsight::algo::StripeRow;
using cellsight::algo::StripeStatus;

// How the test renders a stripe into a pixel: the Gaussian's value at the pixel centre, or its mean over the
// pixel's area (what a sensor with 100 % fill factor integrates).
enum class Sampling { kPoint, kArea };

struct Line {
  double centre_px;
  double sigma_px;
  double amplitude_dn;  // peak of the continuous Gaussian, before clipping at 255
};

double line_dn(double x, const Line& l, Sampling s) {
  if (s == Sampling::kPoint) {
    const double d = (x - l.centre_px) / l.sigma_px;
    return l.amplitude_dn * std::exp(-0.5 * d * d);
  }
  const double k = 1.0 / (l.sigma_px * std::sqrt(2.0));
  return l.amplitude_dn * l.sigma_px * std::sqrt(std::numbers::pi / 2.0) *
         (std::erf((x + 0.5 - l.centre_px) * k) - std::erf((x - 0.5 - l.centre_px) * k));
}

struct Noise {
  double read_dn = 0.0;          // Gaussian read noise
  double shot_dn2_per_dn = 0.0;  // shot noise variance per DN of signal
};

// One row: background + sum of lines (+ noise), rounded to the nearest DN and clipped like an 8-bit sensor.
void render_row(std::uint8_t* row, int width, double background_dn, const std::vector<Line>& lines, Sampling s,
                const Noise& noise = {}, std::mt19937* rng = nullptr) {
  std::normal_distribution<double> n01(0.0, 1.0);
  for (int x = 0; x < width; ++x) {
    double v = background_dn;
    for (const Line& l : lines) {
      v += line_dn(double(x), l, s);
    }
    if (rng != nullptr) {
      const double var = noise.read_dn * noise.read_dn + noise.shot_dn2_per_dn * std::max(0.0, v);
      v += std::sqrt(var) * n01(*rng);
    }
    row[x] = std::uint8_t(std::clamp(std::lround(v), 0L, 255L));
  }
}

struct Image {
  int width = 0, height = 0, stride = 0;
  std::vector<std::uint8_t> pixels;
  Image(int w, int h, int pad = 0) : width(w), height(h), stride(w + pad), pixels(std::size_t(h) * (w + pad), 0) {}
  std::uint8_t* row(int r) { return pixels.data() + std::size_t(r) * stride; }
};

StripeResult run(const Image& img, const StripeParams& params, StripeProfile& out,
                 StripeKernel kernel = StripeKernel::kBest) {
  return extract_stripe(img.pixels.data(), img.width, img.height, img.stride, params, out, kernel);
}

// Width above `level` of a continuous line profile, by bisection on each flank (independent of the extractor).
double analytic_width(const Line& l, Sampling s, double level) {
  auto crossing = [&](double dir) {
    double in = l.centre_px, out = l.centre_px + dir * 20.0 * l.sigma_px;
    for (int i = 0; i < 80; ++i) {
      const double m = 0.5 * (in + out);
      (line_dn(m, l, s) > level ? in : out) = m;
    }
    return 0.5 * (in + out);
  };
  return crossing(+1.0) - crossing(-1.0);
}

bool usable(const StripeRow& r) {
  return r.status == StripeStatus::kValid || r.status == StripeStatus::kSaturated;
}

constexpr int kWidth = 256;
constexpr double kBackgroundDn = 6.0;

}  // namespace

SCENARIO("noise-free Gaussian stripes are located to 0.02 px", "[stripe]") {
  const Sampling sampling = GENERATE(Sampling::kPoint, Sampling::kArea);
  GIVEN("rows with one unsaturated Gaussian, sigma 0.8-1.6 px, peaks 100-240 DN, every 0.05 px of offset") {
    const StripeParams params;
    {
      std::vector<Line> truth;
      for (double sigma : {0.8, 1.0, 1.2, 1.6}) {
        for (double amp : {100.0, 170.0, 240.0}) {
          for (int k = 0; k <= 20; ++k) {
            truth.push_back({100.0 + 0.05 * k, sigma, amp});
          }
        }
      }
      Image img(kWidth, int(truth.size()));
      for (int r = 0; r < img.height; ++r) {
        render_row(img.row(r), img.width, kBackgroundDn, {truth[std::size_t(r)]}, sampling);
      }
      StripeProfile profile(img.height);
      WHEN("the stripe is extracted") {
        REQUIRE(run(img, params, profile) == StripeResult::kOk);
        THEN("every row is valid and its centre is within 0.02 px of the truth") {
          // Budget: the estimator's own bias on unquantised analytic rows is <= 0.015 px (measured while choosing
          // it, see extract_centre); 8-bit rounding adds a few thousandths at these amplitudes.
          double max_err = 0.0;
          for (int r = 0; r < img.height; ++r) {
            const StripeRow& row = profile.row(r);
            INFO("row " << r << " sigma " << truth[std::size_t(r)].sigma_px << " amp "
                        << truth[std::size_t(r)].amplitude_dn);
            REQUIRE(row.status == StripeStatus::kValid);
            max_err = std::max(max_err, std::fabs(row.centre_px - truth[std::size_t(r)].centre_px));
          }
          INFO("sampling " << (sampling == Sampling::kPoint ? "point" : "area") << " max error " << max_err);
          CHECK(max_err <= 0.02);
        }
        THEN("the width matches the analytic width above background + threshold") {
          // Point sampling: log(Gaussian) is a parabola; the chord between the samples around each crossing sags by
          // at most 1/(8 sigma^2) in log units, and its slope is at least (w/2 - 1/2)/sigma^2: the crossing moves
          // inward by <= 1/(4(w - 1)) per edge, 1/(2(w - 1)) in all.
          // Area sampling is not exactly log-parabolic; its truth is the continuous profile's crossing
          // (bisection), and 0.1 px more is allowed for that. Plus 0.05 px for rounding to whole DN.
          for (int r = 0; r < img.height; ++r) {
            const Line& l = truth[std::size_t(r)];
            const double w_true =
                sampling == Sampling::kPoint
                    ? 2.0 * l.sigma_px * std::sqrt(2.0 * std::log(l.amplitude_dn / params.threshold_dn))
                    : analytic_width(l, sampling, params.threshold_dn);
            const double bound = 1.0 / (2.0 * (w_true - 1.0)) + 0.05 + (sampling == Sampling::kArea ? 0.1 : 0.0);
            INFO("row " << r << " sigma " << l.sigma_px << " amp " << l.amplitude_dn << " w_true " << w_true);
            CHECK(std::fabs(profile.row(r).width_px - w_true) <= bound);
          }
        }
      }
    }
  }
}

SCENARIO("stripes a few DN above the threshold are still found", "[stripe]") {
  GIVEN("wide, weak Gaussians: peaks 20-24 DN over the background (threshold 16), sigma 1.2-1.6 px") {
    const StripeParams params;
    std::vector<Line> truth;
    for (double sigma : {1.2, 1.6}) {
      for (double amp : {20.0, 24.0}) {
        for (int k = 0; k <= 10; ++k) {
          truth.push_back({100.0 + 0.1 * k, sigma, amp});
        }
      }
    }
    Image img(kWidth, int(truth.size()));
    for (int r = 0; r < img.height; ++r) {
      render_row(img.row(r), img.width, kBackgroundDn, {truth[std::size_t(r)]}, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("every row is valid and within 0.1 px: the local background is not raised by the stripe's own light") {
      // A background taken over the stripe's own 16-px chunk would rise by A sigma sqrt(2 pi) / 16 (up to 5 DN
      // here) and lift the threshold above these peaks; the median over 5 chunks does not see the stripe.
      // With 4-8 DN of signal above the threshold, 8-bit rounding alone moves the centre by a few 0.01 px.
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r << " sigma " << truth[std::size_t(r)].sigma_px << " amp "
                    << truth[std::size_t(r)].amplitude_dn);
        REQUIRE(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(truth[std::size_t(r)].centre_px).margin(0.1));
      }
    }
  }
}

SCENARIO("the width grows monotonically with exposure and is insensitive to the centre offset", "[stripe]") {
  GIVEN("one sigma and peaks rising from 30 DN to 20x saturation (clipped at 255)") {
    StripeParams params;
    params.min_relative_strength = 0.0f;  // this frame spans peaks 30 to 5200 DN on purpose
    std::vector<double> amps;
    for (double a = 30.0; a < 5200.0; a *= 1.15) {
      amps.push_back(a);
    }
    Image img(kWidth, int(amps.size()));
    for (int r = 0; r < img.height; ++r) {
      render_row(img.row(r), img.width, kBackgroundDn, {{120.3, 1.2, amps[std::size_t(r)]}}, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("each 15 % step of peak widens the line, as 2 sigma sqrt(2 ln(A/T)) predicts") {
      for (int r = 1; r < img.height; ++r) {
        INFO("amp " << amps[std::size_t(r)]);
        CHECK(profile.row(r).width_px > profile.row(r - 1).width_px);
      }
    }
    THEN("rows reaching 255 are flagged saturated and still measured") {
      for (int r = 0; r < img.height; ++r) {
        const bool clipped = *std::max_element(img.row(r), img.row(r) + img.width) == 255;
        INFO("amp " << amps[std::size_t(r)]);
        CHECK(profile.row(r).status == (clipped ? StripeStatus::kSaturated : StripeStatus::kValid));
      }
    }
  }
}

SCENARIO("saturated stripes are flagged and located to 0.2 px", "[stripe]") {
  const Sampling sampling = GENERATE(Sampling::kPoint, Sampling::kArea);
  GIVEN("Gaussians of 1.6x to 40x the clip level, sigma 0.8-1.6, both samplings") {
    const StripeParams params;
    {
      std::vector<Line> truth;
      for (double sigma : {0.8, 1.2, 1.6}) {
        for (double amp : {400.0, 1000.0, 3000.0, 10000.0}) {
          for (int k = 0; k <= 20; ++k) {
            truth.push_back({90.0 + 0.05 * k, sigma, amp});
          }
        }
      }
      Image img(kWidth, int(truth.size()));
      for (int r = 0; r < img.height; ++r) {
        render_row(img.row(r), img.width, kBackgroundDn, {truth[std::size_t(r)]}, sampling);
      }
      StripeProfile profile(img.height);
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("status is saturated, the centre error stays within 0.2 px and the width follows the unclipped flanks") {
        // A clipped stripe tends to a box, whose sampled centre is only known to a fraction of a pixel: measured
        // worst case 0.17 px at sigma 0.8 and 40x saturation. Flanks below 255 are not clipped, so the
        // width above threshold keeps its analytic value (same bound as unsaturated).
        double max_err = 0.0;
        for (int r = 0; r < img.height; ++r) {
          const Line& l = truth[std::size_t(r)];
          const StripeRow& row = profile.row(r);
          INFO("row " << r << " sigma " << l.sigma_px << " amp " << l.amplitude_dn);
          REQUIRE(row.status == StripeStatus::kSaturated);
          CHECK(row.peak == 255);
          max_err = std::max(max_err, std::fabs(row.centre_px - l.centre_px));
          const double w_true = analytic_width(l, sampling, params.threshold_dn);
          CHECK(std::fabs(row.width_px - w_true) <=
                1.0 / (2.0 * (w_true - 1.0)) + 0.05 + (sampling == Sampling::kArea ? 0.1 : 0.0));
        }
        INFO("max error " << max_err);
        CHECK(max_err <= 0.2);
        CHECK(profile.summary().saturated_rows == img.height);
        CHECK(profile.summary().valid_rows == img.height);
      }
    }
  }
}

SCENARIO("with realistic sensor noise the centre error stays within 0.1 px", "[stripe]") {
  GIVEN("a seeded frame: ambient 4-10 DN, read noise 1.5-2 DN, shot noise, sigma 0.8-1.6, peaks 80-220 DN") {
    std::mt19937 rng(20240611);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    const StripeParams params;
    Image img(1024, 768);
    std::vector<Line> truth(std::size_t(img.height));
    for (int r = 0; r < img.height; ++r) {
      const double ambient = 4.0 + 6.0 * u01(rng);
      const Noise noise{1.5 + 0.5 * u01(rng), 1.0 / 16.0};
      truth[std::size_t(r)] = {200.0 + 600.0 * u01(rng), 0.8 + 0.8 * u01(rng), 80.0 + 140.0 * u01(rng)};
      render_row(img.row(r), img.width, ambient, {truth[std::size_t(r)]},
                 r % 2 == 0 ? Sampling::kPoint : Sampling::kArea, noise, &rng);
    }
    StripeProfile profile(img.height);
    WHEN("the stripe is extracted") {
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("all rows are usable, the rms error is <= 0.04 px, 99 % are within 0.1 px and all within 0.2 px") {
        // Propagated noise of the CoG: sigma_n sqrt(sum (x - c)^2) / sum(I - b). The weakest rows (peak 80,
        // sigma 1.6, ~2.3 DN of read + shot noise, window +-4 px) give ~0.05 px rms, the brightest (220 DN)
        // ~0.02: 0.1 px is 2 sigma of the worst rows, 0.2 px is 4 sigma.
        double sum2 = 0.0, max_err = 0.0;
        int within = 0;
        for (int r = 0; r < img.height; ++r) {
          const StripeRow& row = profile.row(r);
          REQUIRE(usable(row));  // a noise peak may touch 255 on the brightest rows: flagged, still measured
          const double e = row.centre_px - truth[std::size_t(r)].centre_px;
          sum2 += e * e;
          max_err = std::max(max_err, std::fabs(e));
          within += std::fabs(e) <= 0.1 ? 1 : 0;
        }
        const double rms = std::sqrt(sum2 / img.height);
        INFO("rms " << rms << " max " << max_err << " within 0.1 px: " << within);
        CHECK(rms <= 0.04);
        CHECK(within >= int(0.99 * img.height));
        CHECK(max_err <= 0.2);
      }
    }
  }
}

SCENARIO("empty rows and hot pixels and blobs and the image border give no stripe", "[stripe]") {
  const StripeParams params;
  std::mt19937 rng(7);
  const Noise noise{2.0, 0.0};
  Image img(kWidth, 6);
  GIVEN(
      "rows of background noise, a lone hot pixel, two hot pixels far apart, a broad ambient blob, and stripes "
      "cut by the left and right image borders") {
    render_row(img.row(0), img.width, kBackgroundDn, {}, Sampling::kPoint, noise, &rng);
    render_row(img.row(1), img.width, kBackgroundDn, {}, Sampling::kPoint, noise, &rng);
    img.row(1)[77] = 255;
    render_row(img.row(2), img.width, kBackgroundDn, {}, Sampling::kPoint, noise, &rng);
    img.row(2)[30] = 200;
    img.row(2)[180] = 90;
    render_row(img.row(3), img.width, kBackgroundDn, {{128.0, 20.0, 100.0}}, Sampling::kPoint, noise, &rng);
    render_row(img.row(4), img.width, kBackgroundDn, {{0.4, 1.2, 200.0}}, Sampling::kPoint, noise, &rng);
    render_row(img.row(5), img.width, kBackgroundDn, {{kWidth - 1.3, 1.2, 200.0}}, Sampling::kPoint, noise, &rng);
    StripeProfile profile(img.height);
    WHEN("the stripe is extracted") {
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("every row reports no stripe with a NaN centre and zero width") {
        for (int r = 0; r < img.height; ++r) {
          INFO("row " << r);
          CHECK(profile.row(r).status == StripeStatus::kNoStripe);
          CHECK(std::isnan(profile.row(r).centre_px));
          CHECK(profile.row(r).width_px == 0.0f);
        }
        CHECK(profile.summary().valid_rows == 0);
        CHECK(profile.summary().median_width_px == 0.0f);
      }
      THEN("the broad blob (FWHM 47 px > max_width_px) is counted as too wide, evidence of over-exposure") {
        CHECK(profile.summary().too_wide_rows == 1);
      }
      THEN("the hot-pixel row still reports its maximum as the peak") {
        CHECK(profile.row(1).peak == 255);
      }
    }
  }
}

SCENARIO("a stripe just wider than max_width_px is rejected as too wide, one just narrower is kept", "[stripe]") {
  // The width test is on the FWHM. A Gaussian's is 2 sqrt(2 ln 2) sigma; linear interpolation between point samples
  // at half maximum reads a sigma-3 line within 0.05 px of it, far inside the 3 % (0.21 px) either side used here.
  constexpr double kSigmaPx = 3.0;
  const double fwhm_px = 2.0 * std::sqrt(2.0 * std::log(2.0)) * kSigmaPx;
  Image img(kWidth, 8);
  for (int r = 0; r < img.height; ++r) {
    render_row(img.row(r), img.width, kBackgroundDn, {{120.0 + 0.3 * r, kSigmaPx, 150.0}}, Sampling::kPoint);
  }
  for (const double max_width_share : {0.97, 1.03}) {
    const bool too_wide = max_width_share < 1.0;
    GIVEN("max_width_px " << (too_wide ? "3 % below" : "3 % above") << " the stripe's FWHM") {
      StripeParams params;
      params.max_width_px = float(max_width_share * fwhm_px);
      StripeProfile profile(img.height);
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("every row " << (too_wide ? "has no stripe and counts as too wide (evidence of over-exposure)"
                                     : "keeps its stripe at the true centre")) {
        for (int r = 0; r < img.height; ++r) {
          INFO("row " << r);
          CHECK(profile.row(r).status == (too_wide ? StripeStatus::kNoStripe : StripeStatus::kValid));
          if (!too_wide) CHECK(profile.row(r).centre_px == Approx(120.0 + 0.3 * r).margin(0.03));
        }
        CHECK(profile.summary().valid_rows == (too_wide ? 0 : img.height));
        CHECK(profile.summary().too_wide_rows == (too_wide ? img.height : 0));
      }
    }
  }
}

SCENARIO("a hot pixel or a specular spike does not displace the stripe", "[stripe]") {
  const StripeParams params;
  GIVEN("a weak stripe (peak 60 DN) with a saturated hot pixel elsewhere in the row") {
    Image img(kWidth, 1);
    render_row(img.row(0), img.width, kBackgroundDn, {{150.25, 1.0, 60.0}}, Sampling::kPoint);
    img.row(0)[40] = 255;
    StripeProfile profile(1);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the stripe is chosen: the 1-px spike fails the minimum width") {
      CHECK(profile.row(0).status == StripeStatus::kValid);
      CHECK(profile.row(0).centre_px == Approx(150.25).margin(0.03));
    }
  }
  GIVEN("a continuous stripe and, for three rows, a brighter saturated 3-px specular blob 40 px beside it") {
    Image img(kWidth, 40);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines{{100.0 + 0.2 * r, 1.2, 150.0}};
      if (r >= 20 && r < 23) {
        lines.push_back({140.0 + 0.2 * r, 0.9, 2000.0});
      }
      render_row(img.row(r), img.width, kBackgroundDn, lines, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the blob is a double peak settled by continuity: every row keeps the stripe") {
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(100.0 + 0.2 * r).margin(0.03));
      }
    }
  }
}

SCENARIO("ghost reflections and second surfaces are resolved by continuity", "[stripe]") {
  const StripeParams params;
  GIVEN("a slanted stripe with a weak ghost (30 % of its peak) 20 px beside it in every row") {
    Image img(kWidth, 60);
    for (int r = 0; r < img.height; ++r) {
      render_row(img.row(r), img.width, kBackgroundDn, {{80.0 + 0.3 * r, 1.2, 200.0}, {100.0 + 0.3 * r, 1.2, 60.0}},
                 Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the ghost is below the double-peak ratio and ignored, even in the first row") {
      for (int r = 0; r < img.height; ++r) {
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(80.0 + 0.3 * r).margin(0.03));
      }
    }
  }
  GIVEN("a stripe whose strong ghost (80 % of its peak) runs 15 px to the side over rows 30-59") {
    Image img(kWidth, 100);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines{{120.0 - 0.25 * r, 1.2, 200.0}};
      if (r >= 30 && r < 60) {
        lines.push_back({135.0 - 0.25 * r, 1.4, 160.0});
      }
      render_row(img.row(r), img.width, kBackgroundDn, lines, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("every ghost row keeps the stripe that continues from the rows above") {
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(120.0 - 0.25 * r).margin(0.03));
      }
      CHECK(profile.summary().ambiguous_rows == 0);
    }
  }
  GIVEN("two equally bright stripes in rows 0-19 of which only one continues below") {
    Image img(kWidth, 80);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines{{150.0 + 0.1 * r, 1.2, 200.0}};
      if (r < 20) {
        lines.push_back({120.0, 1.2, 200.0});
      }
      render_row(img.row(r), img.width, kBackgroundDn, lines, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the top rows have no reference above, so the backward pass settles them from below") {
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(150.0 + 0.1 * r).margin(0.03));
      }
    }
  }
  GIVEN("a plate stripe and a flange stripe at a grazing angle, both real, the flange appearing at row 10") {
    Image img(kWidth, 70);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines{{100.0 + 0.2 * r, 1.2, 150.0}};
      if (r >= 10) {
        lines.push_back({200.0 - 0.5 * (r - 10), 1.4, 220.0});  // brighter than the plate
      }
      render_row(img.row(r), img.width, kBackgroundDn, lines, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the profile follows the surface it started on, although the flange is brighter") {
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(100.0 + 0.2 * r).margin(0.03));
      }
    }
  }
  GIVEN("two equally bright stripes 30 px apart in every row") {
    Image img(kWidth, 20);
    for (int r = 0; r < img.height; ++r) {
      render_row(img.row(r), img.width, kBackgroundDn, {{100.0, 1.2, 200.0}, {130.0, 1.2, 200.0}}, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("no row can be decided: all are ambiguous and carry both candidates") {
      for (int r = 0; r < img.height; ++r) {
        const StripeRow& row = profile.row(r);
        CHECK(row.status == StripeStatus::kAmbiguous);
        const double lo = std::min(row.centre_px, row.alt_centre_px);
        const double hi = std::max(row.centre_px, row.alt_centre_px);
        CHECK(lo == Approx(100.0).margin(0.03));
        CHECK(hi == Approx(130.0).margin(0.03));
      }
      CHECK(profile.summary().ambiguous_rows == img.height);
      CHECK(profile.summary().valid_rows == 0);
    }
  }
  GIVEN("a stripe that jumps 50 px at a depth step, with no second candidate") {
    Image img(kWidth, 20);
    for (int r = 0; r < img.height; ++r) {
      render_row(img.row(r), img.width, kBackgroundDn, {{r < 10 ? 100.0 : 150.0, 1.2, 200.0}}, Sampling::kPoint);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("continuity only settles double peaks: a lone stripe is accepted wherever it is") {
      for (int r = 0; r < img.height; ++r) {
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(r < 10 ? 100.0 : 150.0).margin(0.03));
      }
    }
  }
}

SCENARIO("the background is taken locally so an ambient gradient does not bias the width", "[stripe]") {
  GIVEN("ambient light ramping from 4 DN at the left to 44 DN at the right, stripes on the bright side") {
    const StripeParams params;
    Image img(1024, 21);
    std::vector<Line> truth;
    for (int r = 0; r < img.height; ++r) {
      truth.push_back({900.0 + 0.05 * r, 1.2, 150.0});
      render_row(img.row(r), img.width, 0.0, {truth.back()}, Sampling::kPoint);
      for (int x = 0; x < img.width; ++x) {
        img.row(r)[x] = std::uint8_t(std::min(255L, img.row(r)[x] + std::lround(4.0 + 40.0 * x / 1023.0)));
      }
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("centre and width are those of the stripe over its own background (~39 DN, row mean ~24 DN)") {
      const double w_true = 2.0 * 1.2 * std::sqrt(2.0 * std::log(150.0 / params.threshold_dn));
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        CHECK(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(truth[std::size_t(r)].centre_px).margin(0.03));
        // The local estimate still sees a ramp of 0.04 DN/px over the 128 px of background it averages.
        CHECK(std::fabs(profile.row(r).width_px - w_true) <= 1.0 / (2.0 * (w_true - 1.0)) + 0.15);
      }
    }
  }
}

SCENARIO("a stripe on an ambient-lit surface is measured against that surface", "[stripe]") {
  GIVEN("rows where columns 300-699 are a lit part surface (+30 DN, noisy) carrying the stripe near its edge") {
    const StripeParams params;
    std::mt19937 rng(17);
    Image img(1024, 40);
    std::vector<Line> truth;
    for (int r = 0; r < img.height; ++r) {
      truth.push_back({330.0 + 0.1 * r, 1.2, 180.0});
      render_row(img.row(r), img.width, 0.0, {truth.back()}, Sampling::kPoint);
      std::normal_distribution<double> n01(0.0, 1.0);
      for (int x = 0; x < img.width; ++x) {
        const double ambient = (x >= 300 && x < 700) ? 36.0 : 6.0;
        const double v = img.row(r)[x] + ambient;
        img.row(r)[x] = std::uint8_t(std::clamp(std::lround(v + std::sqrt(3.2 + v / 4.0) * n01(rng)), 0L, 255L));
      }
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN(
        "no row drowns in runs from the lit surface: all are valid, centred, and as wide as over a dark "
        "background") {
      // A row-wide threshold (mean ~20 DN + 16) would sit below the surface's noise peaks (36 + 3 sigma),
      // flooding the run list; the chunk thresholds sit on the surface. Noise here is ~4 DN at the flanks.
      const double w_true = 2.0 * 1.2 * std::sqrt(2.0 * std::log(180.0 / params.threshold_dn));
      double mean_width = 0.0;
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        REQUIRE(profile.row(r).status == StripeStatus::kValid);
        CHECK(profile.row(r).centre_px == Approx(truth[std::size_t(r)].centre_px).margin(0.15));
        mean_width += profile.row(r).width_px / img.height;
      }
      INFO("mean width " << mean_width << " analytic " << w_true);
      CHECK(std::fabs(mean_width - w_true) <= 1.0 / (2.0 * (w_true - 1.0)) + 0.1);
    }
  }
}

SCENARIO("ambient-lit carrier members are not taken for the laser in rows it does not reach", "[stripe]") {
  GIVEN("a frame whose upper rows hold only a lit strap (6 px, +22 DN) and whose lower rows hold the laser") {
    Image img(512, 60);
    std::mt19937 rng(23);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines;
      if (r >= 20) {
        lines.push_back({250.0, 1.2, 240.0});
      }
      render_row(img.row(r), img.width, 6.0, lines, Sampling::kPoint, Noise{1.8, 0.25}, &rng);
      for (int x = 100; x < 106; ++x) {
        img.row(r)[x] = std::uint8_t(std::min(255, img.row(r)[x] + 22));
      }
    }
    WHEN("the frame-relative strength test is on (default)") {
      const StripeParams params;
      StripeProfile profile(img.height);
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("the strap rows have no stripe and the laser rows keep theirs") {
        for (int r = 0; r < img.height; ++r) {
          INFO("row " << r);
          if (r < 20) {
            CHECK(profile.row(r).status == StripeStatus::kNoStripe);
          } else {
            CHECK(usable(profile.row(r)));  // shot noise may touch 255 at the peak
            CHECK(profile.row(r).centre_px == Approx(250.0).margin(0.1));
          }
        }
      }
    }
    WHEN("it is switched off") {
      StripeParams params;
      params.min_relative_strength = 0.0f;
      StripeProfile profile(img.height);
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      THEN("the strap passes for a dim 6-px stripe: this is what the test guards against") {
        int strap_rows = 0;
        for (int r = 0; r < 20; ++r) {
          strap_rows += usable(profile.row(r)) ? 1 : 0;
        }
        CHECK(strap_rows == 20);
      }
    }
  }
}

SCENARIO("the summary counts rows and takes the median width of the usable rows", "[stripe]") {
  GIVEN("a frame with valid, saturated, empty and ambiguous rows of many widths") {
    const StripeParams params;
    std::mt19937 rng(99);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    Image img(512, 301);
    for (int r = 0; r < img.height; ++r) {
      std::vector<Line> lines;
      const int kind = r % 10;
      if (kind < 6) {
        lines.push_back({250.0 + 20.0 * u01(rng), 0.8 + 0.8 * u01(rng), 30.0 + 200.0 * u01(rng)});
      } else if (kind < 8) {
        lines.push_back({250.0 + 20.0 * u01(rng), 0.8 + 0.8 * u01(rng), 300.0 + 3000.0 * u01(rng)});
      } else if (kind == 8) {
        lines.push_back({100.0, 1.0, 200.0});
        lines.push_back({400.0, 1.0, 200.0});
      }
      render_row(img.row(r), img.width, kBackgroundDn, lines, Sampling::kArea, Noise{1.5, 1.0 / 16.0}, &rng);
    }
    StripeProfile profile(img.height);
    REQUIRE(run(img, params, profile) == StripeResult::kOk);
    THEN("the counts agree with a recount of the row statuses and the median with a full sort") {
      int valid = 0, saturated = 0, ambiguous = 0;
      std::vector<float> widths;
      for (const StripeRow& row : profile.row_data()) {
        valid += usable(row) ? 1 : 0;
        saturated += row.status == StripeStatus::kSaturated ? 1 : 0;
        ambiguous += row.status == StripeStatus::kAmbiguous ? 1 : 0;
        if (usable(row)) {
          widths.push_back(row.width_px);
        }
      }
      std::sort(widths.begin(), widths.end());
      const std::size_t n = widths.size();
      REQUIRE(n > 0);
      const float median = n % 2 == 1 ? widths[n / 2] : 0.5f * (widths[n / 2 - 1] + widths[n / 2]);
      const auto& s = profile.summary();
      CHECK(s.rows == img.height);
      CHECK(s.valid_rows == valid);
      CHECK(s.saturated_rows == saturated);
      CHECK(s.ambiguous_rows == ambiguous);
      CHECK(s.median_width_px == median);
      CHECK(s.saturated_fraction() == Approx(double(saturated) / valid));
      AND_THEN("the row kinds were recognised as rendered: 6 in 10 valid, 2 saturated, 1 ambiguous, 1 empty") {
        CHECK(valid - saturated == 181);
        CHECK(saturated == 60);
        CHECK(ambiguous == 30);
      }
    }
  }
}

SCENARIO("the vector kernels give exactly the scalar result", "[stripe]") {
  if (!cellsight::algo::stripe_has_simd()) {
    WARN("no vector kernel in this build; the comparison is trivial");
  }
  std::mt19937 rng(31337);
  std::uniform_int_distribution<int> byte(0, 255);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const StripeParams params;
  for (const int width : {3, 15, 16, 17, 63, 64, 65, 100, 1000, 1023, 1024, 1030}) {
    for (int variant = 0; variant < 4; ++variant) {
      Image img(width, 40, variant);  // strides wider than the row
      for (int r = 0; r < img.height; ++r) {
        std::uint8_t* row = img.row(r);
        if (variant == 0) {  // uniform random bytes: many runs, run-list overflow, merged windows
          for (int x = 0; x < img.stride; ++x) {
            row[x] = std::uint8_t(byte(rng));
          }
        } else if (variant == 1) {  // realistic: noise, stripes, ghosts, hot pixels
          std::vector<Line> lines{{width * u01(rng), 0.8 + 0.8 * u01(rng), 20.0 + 2000.0 * u01(rng)}};
          if (u01(rng) < 0.5) {
            lines.push_back({width * u01(rng), 1.0 + u01(rng), 20.0 + 300.0 * u01(rng)});
          }
          render_row(row, width, 4.0 + 6.0 * u01(rng), lines, Sampling::kPoint, Noise{2.0, 1.0 / 16.0}, &rng);
          if (u01(rng) < 0.3) {
            row[std::size_t(byte(rng)) % std::size_t(width)] = 255;
          }
        } else if (variant == 2) {  // sparse spikes of every level on a flat background
          for (int x = 0; x < width; ++x) {
            row[x] = u01(rng) < 0.05 ? std::uint8_t(byte(rng)) : std::uint8_t(6);
          }
        } else {  // constant rows, from black to white
          std::memset(row, r * 255 / (img.height - 1), std::size_t(width));
        }
      }
      StripeProfile vec(img.height), ref(img.height);
      REQUIRE(run(img, params, vec, StripeKernel::kBest) == StripeResult::kOk);
      REQUIRE(run(img, params, ref, StripeKernel::kScalar) == StripeResult::kOk);
      INFO("width " << width << " variant " << variant);
      for (int r = 0; r < img.height; ++r) {
        INFO("row " << r);
        // Bitwise, NaN included: both kernels feed the same scalar measurement with the same integers.
        CHECK(std::memcmp(&vec.row(r), &ref.row(r), sizeof(StripeRow)) == 0);
      }
      CHECK(std::memcmp(&vec.summary(), &ref.summary(), sizeof(cellsight::algo::StripeSummary)) == 0);
    }
  }
}

SCENARIO("extract_stripe validates its input and allocates nothing", "[stripe]") {
  const StripeParams params;
  Image img(1024, 768);
  std::mt19937 rng(5);
  for (int r = 0; r < img.height; ++r) {
    std::vector<Line> lines{{300.0 + 0.3 * r, 1.2, 300.0}};
    if (r >= 10) {
      lines.push_back({330.0 + 0.3 * r, 1.2, 200.0});  // a strong ghost: every row below needs continuity
    }
    render_row(img.row(r), img.width, 6.0, lines, Sampling::kPoint, Noise{2.0, 1.0 / 16.0}, &rng);
  }
  GIVEN("a profile reserved for 768 rows at start-up") {
    StripeProfile profile(768);
    THEN("a full frame is extracted without a single heap allocation") {
      long allocations = 0;
      StripeResult result{};
      {
        const cellsight::test::AllocationWindow window;  // proves extract_stripe() allocates nothing
        result = run(img, params, profile);
        allocations = window.count();
      }
      REQUIRE(result == StripeResult::kOk);
      CHECK(allocations == 0);
      CHECK(profile.rows() == 768);
      CHECK(profile.summary().valid_rows == 768);  // the ghost is settled by continuity in every row
    }
    THEN("bad images are refused and leave the profile empty") {
      REQUIRE(run(img, params, profile) == StripeResult::kOk);
      CHECK(extract_stripe(nullptr, 1024, 768, 1024, params, profile) == StripeResult::kInvalidImage);
      CHECK(profile.rows() == 0);
      CHECK(extract_stripe(img.pixels.data(), 2, 768, 1024, params, profile) == StripeResult::kInvalidImage);
      CHECK(extract_stripe(img.pixels.data(), 1024, 768, 1000, params, profile) == StripeResult::kInvalidImage);
      CHECK(extract_stripe(img.pixels.data(), 1024, -1, 1024, params, profile) == StripeResult::kInvalidImage);
      CHECK(extract_stripe(img.pixels.data(), 1024, 0, 1024, params, profile) == StripeResult::kOk);
      CHECK(profile.rows() == 0);
    }
  }
  GIVEN("a profile reserved for fewer rows than the image has") {
    StripeProfile profile(100);
    THEN("the frame is refused rather than written past the capacity") {
      CHECK(run(img, params, profile) == StripeResult::kCapacityExceeded);
      CHECK(profile.rows() == 0);
    }
  }
}
