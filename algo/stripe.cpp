// Sub-pixel laser stripe extraction: vector row scans, candidate measurement, continuity between rows.
#include "algo/stripe.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <limits>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace cellsight::algo {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
// Rows are summed in 16-pixel chunks (one SSE2 register). The detection threshold of a chunk is the MEDIAN of the
// chunk means within +-kBackgroundChunks, plus threshold_dn: a stripe (<= ~15 px even saturated and blooming)
// raises at most 2 neighbouring chunks, so the median of 5 is stripe-free; it follows ambient light that is not
// uniform along the row (lit carrier members and part surfaces, the cabin's gradient) and, unlike a minimum,
// does not fall to the dark side within 32 px of the edge of a lit surface.
constexpr int kChunkPx = 16;
constexpr int kMaxChunks = (kStripeMaxWidthPx + kChunkPx - 1) / kChunkPx;
constexpr int kBackgroundChunks = 2;
constexpr int kPadChunks = 8;  // room for the vector median to read and write past the last chunk
// A candidate's own background: the mean of two flanks of kFlankPx pixels, kept clear of its tails (which reach
// ~4.7 sigma at 0.5 DN) by kTailMinPx plus half the run's length; pixels above their chunk threshold (other
// candidates, hot pixels) are left out. Fewer than kMinFlankPixels -> the chunk background.
constexpr int kFlankPx = 8;
constexpr int kTailMinPx = 4;
constexpr int kMinFlankPixels = 6;
// More runs above threshold than this in one row is not a laser line; the extra runs are dropped and a chosen
// stripe in such a row is reported ambiguous.
constexpr int kMaxRuns = 32;
// The centre window reaches this far beyond the threshold crossings: the measured bias/noise trade-off (see
// extract_centre).
constexpr float kCentreWindowMarginPx = 1.0f;
constexpr int kCentreIterations = 4;
constexpr float kCentreConvergedPx = 1e-3f;
// log() of a pixel at or below the background would be undefined; the flank interpolation clamps to this.
constexpr float kLogFloorDn = 0.5f;
// The threshold is a level above background; below 1 DN the log interpolation and the noise model break down.
constexpr float kMinThresholdDn = 1.0f;
constexpr float kMaxThresholdDn = 254.0f;

struct Run {
  int begin = 0;  // inclusive
  int end = 0;    // inclusive
};

// Output of the second row scan: runs of pixels above their chunk's threshold.
struct RowScan {
  std::array<Run, kMaxRuns> runs{};
  int run_count = 0;
  bool overflow = false;
};

// Appends the above-threshold pixels flagged in `mask` (bit i -> column base + i) to the run list.
inline void add_above(std::uint32_t mask, int base, RowScan& scan) {
  while (mask != 0) {
    const int x = base + __builtin_ctz(mask);
    mask &= mask - 1;
    if (scan.run_count > 0 && scan.runs[std::size_t(scan.run_count - 1)].end == x - 1) {
      scan.runs[std::size_t(scan.run_count - 1)].end = x;
    } else if (scan.run_count < kMaxRuns) {
      scan.runs[std::size_t(scan.run_count++)] = Run{x, x};
    } else {
      scan.overflow = true;
    }
  }
}

// ---- scalar kernels: the reference semantics -------------------------------------------------------------

struct ChunkStats {
  std::uint8_t max = 0;  // row maximum
  int lowest = 0;        // lowest chunk sum
};

// Sum of one chunk of `count` <= 16 pixels, scaled to 16 pixels when short so that all sums compare as means.
inline std::int16_t chunk_sum_scalar(const std::uint8_t* p, int count, std::uint8_t& max) {
  std::uint32_t sum = 0;
  for (int x = 0; x < count; ++x) {
    sum += p[x];
    max = std::max(max, p[x]);
  }
  return std::int16_t(count == kChunkPx ? sum : sum * kChunkPx / std::uint32_t(count));
}

// Pass 1: the sum of every 16-pixel chunk (as int16, <= 4080), the row maximum and the lowest chunk sum.
ChunkStats chunk_sums_scalar(const std::uint8_t* p, int n, std::int16_t* sums) {
  ChunkStats s;
  s.lowest = std::numeric_limits<int>::max();
  for (int c = 0; c * kChunkPx < n; ++c) {
    sums[c] =
        chunk_sum_scalar(p + static_cast<std::ptrdiff_t>(c) * kChunkPx, std::min(kChunkPx, n - c * kChunkPx), s.max);
    s.lowest = std::min(s.lowest, int(sums[c]));
  }
  return s;
}

