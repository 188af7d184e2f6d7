// Sub-pixel laser stripe extraction: one column per image row from a mono8 frame (thesis 3.3.2.2).
#pragma once

#include <cstdint>
#include <span>
#include <vector>

namespace cellsight::algo {

// Tuning of the extractor. Levels are DN above the local background; widths and distances in pixels.
//
// Background: for detection, the median of the 16-px chunk means within +-32 px (the stripe cannot bias it,
// it follows ambient light on carrier and part); for measurement, the mean of two 8-px flanks just beyond the
// candidate's tails. Per row: candidates = runs above background + threshold_dn, each measured (width, FWHM,
// centre); spikes and blobs rejected by FWHM; the strongest kept unless a comparable one (double_peak_ratio)
// exists, then continuity with the neighbouring rows decides, else the row is ambiguous.
struct StripeParams {
  // Detection and width level: a pixel belongs to a stripe candidate when it exceeds the local background by
  // more than this. With read noise sigma ~2 DN this is ~8 sigma, so noise alone almost never makes a candidate.
  // Clamped to [1, 254].
  float threshold_dn = 16.0f;
  // Shape test on the full width at half (peak - background). A hot pixel has exactly 1.0 whatever its
  // amplitude, a Gaussian stripe with sigma >= 0.8 px has >= 1.85 (point-sampled), so 1.4 separates them.
  float min_width_px = 1.4f;
  // Wider than this at half maximum is not a laser line (ambient light patch, large diffuse reflection).
  float max_width_px = 24.0f;
  // A second candidate whose (peak - background) is at least this share of the strongest one makes the row a
  // double peak, to be settled by continuity; weaker candidates (most ghosts) are ignored.
  float double_peak_ratio = 0.5f;
  // Candidates whose centres are closer than this are the same stripe, never a double peak.
  float double_peak_gap_px = 3.0f;
  // Continuity: a double peak is settled in favour of the candidate within this distance of the reference
  // (the nearest decided row above, then below) ...
  float continuity_tolerance_px = 4.0f;
  // ... provided the next candidate is at least this much farther away; otherwise the row is ambiguous.
  float continuity_margin_px = 1.5f;
  // A decided row serves as a continuity reference for at most this many rows (holes break continuity).
  int continuity_max_gap_rows = 8;
  // Pixel value at which the sensor clips; a chosen stripe reaching it is flagged saturated (still usable).
  int saturation_dn = 255;
  // A row whose stripe (peak - background) is weaker than this share of the frame's median stripe is not lit by
  // the laser: in rows where the laser hits nothing, ambient-lit carrier members and part edges (a few to
  // ~30 DN) would otherwise pass for a dim stripe. The laser, exposed for the band, is far brighter.
  float min_relative_strength = 0.15f;
};

enum class StripeStatus : std::uint8_t {
  kValid = 0,  // one stripe, measured
  kNoStripe,   // nothing above threshold, only spikes / over-wide blobs / a touch of the image border, or
               // far weaker than the frame's stripes (min_relative_strength); centre is NaN
  kSaturated,  // measured, but the stripe reached saturation_dn: usable, centre less precise (<= 0.2 px)
  kAmbiguous,  // two comparable stripes that continuity could not settle (centre = the stronger, alt_* =
               // the other), or a row too cluttered to trust (more than 32 runs above threshold)
};

[[nodiscard]] constexpr const char* to_string(StripeStatus status) {
  switch (status) {
    case StripeStatus::kValid: return "valid";
    case StripeStatus::kNoStripe: return "no_stripe";
    case StripeStatus::kSaturated: return "saturated";
    case StripeStatus::kAmbiguous: return "ambiguous";
  }
  return "unknown";
}

// One image row of the profile.
//
// width_px is the width of the stripe ABOVE THE ABSOLUTE LEVEL background + threshold_dn, with each edge found
// by log-linear interpolation between the last pixel above and the first pixel below that level. Why this and
// not the FWHM: below saturation a Gaussian's FWHM (2.355 sigma) does not depend on its amplitude at all, so it
// cannot tell the exposure controller whether the line is too dark or too bright. The width above a fixed
// level is 2 sigma sqrt(2 ln(A / threshold)) for peak A (still true when A is clipped at 255, since the
// flanks are not), which grows monotonically with exposure x reflectivity over the whole range, including
// over-exposure: it is the "width of the laser line" the thesis (6.2) keeps in a band. Log-linear edges are
// exact on a point-sampled Gaussian up to the chord of the log-parabola, which reads the line narrower by at
// most 1 / (2 (width - 1)) px (0.05-0.2 px in practice); the controller's band is in these measured pixels.
struct StripeRow {
  float centre_px = 0.0f;      // sub-pixel column, pixel centres at integer coordinates (OpenCV); NaN if none
  float width_px = 0.0f;       // see above; 0 when no stripe
  float alt_centre_px = 0.0f;  // ambiguous rows only: the other candidate (NaN otherwise)
  float alt_width_px = 0.0f;   // ambiguous rows only
  std::uint8_t peak = 0;       // brightest pixel of the chosen stripe (the row maximum when none)
  std::uint8_t alt_peak = 0;   // ambiguous rows only
  StripeStatus status = StripeStatus::kNoStripe;
};

// Per-frame summary; what the exposure controller consumes.
struct StripeSummary {
  int rows = 0;
  int valid_rows = 0;      // usable rows: status valid OR saturated
  int saturated_rows = 0;  // subset of valid_rows
  int ambiguous_rows = 0;
  int too_wide_rows = 0;         // rows with no stripe whose brightest rejected candidate was wider than max_width
  float median_width_px = 0.0f;  // median width_px over valid_rows (mean of the two middle values); 0 if none

