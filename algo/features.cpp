// The 74 recognition features (thesis 2.2, 6.4.1): boundaries, FFT cuts, Hu moments, area, eccentricity, histogram.
#include "algo/features.hpp"

#include <algorithm>
#include <bit>
#include <cassert>
#include <cmath>
#include <numbers>

namespace cellsight::algo {

namespace {

constexpr double kDepthLevels = 255.0;  // depth image: 1..255 over the grid depth (grid.hpp)

// Thesis 2.2.2.1: the Hamming window tapers both ends of the cut (to 0.08) against leakage.
double hamming(int n, int count) {
  constexpr double kA0 = 0.54, kA1 = 0.46;
  return kA0 - kA1 * std::cos(2.0 * std::numbers::pi * n / (count - 1));
}

}  // namespace

int feature_index(std::string_view name) {
  for (int i = 0; i < kFeatureCount; ++i) {
    if (kFeatureTable[static_cast<std::size_t>(i)].name == name) return i;
  }
  return -1;
}

FeatureParams feature_params_for(const GridSpec& spec) {
  FeatureParams p;
  p.cell_m = spec.resolution_m;
  p.depth_full_scale_m = spec.nz * spec.resolution_m;
  return p;
}

std::string_view to_string(FeatureStatus status) {
  switch (status) {
    case FeatureStatus::kOk: return "ok";
    case FeatureStatus::kEmptyImage: return "empty depth image (no occupied pixel)";
    case FeatureStatus::kWrongImage: return "depth image is not CV_8UC1 of the extractor's size";
  }
  return "unknown";
}

// ---- FFT ----------------------------------------------------------------------------------------------------

RadixTwoFft::RadixTwoFft(int size) : size_(size) {
  assert(size >= 2 && std::has_single_bit(static_cast<unsigned>(size)));
  twiddles_.resize(static_cast<std::size_t>(size / 2));
  for (int k = 0; k < size / 2; ++k) {
    twiddles_[static_cast<std::size_t>(k)] = std::polar(1.0, -2.0 * std::numbers::pi * k / size);
  }
  const int bits = std::countr_zero(static_cast<unsigned>(size));
  reversed_.resize(static_cast<std::size_t>(size));
  for (int i = 0; i < size; ++i) {
    int r = 0;
    for (int b = 0; b < bits; ++b) r |= ((i >> b) & 1) << (bits - 1 - b);
    reversed_[static_cast<std::size_t>(i)] = r;
  }
}

void RadixTwoFft::transform(std::span<std::complex<double>> data) const {
  assert(static_cast<int>(data.size()) == size_);
  const auto n = static_cast<std::size_t>(size_);
  for (std::size_t i = 0; i < n; ++i) {
    const auto j = static_cast<std::size_t>(reversed_[i]);
    if (i < j) std::swap(data[i], data[j]);
  }
  // Cooley-Tukey butterflies, decimation in time.
  for (std::size_t len = 2; len <= n; len <<= 1) {
    const std::size_t half = len / 2, stride = n / len;
    for (std::size_t start = 0; start < n; start += len) {
      for (std::size_t j = 0; j < half; ++j) {
        const std::complex<double> u = data[start + j];
        const std::complex<double> v = data[start + j + half] * twiddles_[j * stride];
        data[start + j] = u + v;
        data[start + j + half] = u - v;
      }
    }
  }
}

// ---- one cut --------------------------------------------------------------------------------------------------

CutAnalyser::CutAnalyser(int max_samples)
    : fft_(static_cast<int>(std::bit_ceil(static_cast<unsigned>(std::max(max_samples, 2))))),
      spectrum_(static_cast<std::size_t>(fft_.size())),
      magnitude_(static_cast<std::size_t>(fft_.size() / 2 + 1), 0.0) {}

SpectralPeak CutAnalyser::analyse(std::span<const double> profile_m, double spacing_m) {
  const int n = static_cast<int>(profile_m.size());
  std::fill(magnitude_.begin(), magnitude_.end(), 0.0);
  if (n < kMinSamples || n > fft_.size() || !(spacing_m > 0.0)) return {};

  // Thesis 6.4.1.3: the part hangs slightly tilted, so the DC level drifts along the cut; a least-squares line
  // (not just the mean) is the "DC component" removed.
  const double n_mean = 0.5 * (n - 1);
  double d_mean = 0.0;
  for (double d : profile_m) d_mean += d;
  d_mean /= n;
  double sxy = 0.0;
  for (int i = 0; i < n; ++i) sxy += (i - n_mean) * profile_m[static_cast<std::size_t>(i)];
  const double sxx = n * (static_cast<double>(n) * n - 1.0) / 12.0;  // sum (i - mean)^2
  const double slope = sxy / sxx;
  const double intercept = d_mean - slope * n_mean;

  double window_sum = 0.0;
  for (int i = 0; i < n; ++i) {
    const double w = hamming(i, n);
    window_sum += w;
    const double residual = profile_m[static_cast<std::size_t>(i)] - (intercept + slope * i);
    spectrum_[static_cast<std::size_t>(i)] = {residual * w, 0.0};
  }
  std::fill(spectrum_.begin() + n, spectrum_.end(), std::complex<double>{});  // zero padding to 2^N
  fft_.transform(spectrum_);

  SpectralPeak peak;
  double best = -1.0;
  const int half = fft_.size() / 2;
  for (int k = 0; k <= half; ++k) {
    const double m = std::abs(spectrum_[static_cast<std::size_t>(k)]);
    magnitude_[static_cast<std::size_t>(k)] = m;
    if (k >= 1 && m > best) {  // k = 0 is DC: excluded (6.4.1.3)
      best = m;
      peak.bin = k;
    }
  }
  peak.amplitude_m = 2.0 * best / window_sum;  // undo the window's coherent gain: a sine of amplitude A reads A
  peak.frequency_cpm = peak.bin / (fft_.size() * spacing_m);  // eq. 6.1 with Fs = 1 / cell
  return peak;
}

// ---- Hu ---------------------------------------------------------------------------------------------------------

std::array<double, 8> hu_invariants(const NormalisedMoments& e) {
  const double t0 = e.eta30 + e.eta12, t1 = e.eta21 + e.eta03;
  const double q0 = e.eta30 - 3.0 * e.eta12, q1 = 3.0 * e.eta21 - e.eta03;
  const double d = e.eta20 - e.eta02;
  std::array<double, 8> i{};
  i[0] = e.eta20 + e.eta02;                                                          // I1
  i[1] = d * d + 4.0 * e.eta11 * e.eta11;                                            // I2
  i[2] = q0 * q0 + q1 * q1;                                                          // I3
  i[3] = t0 * t0 + t1 * t1;                                                          // I4
  i[4] = q0 * t0 * (t0 * t0 - 3.0 * t1 * t1) + q1 * t1 * (3.0 * t0 * t0 - t1 * t1);  // I5
  i[5] = d * (t0 * t0 - t1 * t1) + 4.0 * e.eta11 * t0 * t1;                          // I6
  i[6] = q1 * t0 * (t0 * t0 - 3.0 * t1 * t1) - q0 * t1 * (3.0 * t0 * t0 - t1 * t1);  // I7
  i[7] = e.eta11 * (t0 * t0 - t1 * t1) - d * t0 * t1;                                // I8, the thesis's eighth
  return i;
}

// ---- extractor --------------------------------------------------------------------------------------------------

FeatureExtractor::FeatureExtractor(int rows, int cols, const FeatureParams& params)
    : rows_(rows),
      cols_(cols),
      params_(params),
      row_left_(static_cast<std::size_t>(rows)),
      row_right_(static_cast<std::size_t>(rows)),
      col_top_(static_cast<std::size_t>(cols)),
      col_bottom_(static_cast<std::size_t>(cols)),
      profile_m_(static_cast<std::size_t>(std::max(rows, cols))),
      analyser_(std::max(rows, cols)) {}

namespace {

// What one pass over the depth image gathers: the raw grey moments m_pq (eq. 2.2, the depth value is the density
// f(x, y), x = column, y = row as in cv::moments) and the occupied pixels' binary moments (their covariance gives the
// eccentricity).
struct ImageMoments {
  double m00, m10, m01, m20, m11, m02, m30, m21, m12, m03;
  double b0, bx, by, bxx, bxy, byy;
};

// The one pass. It also fills the histogram of the object's depth values (eq. 2.12-2.13) and records per row the
// first and last occupied column and per column the first and last occupied row (thesis 6.4.1.2's limits). The
// moments accumulate per row in exact integers, then in double.
ImageMoments accumulate_moments(const cv::Mat& image, std::array<std::uint32_t, 256>& histogram,
                                std::vector<int>& row_left, std::vector<int>& row_right, std::vector<int>& col_top,
                                std::vector<int>& col_bottom) {
  const int rows = image.rows, cols = image.cols;
  std::fill(row_left.begin(), row_left.end(), cols);
  std::fill(row_right.begin(), row_right.end(), -1);
  std::fill(col_top.begin(), col_top.end(), rows);
  std::fill(col_bottom.begin(), col_bottom.end(), -1);
  double m00 = 0, m10 = 0, m01 = 0, m20 = 0, m11 = 0, m02 = 0, m30 = 0, m21 = 0, m12 = 0, m03 = 0;
  double b0 = 0, bx = 0, by = 0, bxx = 0, bxy = 0, byy = 0;
  for (int y = 0; y < rows; ++y) {
    const std::uint8_t* p = image.ptr<std::uint8_t>(y);
    std::int64_t s0 = 0, s1 = 0, s2 = 0, s3 = 0, c0 = 0, c1 = 0, c2 = 0;
    int left = cols, right = -1;
    for (int x = 0; x < cols; ++x) {
      const std::int64_t v = p[x];
      if (v == 0) continue;
      const std::int64_t xv = x * v, xx = static_cast<std::int64_t>(x) * x;
      s0 += v;
      s1 += xv;
      s2 += xv * x;
      s3 += xv * xx;
      ++c0;
      c1 += x;
      c2 += xx;
      ++histogram[static_cast<std::size_t>(v)];
      left = std::min(left, x);
      right = x;
      auto xi = static_cast<std::size_t>(x);
      col_top[xi] = std::min(col_top[xi], y);
      col_bottom[xi] = y;
    }
    if (c0 == 0) continue;
    row_left[static_cast<std::size_t>(y)] = left;
    row_right[static_cast<std::size_t>(y)] = right;
    const double yd = y, yy = yd * yd;
    m00 += s0;
    m10 += s1;
    m20 += s2;
    m30 += s3;
    m01 += s0 * yd;
    m11 += s1 * yd;
    m21 += s2 * yd;
    m02 += s0 * yy;
    m12 += s1 * yy;
    m03 += s0 * yy * yd;
    b0 += c0;
    bx += c1;
    bxx += c2;
    by += c0 * yd;
    bxy += c1 * yd;
    byy += c0 * yy;
  }
  return {m00, m10, m01, m20, m11, m02, m30, m21, m12, m03, b0, bx, by, bxx, bxy, byy};
}

// Eq. 2.3-2.4 central moments from the raw ones (the same expansion cv::moments uses), eq. 2.7 normalisation.
NormalisedMoments normalised_moments(const ImageMoments& m) {
  const double cx = m.m10 / m.m00, cy = m.m01 / m.m00;
  const double mu20 = m.m20 - m.m10 * cx, mu11 = m.m11 - m.m10 * cy, mu02 = m.m02 - m.m01 * cy;
  const double mu30 = m.m30 - cx * (3.0 * mu20 + cx * m.m10);
  const double mu21 = m.m21 - cx * (2.0 * mu11 + cx * m.m01) - cy * mu20;
  const double mu12 = m.m12 - cy * (2.0 * mu11 + cy * m.m10) - cx * mu02;
  const double mu03 = m.m03 - cy * (3.0 * mu02 + cy * m.m01);
  const double n2 = 1.0 / (m.m00 * m.m00), n3 = n2 / std::sqrt(m.m00);  // m00^-(p+q)/2-1 for p+q = 2 and 3
  return {mu20 * n2, mu11 * n2, mu02 * n2, mu30 * n3, mu21 * n3, mu12 * n3, mu03 * n3};
}

// Eccentricity (2.2.1, after eq. 2.6): sqrt(1 - l2/l1) of the covariance J of the occupied pixels (eq. 2.5 with
// f = 1 on the object), so it describes the silhouette, not the depth shading.
float silhouette_eccentricity(const ImageMoments& m) {
  const double b0 = m.b0;
  const double vx = m.bxx / b0 - (m.bx / b0) * (m.bx / b0);
  const double vy = m.byy / b0 - (m.by / b0) * (m.by / b0);
  const double cxy = m.bxy / b0 - (m.bx / b0) * (m.by / b0);
  const double mid = 0.5 * (vx + vy), radius = std::sqrt(0.25 * (vx - vy) * (vx - vy) + cxy * cxy);
  const double l1 = mid + radius, l2 = std::max(0.0, mid - radius);
  return l1 > 0.0 ? static_cast<float>(std::sqrt(std::max(0.0, 1.0 - l2 / l1))) : 0.0F;
}

// Eq. 2.12-2.13 on the normalised histogram of the object's depth values (the empty background is left out: it
// would only repeat the area).
void write_histogram_features(const std::array<std::uint32_t, 256>& histogram, double b0, FeatureVector& out) {
  double energy = 0.0, entropy = 0.0;
  for (std::size_t v = 1; v < histogram.size(); ++v) {
    if (histogram[v] == 0) continue;
    const double h = histogram[v] / b0;
    energy += h * h;
    entropy -= h * std::log2(h);
  }
  out[kHistEnergyIndex] = static_cast<float>(energy);
  out[kHistEntropyIndex] = static_cast<float>(entropy);
}

}  // namespace

FeatureStatus FeatureExtractor::compute(const cv::Mat& image, FeatureVector& out) {
  out.fill(0.0F);
  if (image.type() != CV_8UC1 || image.rows != rows_ || image.cols != cols_ || rows_ <= 0) {
    return FeatureStatus::kWrongImage;
  }
  std::array<std::uint32_t, 256> histogram{};
  const ImageMoments m = accumulate_moments(image, histogram, row_left_, row_right_, col_top_, col_bottom_);
  if (m.b0 == 0) {
    bounds_ = {};
    return FeatureStatus::kEmptyImage;
  }

  // Thesis 6.4.1.2: width and height are the mean distance between the left/right (top/bottom) limits.
  find_bounds();
  out[kWidthIndex] = static_cast<float>(bounds_.mean_row_extent_px * params_.cell_m);
  out[kHeightIndex] = static_cast<float>(bounds_.mean_col_extent_px * params_.cell_m);

  compute_cuts(image, out);

  const std::array<double, 8> hu = hu_invariants(normalised_moments(m));
  for (std::size_t i = 0; i < hu.size(); ++i) out[static_cast<std::size_t>(kHuIndex) + i] = static_cast<float>(hu[i]);

  out[kAreaIndex] = static_cast<float>(m.b0 * params_.cell_m * params_.cell_m);
  out[kEccentricityIndex] = silhouette_eccentricity(m);
  write_histogram_features(histogram, m.b0, out);
  return FeatureStatus::kOk;
}

void FeatureExtractor::find_bounds() {
  ObjectBounds b;
  b.top = rows_;
  b.left = cols_;
  double row_sum = 0.0, col_sum = 0.0;
  int row_count = 0, col_count = 0;
  for (int y = 0; y < rows_; ++y) {
    const auto yi = static_cast<std::size_t>(y);
    if (row_right_[yi] < 0) continue;
    b.top = std::min(b.top, y);
    b.bottom = y;
    row_sum += row_right_[yi] - row_left_[yi] + 1;
    ++row_count;
  }
  for (int x = 0; x < cols_; ++x) {
    const auto xi = static_cast<std::size_t>(x);
    if (col_bottom_[xi] < 0) continue;
    b.left = std::min(b.left, x);
    b.right = x;
    col_sum += col_bottom_[xi] - col_top_[xi] + 1;
    ++col_count;
  }
  b.mean_row_extent_px = row_count > 0 ? row_sum / row_count : 0.0;
  b.mean_col_extent_px = col_count > 0 ? col_sum / col_count : 0.0;
  bounds_ = b;
}

void FeatureExtractor::compute_cuts(const cv::Mat& image, FeatureVector& out) {
  // Thesis 6.4.1.2, Fig. 6.11: 15 cuts per direction, evenly spaced strictly inside the object's limits. A cut runs
  // between that row's (column's) own left and right (top and bottom) boundary, the limits 6.4.1.2 computes for
  // every line: the empty corners of a turned part stay out of the spectrum, holes inside read as depth 0.
  const double to_m = params_.depth_full_scale_m / kDepthLevels;
  constexpr int kSlots = kCutsPerDirection + 1;
  const int height = bounds_.bottom - bounds_.top, width = bounds_.right - bounds_.left;
  std::span<double> profile(profile_m_);
  auto store = [&](int index, const SpectralPeak& peak) {
    out[static_cast<std::size_t>(index)] = static_cast<float>(peak.amplitude_m);
    out[static_cast<std::size_t>(index) + 1] = static_cast<float>(peak.frequency_cpm);
  };
  for (int k = 0; k < kCutsPerDirection; ++k) {
    const int row = bounds_.top + ((k + 1) * height + kSlots / 2) / kSlots;
    horizontal_cuts_[static_cast<std::size_t>(k)] = row;
    const int left = row_left_[static_cast<std::size_t>(row)], right = row_right_[static_cast<std::size_t>(row)];
    const int n = std::max(0, right - left + 1);  // 0 when the row is empty: no peak
    const std::uint8_t* p = image.ptr<std::uint8_t>(row);
    for (int i = 0; i < n; ++i) profile[static_cast<std::size_t>(i)] = p[left + i] * to_m;
    store(kHorizontalCutIndex + 2 * k, analyser_.analyse(profile.first(static_cast<std::size_t>(n)), params_.cell_m));
  }
  for (int k = 0; k < kCutsPerDirection; ++k) {
    const int col = bounds_.left + ((k + 1) * width + kSlots / 2) / kSlots;
    vertical_cuts_[static_cast<std::size_t>(k)] = col;
    const int top = col_top_[static_cast<std::size_t>(col)], bottom = col_bottom_[static_cast<std::size_t>(col)];
    const int n = std::max(0, bottom - top + 1);
    for (int i = 0; i < n; ++i) profile[static_cast<std::size_t>(i)] = image.ptr<std::uint8_t>(top + i)[col] * to_m;
    store(kVerticalCutIndex + 2 * k, analyser_.analyse(profile.first(static_cast<std::size_t>(n)), params_.cell_m));
  }
}

}  // namespace cellsight::algo