// Pass 2: pixels above their chunk's threshold become runs.
void scan_row_scalar(const std::uint8_t* p, int n, const std::uint8_t* thr, RowScan& scan) {
  scan.run_count = 0;
  scan.overflow = false;
  for (int c = 0; c * kChunkPx < n; ++c) {
    std::uint32_t above = 0;
    const int x0 = c * kChunkPx;
    for (int x = x0; x < std::min(n, x0 + kChunkPx); ++x) {
      if (p[x] > thr[c]) {
        above |= 1u << unsigned(x - x0);
      }
    }
    add_above(above, x0, scan);
  }
}

// Median of 5 from min/max only: median3(c, max(min(a, b), min(d, e)), min(max(a, b), max(d, e))) (checked
// against sorting on all 5^5 tuples of 0..4, ties included, when written; the kernel-equality and lit-surface
// tests exercise it here).
inline std::int16_t median3(std::int16_t x, std::int16_t y, std::int16_t z) {
  return std::max(std::min(x, y), std::min(std::max(x, y), z));
}

// Pass 1b: per chunk the median of its sum and its 2 neighbours on either side (the background, in sixteenths of
// a DN) and the detection threshold floor(median / 16 + threshold) = (median + threshold_sixteenths) >> 4.
// `padded` holds the sums from index kBackgroundChunks on, edge values repeated twice before and after.
void chunk_thresholds_scalar(const std::int16_t* padded, int chunks, int threshold_sixteenths, std::int16_t* median,
                             std::uint8_t* thr) {
  for (int c = 0; c < chunks; ++c) {
    const std::int16_t* w = padded + c;  // w[0..4] = chunks c-2 .. c+2
    median[c] = median3(w[2], std::max(std::min(w[0], w[1]), std::min(w[3], w[4])),
                        std::min(std::max(w[0], w[1]), std::max(w[3], w[4])));
    thr[c] = std::uint8_t(std::min((int(median[c]) + threshold_sixteenths) >> 4, 254));
  }
}

// ---- SSE2 kernels (baseline on every x86-64 CPU) -----------------------------------------------------------

#if defined(__SSE2__)

// Two chunks -> their sums in the low 16 bits of two 64-bit lanes.
inline __m128i pair_sums(__m128i a, __m128i b) {
  const __m128i zero = _mm_setzero_si128();
  const __m128i sa = _mm_sad_epu8(a, zero);  // [sum of a's low 8 bytes, sum of its high 8]
  const __m128i sb = _mm_sad_epu8(b, zero);
  return _mm_add_epi64(_mm_unpacklo_epi64(sa, sb), _mm_unpackhi_epi64(sa, sb));
}

ChunkStats chunk_sums_sse2(const std::uint8_t* p, int n, std::int16_t* sums) {
  __m128i vmax = _mm_setzero_si128();
  __m128i vmin = _mm_set1_epi16(std::numeric_limits<std::int16_t>::max());
  int c = 0;
  for (; (c + 8) * kChunkPx <= n; c += 8) {  // 8 chunks -> 8 int16 sums in one register
    const auto* q = reinterpret_cast<const __m128i*>(p + static_cast<std::ptrdiff_t>(c) * kChunkPx);
    __m128i v[8];
    for (int k = 0; k < 8; ++k) {
      v[k] = _mm_loadu_si128(q + k);
    }
    vmax = _mm_max_epu8(vmax, _mm_max_epu8(_mm_max_epu8(_mm_max_epu8(v[0], v[1]), _mm_max_epu8(v[2], v[3])),
                                           _mm_max_epu8(_mm_max_epu8(v[4], v[5]), _mm_max_epu8(v[6], v[7]))));
    // Lanes [s, 0] of 64 bits read as int32 [s, 0, s', 0]; packing twice keeps the sums, in order.
    const __m128i s0123 = _mm_packs_epi32(pair_sums(v[0], v[1]), pair_sums(v[2], v[3]));
    const __m128i s4567 = _mm_packs_epi32(pair_sums(v[4], v[5]), pair_sums(v[6], v[7]));
    const __m128i s = _mm_packs_epi32(s0123, s4567);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(sums + c), s);
    vmin = _mm_min_epi16(vmin, s);
  }
  __m128i m = _mm_max_epu8(vmax, _mm_srli_si128(vmax, 8));
  m = _mm_max_epu8(m, _mm_srli_si128(m, 4));
  m = _mm_max_epu8(m, _mm_srli_si128(m, 2));
  m = _mm_max_epu8(m, _mm_srli_si128(m, 1));
  __m128i l = _mm_min_epi16(vmin, _mm_srli_si128(vmin, 8));
  l = _mm_min_epi16(l, _mm_srli_si128(l, 4));
  l = _mm_min_epi16(l, _mm_srli_si128(l, 2));
  ChunkStats s;
  s.max = std::uint8_t(_mm_cvtsi128_si32(m) & 0xFF);
  s.lowest = std::int16_t(_mm_cvtsi128_si32(l) & 0xFFFF);
  for (; c * kChunkPx < n; ++c) {  // the remaining chunks, the last one maybe short
    sums[c] =
        chunk_sum_scalar(p + static_cast<std::ptrdiff_t>(c) * kChunkPx, std::min(kChunkPx, n - c * kChunkPx), s.max);
    s.lowest = std::min(s.lowest, int(sums[c]));
  }
  return s;
}