  [[nodiscard]] float valid_fraction() const { return rows > 0 ? float(valid_rows) / float(rows) : 0.0f; }
  [[nodiscard]] float saturated_fraction() const {
    return valid_rows > 0 ? float(saturated_rows) / float(valid_rows) : 0.0f;
  }
};

// Fixed-capacity profile: allocated once at start-up (constructor or reserve), reused for every frame.
class StripeProfile {
 public:
  StripeProfile() = default;
  explicit StripeProfile(int capacity_rows) { reserve(capacity_rows); }

  // Start-up only: allocates. Never shrinks.
  void reserve(int capacity_rows);

  // Empties the profile without releasing memory.
  void clear() {
    row_count_ = 0;
    summary_ = StripeSummary{};
  }

  [[nodiscard]] int capacity() const { return static_cast<int>(rows_.size()); }
  [[nodiscard]] int rows() const { return row_count_; }
  [[nodiscard]] std::span<const StripeRow> row_data() const { return {rows_.data(), std::size_t(row_count_)}; }
  [[nodiscard]] const StripeRow& row(int r) const { return rows_[std::size_t(r)]; }
  [[nodiscard]] const StripeSummary& summary() const { return summary_; }

 private:
  friend class StripeExtractor;
  std::vector<StripeRow> rows_;
  std::vector<float> scratch_;   // medians without allocating
  std::vector<float> strength_;  // per row: peak - background of the reported stripe
  int row_count_ = 0;
  StripeSummary summary_{};
};

enum class [[nodiscard]] StripeResult : std::uint8_t{
    kOk = 0,
    kInvalidImage,      // null pixels, width < 3 or > kStripeMaxWidthPx, height < 0, stride < width
    kCapacityExceeded,  // height > out.capacity(): reserve at start-up with the camera's height
};

[[nodiscard]] constexpr const char* to_string(StripeResult result) {
  switch (result) {
    case StripeResult::kOk: return "ok";
    case StripeResult::kInvalidImage: return "invalid image";
    case StripeResult::kCapacityExceeded: return "profile capacity exceeded";
  }
  return "unknown";
}

// Widest row the extractor accepts (its per-row scratch lives on the stack).
inline constexpr int kStripeMaxWidthPx = 8192;

// Which row kernels to run: the vector ones (SSE2 on x86-64, the default) or the portable scalar ones. Both
// give bit-identical results (tests compare them); the choice exists for that test and for the benchmark.
enum class StripeKernel : std::uint8_t { kBest, kScalar };

// Extracts the stripe column of every row of a mono8 image (width and height from the caller, rows `stride`
// bytes apart). Real-time path: no allocation, no exceptions. On error `out` is left empty (rows() == 0).
[[nodiscard]] StripeResult extract_stripe(const std::uint8_t* pixels, int width, int height, int stride,
                                          const StripeParams& params, StripeProfile& out,
                                          StripeKernel kernel = StripeKernel::kBest);

// True when this build has a vector kernel (kBest differs from kScalar).
[[nodiscard]] bool stripe_has_simd();

}  // namespace cellsight::algo