void scan_row_sse2(const std::uint8_t* p, int n, const std::uint8_t* thr, RowScan& scan) {
  scan.run_count = 0;
  scan.overflow = false;
  const __m128i zero = _mm_setzero_si128();
  int c = 0;
  for (; (c + 1) * kChunkPx <= n; ++c) {
    const __m128i v = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p + static_cast<std::ptrdiff_t>(c) * kChunkPx));
    // v <= thr  <=>  saturating v - thr == 0 (an unsigned compare without a sign flip).
    const __m128i le = _mm_cmpeq_epi8(_mm_subs_epu8(v, _mm_set1_epi8(static_cast<char>(thr[c]))), zero);
    const std::uint32_t above = ~std::uint32_t(_mm_movemask_epi8(le)) & 0xFFFFu;
    if (above != 0) {
      add_above(above, c * kChunkPx, scan);
    }
  }
  if (c * kChunkPx < n) {  // the short last chunk: same semantics, scalar
    std::uint32_t above = 0;
    const int x0 = c * kChunkPx;
    for (int x = x0; x < n; ++x) {
      if (p[x] > thr[c]) {
        above |= 1u << unsigned(x - x0);
      }
    }
    add_above(above, x0, scan);
  }
}

// Eight chunks at a time with the same min/max network and integer arithmetic: identical to the scalar one.
void chunk_thresholds_sse2(const std::int16_t* padded, int chunks, int threshold_sixteenths, std::int16_t* median,
                           std::uint8_t* thr) {
  const __m128i t16 = _mm_set1_epi16(std::int16_t(threshold_sixteenths));
  const __m128i cap = _mm_set1_epi16(254);
  for (int c = 0; c < chunks; c += 8) {  // may run into the padding of `padded`, `median` and `thr`: sized for it
    const std::int16_t* w = padded + c;
    const __m128i a = _mm_loadu_si128(reinterpret_cast<const __m128i*>(w));
    const __m128i b = _mm_loadu_si128(reinterpret_cast<const __m128i*>(w + 1));
    const __m128i m = _mm_loadu_si128(reinterpret_cast<const __m128i*>(w + 2));
    const __m128i d = _mm_loadu_si128(reinterpret_cast<const __m128i*>(w + 3));
    const __m128i e = _mm_loadu_si128(reinterpret_cast<const __m128i*>(w + 4));
    const __m128i lo = _mm_max_epi16(_mm_min_epi16(a, b), _mm_min_epi16(d, e));
    const __m128i hi = _mm_min_epi16(_mm_max_epi16(a, b), _mm_max_epi16(d, e));
    const __m128i med = _mm_max_epi16(_mm_min_epi16(m, lo), _mm_min_epi16(_mm_max_epi16(m, lo), hi));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(median + c), med);
    const __m128i t = _mm_min_epi16(_mm_srai_epi16(_mm_add_epi16(med, t16), 4), cap);
    _mm_storel_epi64(reinterpret_cast<__m128i*>(thr + c), _mm_packus_epi16(t, t));
  }
}

#endif  // __SSE2__

// One stripe candidate of a row, measured.
struct Candidate {
  int lo = 0, hi = 0;        // pixels strictly above background + threshold
  int peak = 0, peak_x = 0;  // brightest pixel (the first one of a saturated plateau)
  float background_dn = 0.0f;
  float left_px = 0.0f, right_px = 0.0f;  // sub-pixel threshold crossings
  float width_px = 0.0f;                  // right - left
  float fwhm_px = 0.0f;                   // width at half (peak - background), for the shape test only
  float mid_px = 0.0f;                    // (left + right) / 2: good enough to compare candidates
  bool usable = false;
  bool too_wide = false;
};

// Crossing of `level` (DN above background) on a flank between pixel `inner` (above) and `outer` (at or below),
// interpolated linearly in log intensity: a Gaussian's log is a parabola, so the only error is the chord's.
inline float log_crossing(float inner_dn, float outer_dn, float log_level) {
  const float log_in = std::log(inner_dn);
  const float log_out = std::log(std::max(outer_dn, kLogFloorDn));
  return (log_in - log_level) / (log_in - log_out);  // fraction of the step from inner towards outer, (0, 1]
}

// Linear crossing at an absolute level between an inner pixel (above) and an outer one (at or below).
inline float linear_crossing(float inner, float outer, float level) {
  return (inner - level) / (inner - outer);
}

// Centre of gravity of (pixel - background) over a window [c - h, c + h], h = width / 2 + 1 px, centred on the
// current estimate, pixels cut by the window edge weighted by their covered fraction, iterated to its fixed
// point. Measured on analytic Gaussians (sigma 0.8-1.6 px, peaks 30-240 DN over a 16 DN threshold,
// point-sampled and pixel-integrated): max bias <= 0.012 px, where plain CoG over the above-threshold pixels
// has up to 0.28 px (the window is cut asymmetrically by the integer threshold crossings) and CoG of
// (pixel - threshold) up to 0.13 px. The 3-point log-parabola is exact noise-free but uses 3 pixels only (2x the
// noise at sigma 1.6) and fails on a clipped plateau, where this window still gives <= 0.15 px. The margin of
// 1 px beyond the crossings is the bias/noise trade-off: 1.5 px halves the bias but adds 10-25 % noise, 0.5 px
// doubles the bias. A symmetric window also cancels a constant error of the background to first order.
float extract_centre(const std::uint8_t* p, int n, const Candidate& c) {
  const float half_px = 0.5f * c.width_px + kCentreWindowMarginPx;
  const float bg = c.background_dn;
  float centre = c.mid_px;
  for (int it = 0; it < kCentreIterations; ++it) {
    // Pixel x covers [x - 0.5, x + 0.5): the window's end pixels count with the share they cover, the ones
    // between them fully. Candidates touching the image border were rejected, so the clamps rarely act.
    const float a = centre - half_px;
    const float b = centre + half_px;
    const int xa = std::max(0, int(std::floor(a + 0.5f)));
    const int xb = std::min(n - 1, int(std::floor(b + 0.5f)));
    const float wa = (float(p[xa]) - bg) * std::min(1.0f, float(xa) + 0.5f - a);
    const float wb = (float(p[xb]) - bg) * std::min(1.0f, b - (float(xb) - 0.5f));
    float sum_w = wa + wb;
    float sum_wx = wa * float(xa) + wb * float(xb);
    for (int x = xa + 1; x < xb; ++x) {
      const float w = float(p[x]) - bg;
      sum_w += w;
      sum_wx += w * float(x);
    }
    if (!(sum_w > 0.0f)) {
      return c.mid_px;  // degenerate (cannot happen with a real stripe above threshold); keep the rough centre
    }
    const float next = sum_wx / sum_w;
    const bool done = std::fabs(next - centre) < kCentreConvergedPx;
    centre = next;
    if (done) {
      break;
    }
  }
  return centre;
}

}  // namespace

void StripeProfile::reserve(int capacity_rows) {
  if (capacity_rows > capacity()) {
    rows_.resize(std::size_t(capacity_rows));
    scratch_.resize(std::size_t(capacity_rows));
    strength_.resize(std::size_t(capacity_rows));
  }
}

bool stripe_has_simd() {
#if defined(__SSE2__)
  return true;
#else
  return false;
#endif
}

// The per-frame work, with access to the profile's storage.
class StripeExtractor {
 public:
  StripeExtractor(const StripeParams& params, StripeProfile& out, StripeKernel kernel)
      : params_(params), out_(out), kernel_(kernel) {
    threshold_dn_ = std::isnan(params_.threshold_dn)
                        ? kMinThresholdDn
                        : std::clamp(params_.threshold_dn, kMinThresholdDn, kMaxThresholdDn);
    threshold_sixteenths_ = int(std::lround(threshold_dn_ * float(kChunkPx)));
    log_threshold_ = std::log(threshold_dn_);
  }

  void run(const std::uint8_t* pixels, int width, int height, int stride) {
    out_.row_count_ = height;
    out_.summary_ = StripeSummary{};
    out_.summary_.rows = height;
    for (int r = 0; r < height; ++r) {
      StripeRow& row = out_.rows_[std::size_t(r)];
      measure_row(pixels + std::ptrdiff_t(r) * stride, width, r, row);
      if (row.status == StripeStatus::kValid || row.status == StripeStatus::kSaturated) {
        ref_row_ = r;
        ref_centre_ = row.centre_px;
      }
    }
    drop_weak_rows(height);
    resolve_backward(height);
    summarise(height);
  }

 private:
  ChunkStats chunk_sums(const std::uint8_t* p, int n) {
    std::int16_t* sums = padded_sum_.data() + kBackgroundChunks;
#if defined(__SSE2__)
    if (kernel_ == StripeKernel::kBest) {
      return chunk_sums_sse2(p, n, sums);
    }
#endif
    return chunk_sums_scalar(p, n, sums);
  }

  void scan_row(const std::uint8_t* p, int n) {
#if defined(__SSE2__)
    if (kernel_ == StripeKernel::kBest) {
      scan_row_sse2(p, n, chunk_thr_.data(), scan_);
      return;
    }
#endif
    scan_row_scalar(p, n, chunk_thr_.data(), scan_);
  }

  // Chunk backgrounds (median chunk mean within +-kBackgroundChunks) and detection thresholds, in integer
  // sixteenths of a DN (a chunk sum is 16 x its mean): threshold = floor(median mean + threshold_dn).
  void chunk_thresholds(int n) {
    const int chunks = (n + kChunkPx - 1) / kChunkPx;
    std::int16_t* padded = padded_sum_.data();
    for (int k = 0; k < kBackgroundChunks; ++k) {  // the median's neighbours beyond the row: its edge values
      padded[k] = padded[kBackgroundChunks];
    }
    for (int k = 0; k < kBackgroundChunks + kPadChunks; ++k) {
      padded[chunks + kBackgroundChunks + k] = padded[chunks + kBackgroundChunks - 1];
    }
#if defined(__SSE2__)
    if (kernel_ == StripeKernel::kBest) {
      chunk_thresholds_sse2(padded, chunks, threshold_sixteenths_, median_sum_.data(), chunk_thr_.data());
      return;
    }
#endif
    chunk_thresholds_scalar(padded, chunks, threshold_sixteenths_, median_sum_.data(), chunk_thr_.data());
  }

  [[nodiscard]] float chunk_background(int x) const {
    return float(median_sum_[std::size_t(x / kChunkPx)]) * (1.0f / float(kChunkPx));
  }

  // Background of a run: the mean of two flanks beyond its tails, without pixels above their chunk threshold
  // (other candidates, hot pixels); the chunk background when the flanks are too short or all bright.
  float flank_background(const std::uint8_t* p, int n, const Run& run) const {
    const int guard = kTailMinPx + (run.end - run.begin + 1) / 2;
    std::uint32_t sum = 0;
    int count = 0;
    auto add = [&](int x0, int x1) {
      for (int x = std::max(0, x0); x < std::min(n, x1); ++x) {
        if (p[x] <= chunk_thr_[std::size_t(x / kChunkPx)]) {
          sum += p[x];
          ++count;
        }
      }
    };
    add(run.begin - guard - kFlankPx, run.begin - guard);
    add(run.end + guard + 1, run.end + guard + 1 + kFlankPx);
    if (count < kMinFlankPixels) {
      return chunk_background(run.begin);
    }
    return float(sum) / float(count);
  }

  // Measures a candidate from its peak and background. False when it touches the image border.
  bool measure(const std::uint8_t* p, int n, Candidate& c) const {
    // The window is re-walked from the peak because a merge may have changed the background, hence the level.
    const float level = c.background_dn + threshold_dn_;
    c.lo = c.peak_x;
    c.hi = c.peak_x;
    while (c.lo > 0 && float(p[c.lo - 1]) > level) {
      --c.lo;
    }
    while (c.hi < n - 1 && float(p[c.hi + 1]) > level) {
      ++c.hi;
    }
    if (c.lo <= 0 || c.hi >= n - 1) {
      return false;  // a flank is outside the image: neither width nor centre can be measured
    }
    const float bg = c.background_dn;
    c.left_px = float(c.lo) - log_crossing(float(p[c.lo]) - bg, float(p[c.lo - 1]) - bg, log_threshold_);
    c.right_px = float(c.hi) + log_crossing(float(p[c.hi]) - bg, float(p[c.hi + 1]) - bg, log_threshold_);
    c.width_px = c.right_px - c.left_px;
    c.mid_px = 0.5f * (c.left_px + c.right_px);
    // Shape: full width at half of (peak - background), walking out from the peak (plateau included).
    const float half = bg + 0.5f * (float(c.peak) - bg);
    int a = c.peak_x, b = c.peak_x;
    while (a > 0 && float(p[a - 1]) > half) {
      --a;
    }
    while (b < n - 1 && float(p[b + 1]) > half) {
      ++b;
    }
    const float left_half = a > 0 ? float(a) - linear_crossing(float(p[a]), float(p[a - 1]), half) : float(a);
    const float right_half = b < n - 1 ? float(b) + linear_crossing(float(p[b]), float(p[b + 1]), half) : float(b);
    c.fwhm_px = right_half - left_half;
    c.too_wide = c.fwhm_px > params_.max_width_px;
    c.usable = c.fwhm_px >= params_.min_width_px && !c.too_wide;
    return true;
  }

  void set_no_stripe(StripeRow& row, std::uint8_t row_max) const {
    row = StripeRow{};
    row.centre_px = kNaN;
    row.alt_centre_px = kNaN;
    row.peak = row_max;
    row.status = StripeStatus::kNoStripe;
  }

  void measure_row(const std::uint8_t* p, int n, int row_index, StripeRow& row) {
    const ChunkStats stats = chunk_sums(p, n);
    const std::uint8_t row_max = stats.max;
    // A median is never below the lowest value it is taken from, so no pixel can exceed its chunk threshold when
    // the row maximum does not exceed floor(lowest chunk mean + threshold): the empty row ends here.
    if (int(row_max) <= std::min((stats.lowest + threshold_sixteenths_) >> 4, 254)) {
      set_no_stripe(row, row_max);
      return;
    }
    chunk_thresholds(n);
    scan_row(p, n);
    collect_candidates(p, n);
    bool rejected_too_wide = false;
    const int usable = keep_usable_candidates(p, n, rejected_too_wide);
    if (usable == 0) {
      set_no_stripe(row, row_max);
      if (rejected_too_wide) {
        ++too_wide_rows_;  // evidence of gross over-exposure for the exposure controller
      }
      return;
    }
    choose_candidate(p, n, row_index, usable, row);
  }

  // Runs -> candidate windows at the local level background + threshold, merging runs that the lower local level
  // joins (a stripe split by noise near the threshold).
  void collect_candidates(const std::uint8_t* p, int n) {
    candidate_count_ = 0;
    for (int i = 0; i < scan_.run_count; ++i) {
      const Run& run = scan_.runs[std::size_t(i)];
      int peak = -1, peak_x = run.begin;
      for (int x = run.begin; x <= run.end; ++x) {
        if (int(p[x]) > peak) {
          peak = p[x];
          peak_x = x;
        }
      }
      const float bg = flank_background(p, n, run);
      const float level = bg + threshold_dn_;
      if (float(peak) <= level) {
        continue;
      }
      int lo = peak_x, hi = peak_x;
      while (lo > 0 && float(p[lo - 1]) > level) {
        --lo;
      }
      while (hi < n - 1 && float(p[hi + 1]) > level) {
        ++hi;
      }
      if (candidate_count_ > 0 && lo <= candidates_[std::size_t(candidate_count_ - 1)].hi + 1) {
        Candidate& prev = candidates_[std::size_t(candidate_count_ - 1)];
        prev.lo = std::min(prev.lo, lo);
        prev.hi = std::max(prev.hi, hi);
        if (peak > prev.peak) {
          prev.peak = peak;
          prev.peak_x = peak_x;
          prev.background_dn = bg;
        }
        continue;
      }
      Candidate& c = candidates_[std::size_t(candidate_count_++)];
      c = Candidate{};
      c.lo = lo;
      c.hi = hi;
      c.peak = peak;
      c.peak_x = peak_x;
      c.background_dn = bg;
    }
  }

  // Measures the candidates and keeps the usable ones in place; returns how many. rejected_too_wide: the brightest
  // rejected one was too wide.
  int keep_usable_candidates(const std::uint8_t* p, int n, bool& rejected_too_wide) {
    int usable = 0;
    int brightest_rejected_peak = -1;
    for (int i = 0; i < candidate_count_; ++i) {
      Candidate c = candidates_[std::size_t(i)];
      if (!measure(p, n, c)) {
        continue;
      }
      if (!c.usable) {
        if (c.peak > brightest_rejected_peak) {
          brightest_rejected_peak = c.peak;
          rejected_too_wide = c.too_wide;
        }
        continue;
      }
      candidates_[std::size_t(usable++)] = c;
    }
    candidate_count_ = usable;
    return usable;
  }

  // The row's stripe among the usable candidates: the strongest unless a comparable competitor makes it a double
  // peak, which continuity with the rows above decides or which stays ambiguous.
  void choose_candidate(const std::uint8_t* p, int n, int row_index, int usable, StripeRow& row) {
    const int best = strongest_candidate(usable);
    const Candidate& b = candidates_[std::size_t(best)];
    const int second = strongest_competitor(usable, best);
    if (second < 0) {
      fill_row(row, p, n, b);
      // More runs than kMaxRuns: some were never looked at, so the choice may be wrong.
      row.status = scan_.overflow ? StripeStatus::kAmbiguous : saturation_status(b.peak);
      return;
    }
    // A double peak: choose by continuity with the nearest decided row above (forward pass), comparing every
    // comparable candidate by its rough centre.
    if (forward_reference(row_index)) {
      const int nearest = clearly_nearest_to_reference(usable, best);
      if (nearest >= 0) {
        const Candidate& chosen = candidates_[std::size_t(nearest)];
        fill_row(row, p, n, chosen);
        row.status = scan_.overflow ? StripeStatus::kAmbiguous : saturation_status(chosen.peak);
        return;
      }
    }
    // Undecided: report the stronger one, keep the second strongest for the backward pass.
    const Candidate& alt = candidates_[std::size_t(second)];
    fill_row(row, p, n, b);
    row.status = StripeStatus::kAmbiguous;
    row.alt_centre_px = extract_centre(p, n, alt);
    row.alt_width_px = alt.width_px;
    row.alt_peak = std::uint8_t(std::clamp(alt.peak, 0, 255));
  }

  // Strongest candidate (tie: the wider one).
  int strongest_candidate(int usable) const {
    int best = 0;
    for (int i = 1; i < usable; ++i) {
      const Candidate& c = candidates_[std::size_t(i)];
      const Candidate& b = candidates_[std::size_t(best)];
      if (strength(c) > strength(b) || (strength(c) == strength(b) && c.width_px > b.width_px)) {
        best = i;
      }
    }
    return best;
  }

  // A candidate nearly as strong as the best and apart from it: a double peak.
  bool competes(const Candidate& c, const Candidate& b) const {
    return !(strength(c) < params_.double_peak_ratio * strength(b) ||
             std::fabs(c.mid_px - b.mid_px) <= params_.double_peak_gap_px);
  }

  // The strongest of the best's competitors; -1 when it has none.
  int strongest_competitor(int usable, int best) const {
    const Candidate& b = candidates_[std::size_t(best)];
    int second = -1;
    for (int i = 0; i < usable; ++i) {
      const Candidate& c = candidates_[std::size_t(i)];
      if (i == best || !competes(c, b)) {
        continue;
      }
      if (second < 0 || strength(c) > strength(candidates_[std::size_t(second)])) {
        second = i;
      }
    }
    return second;
  }

  // Among the best and its competitors, the one whose rough centre is within the continuity tolerance of the
  // reference row's centre and clearly nearer than any other; -1 when none is.
  int clearly_nearest_to_reference(int usable, int best) const {
    const Candidate& b = candidates_[std::size_t(best)];
    int nearest = -1;
    float d1 = std::numeric_limits<float>::infinity(), d2 = d1;
    for (int i = 0; i < usable; ++i) {
      const Candidate& c = candidates_[std::size_t(i)];
      if (i != best && !competes(c, b)) {
        continue;
      }
      const float d = std::fabs(c.mid_px - ref_centre_);
      if (d < d1) {
        d2 = d1;
        d1 = d;
        nearest = i;
      } else if (d < d2) {
        d2 = d;
      }
    }
    if (d1 <= params_.continuity_tolerance_px && d2 - d1 >= params_.continuity_margin_px) {
      return nearest;
    }
    return -1;
  }

  static float strength(const Candidate& c) {
    return float(c.peak) - c.background_dn;
  }

  StripeStatus saturation_status(int peak) const {
    return peak >= params_.saturation_dn ? StripeStatus::kSaturated : StripeStatus::kValid;
  }

  bool forward_reference(int row_index) const {
    return ref_row_ >= 0 && row_index - ref_row_ <= params_.continuity_max_gap_rows;
  }

  void fill_row(StripeRow& row, const std::uint8_t* p, int n, const Candidate& c) {
    out_.strength_[std::size_t(&row - out_.rows_.data())] = strength(c);
    row.centre_px = extract_centre(p, n, c);
    row.width_px = c.width_px;
    row.peak = std::uint8_t(std::clamp(c.peak, 0, 255));
    row.alt_centre_px = kNaN;
    row.alt_width_px = 0.0f;
    row.alt_peak = 0;
  }

  // Rows whose stripe is far weaker than the frame's typical one are not the laser (see
  // StripeParams::min_relative_strength). Ambiguous rows are judged by their stronger candidate.
  void drop_weak_rows(int height) {
    int count = 0;
    for (int r = 0; r < height; ++r) {
      const StripeStatus s = out_.rows_[std::size_t(r)].status;
      if (s == StripeStatus::kValid || s == StripeStatus::kSaturated) {
        out_.scratch_[std::size_t(count++)] = out_.strength_[std::size_t(r)];
      }
    }
    if (count == 0) {
      return;
    }
    auto mid = out_.scratch_.begin() + count / 2;
    std::nth_element(out_.scratch_.begin(), mid, out_.scratch_.begin() + count);
    const float limit = params_.min_relative_strength * *mid;
    for (int r = 0; r < height; ++r) {
      StripeRow& row = out_.rows_[std::size_t(r)];
      if (row.status != StripeStatus::kNoStripe && out_.strength_[std::size_t(r)] < limit) {
        set_no_stripe(row, row.peak);
      }
    }
  }

  // Backward continuity: rows the forward pass left ambiguous are decided against the nearest decided row below
  // (a stripe that starts with its ghost at the top of the part is settled from where the ghost ends). Only the
  // two stored candidates take part here.
  void resolve_backward(int height) {
    int ref_row = -1;
    float ref_centre = 0.0f;
    for (int r = height - 1; r >= 0; --r) {
      StripeRow& row = out_.rows_[std::size_t(r)];
      const bool has_ref = ref_row >= 0 && ref_row - r <= params_.continuity_max_gap_rows;
      if (row.status == StripeStatus::kAmbiguous && has_ref && !std::isnan(row.alt_centre_px)) {
        const float d_main = std::fabs(row.centre_px - ref_centre);
        const float d_alt = std::fabs(row.alt_centre_px - ref_centre);
        if (d_alt <= params_.continuity_tolerance_px && d_main - d_alt >= params_.continuity_margin_px) {
          std::swap(row.centre_px, row.alt_centre_px);
          std::swap(row.width_px, row.alt_width_px);
          std::swap(row.peak, row.alt_peak);
          row.status = saturation_status(row.peak);
        } else if (d_main <= params_.continuity_tolerance_px && d_alt - d_main >= params_.continuity_margin_px) {
          row.status = saturation_status(row.peak);
        }
        if (row.status != StripeStatus::kAmbiguous) {
          row.alt_centre_px = kNaN;  // settled: the other one was a ghost, a spike or the other surface
          row.alt_width_px = 0.0f;
          row.alt_peak = 0;
        }
      }
      if (row.status == StripeStatus::kValid || row.status == StripeStatus::kSaturated) {
        ref_row = r;
        ref_centre = row.centre_px;
      }
    }
  }

  void summarise(int height) {
    StripeSummary& s = out_.summary_;
    int widths = 0;
    for (int r = 0; r < height; ++r) {
      const StripeRow& row = out_.rows_[std::size_t(r)];
      switch (row.status) {
        case StripeStatus::kSaturated: ++s.saturated_rows; [[fallthrough]];
        case StripeStatus::kValid:
          ++s.valid_rows;
          out_.scratch_[std::size_t(widths++)] = row.width_px;
          break;
        case StripeStatus::kAmbiguous: ++s.ambiguous_rows; break;
        case StripeStatus::kNoStripe: break;
      }
    }
    s.too_wide_rows = too_wide_rows_;
    if (widths == 0) {
      return;
    }
    auto first = out_.scratch_.begin();
    auto mid = first + widths / 2;
    std::nth_element(first, mid, first + widths);
    float median = *mid;
    if (widths % 2 == 0) {
      median = 0.5f * (median + *std::max_element(first, mid));
    }
    s.median_width_px = median;
  }

  const StripeParams& params_;
  StripeProfile& out_;
  StripeKernel kernel_;
  float threshold_dn_ = 0.0f;
  int threshold_sixteenths_ = 0;
  float log_threshold_ = 0.0f;
  RowScan scan_{};
  std::array<std::int16_t, kMaxChunks + 2 * kBackgroundChunks + kPadChunks> padded_sum_{};
  std::array<std::int16_t, kMaxChunks + kPadChunks> median_sum_{};
  std::array<std::uint8_t, kMaxChunks + kPadChunks> chunk_thr_{};
  std::array<Candidate, kMaxRuns> candidates_{};
  int candidate_count_ = 0;
  int too_wide_rows_ = 0;
  int ref_row_ = -1;  // forward continuity: last decided row and its centre
  float ref_centre_ = 0.0f;
};

StripeResult extract_stripe(const std::uint8_t* pixels, int width, int height, int stride, const StripeParams& params,
                            StripeProfile& out, StripeKernel kernel) {
  out.clear();
  if (pixels == nullptr || width < 3 || width > kStripeMaxWidthPx || height < 0 || stride < width) {
    return StripeResult::kInvalidImage;
  }
  if (height > out.capacity()) {
    return StripeResult::kCapacityExceeded;
  }
  StripeExtractor extractor(params, out, kernel);
  extractor.run(pixels, width, height, stride);
  return StripeResult::kOk;
}

}  // namespace cellsight::algo
