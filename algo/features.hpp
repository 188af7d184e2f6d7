// The 74 recognition features of the thesis (6.4.1.5) from a part's depth image, allocation-free after start-up.
#pragma once

#include <array>
#include <bitset>
#include <complex>
#include <cstdint>
#include <opencv2/core.hpp>
#include <span>
#include <string_view>
#include <vector>

#include "algo/grid.hpp"

namespace cellsight::algo {

inline constexpr int kFeatureCount = 74;
// Bump whenever a feature's definition, order or units change: a model trained on another version is refused.
inline constexpr std::uint32_t kFeatureVersion = 2;  // 2: computed in the part's own frame (algo/canonical)
inline constexpr int kCutsPerDirection = 15;         // thesis 6.4.1.2: 15 horizontal and 15 vertical cuts

using FeatureVector = std::array<float, kFeatureCount>;
using FeatureMask = std::bitset<kFeatureCount>;  // bit i set: feature i is active (thesis 2.6.1, vector s)

// Where each group starts in a FeatureVector (the order of kFeatureTable).
inline constexpr int kWidthIndex = 0;
inline constexpr int kHeightIndex = 1;
inline constexpr int kHorizontalCutIndex = 2;  // cut k: amplitude at 2 + 2k, frequency at 3 + 2k
inline constexpr int kVerticalCutIndex = kHorizontalCutIndex + 2 * kCutsPerDirection;  // 32
inline constexpr int kHuIndex = kVerticalCutIndex + 2 * kCutsPerDirection;             // 62: I1..I8
inline constexpr int kAreaIndex = kHuIndex + 8;                                        // 70
inline constexpr int kEccentricityIndex = 71;
inline constexpr int kHistEnergyIndex = 72;
inline constexpr int kHistEntropyIndex = 73;

struct FeatureInfo {
  std::string_view name;  // stable identifier, stored in model files
  std::string_view unit;
  std::string_view definition;  // thesis section / equation
  bool heavy_tailed;            // spans many decades and changes sign: the scaler compresses it (asinh) first
};

// The fixed order of the 74 features.
inline constexpr std::array<FeatureInfo, kFeatureCount> kFeatureTable = {{
    {"width_m", "m", "6.4.1.2: mean left-right extent of the occupied rows", false},
    {"height_m", "m", "6.4.1.2: mean top-bottom extent of the occupied columns", false},
    {"hcut00_amp_m", "m", "6.4.1.3: horizontal cut 0, largest non-DC peak, amplitude", false},
    {"hcut00_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 0, largest non-DC peak, frequency", false},
    {"hcut01_amp_m", "m", "6.4.1.3: horizontal cut 1, largest non-DC peak, amplitude", false},
    {"hcut01_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 1, largest non-DC peak, frequency", false},
    {"hcut02_amp_m", "m", "6.4.1.3: horizontal cut 2, largest non-DC peak, amplitude", false},
    {"hcut02_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 2, largest non-DC peak, frequency", false},
    {"hcut03_amp_m", "m", "6.4.1.3: horizontal cut 3, largest non-DC peak, amplitude", false},
    {"hcut03_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 3, largest non-DC peak, frequency", false},
    {"hcut04_amp_m", "m", "6.4.1.3: horizontal cut 4, largest non-DC peak, amplitude", false},
    {"hcut04_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 4, largest non-DC peak, frequency", false},
    {"hcut05_amp_m", "m", "6.4.1.3: horizontal cut 5, largest non-DC peak, amplitude", false},
    {"hcut05_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 5, largest non-DC peak, frequency", false},
    {"hcut06_amp_m", "m", "6.4.1.3: horizontal cut 6, largest non-DC peak, amplitude", false},
    {"hcut06_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 6, largest non-DC peak, frequency", false},
    {"hcut07_amp_m", "m", "6.4.1.3: horizontal cut 7, largest non-DC peak, amplitude", false},
    {"hcut07_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 7, largest non-DC peak, frequency", false},
    {"hcut08_amp_m", "m", "6.4.1.3: horizontal cut 8, largest non-DC peak, amplitude", false},
    {"hcut08_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 8, largest non-DC peak, frequency", false},
    {"hcut09_amp_m", "m", "6.4.1.3: horizontal cut 9, largest non-DC peak, amplitude", false},
    {"hcut09_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 9, largest non-DC peak, frequency", false},
    {"hcut10_amp_m", "m", "6.4.1.3: horizontal cut 10, largest non-DC peak, amplitude", false},
    {"hcut10_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 10, largest non-DC peak, frequency", false},
    {"hcut11_amp_m", "m", "6.4.1.3: horizontal cut 11, largest non-DC peak, amplitude", false},
    {"hcut11_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 11, largest non-DC peak, frequency", false},
    {"hcut12_amp_m", "m", "6.4.1.3: horizontal cut 12, largest non-DC peak, amplitude", false},
    {"hcut12_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 12, largest non-DC peak, frequency", false},
    {"hcut13_amp_m", "m", "6.4.1.3: horizontal cut 13, largest non-DC peak, amplitude", false},
    {"hcut13_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 13, largest non-DC peak, frequency", false},
    {"hcut14_amp_m", "m", "6.4.1.3: horizontal cut 14, largest non-DC peak, amplitude", false},
    {"hcut14_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: horizontal cut 14, largest non-DC peak, frequency", false},
    {"vcut00_amp_m", "m", "6.4.1.3: vertical cut 0, largest non-DC peak, amplitude", false},
    {"vcut00_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 0, largest non-DC peak, frequency", false},
    {"vcut01_amp_m", "m", "6.4.1.3: vertical cut 1, largest non-DC peak, amplitude", false},
    {"vcut01_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 1, largest non-DC peak, frequency", false},
    {"vcut02_amp_m", "m", "6.4.1.3: vertical cut 2, largest non-DC peak, amplitude", false},
    {"vcut02_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 2, largest non-DC peak, frequency", false},
    {"vcut03_amp_m", "m", "6.4.1.3: vertical cut 3, largest non-DC peak, amplitude", false},
    {"vcut03_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 3, largest non-DC peak, frequency", false},
    {"vcut04_amp_m", "m", "6.4.1.3: vertical cut 4, largest non-DC peak, amplitude", false},
    {"vcut04_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 4, largest non-DC peak, frequency", false},
    {"vcut05_amp_m", "m", "6.4.1.3: vertical cut 5, largest non-DC peak, amplitude", false},
    {"vcut05_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 5, largest non-DC peak, frequency", false},
    {"vcut06_amp_m", "m", "6.4.1.3: vertical cut 6, largest non-DC peak, amplitude", false},
    {"vcut06_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 6, largest non-DC peak, frequency", false},
    {"vcut07_amp_m", "m", "6.4.1.3: vertical cut 7, largest non-DC peak, amplitude", false},
    {"vcut07_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 7, largest non-DC peak, frequency", false},
    {"vcut08_amp_m", "m", "6.4.1.3: vertical cut 8, largest non-DC peak, amplitude", false},
    {"vcut08_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 8, largest non-DC peak, frequency", false},
    {"vcut09_amp_m", "m", "6.4.1.3: vertical cut 9, largest non-DC peak, amplitude", false},
    {"vcut09_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 9, largest non-DC peak, frequency", false},
    {"vcut10_amp_m", "m", "6.4.1.3: vertical cut 10, largest non-DC peak, amplitude", false},
    {"vcut10_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 10, largest non-DC peak, frequency", false},
    {"vcut11_amp_m", "m", "6.4.1.3: vertical cut 11, largest non-DC peak, amplitude", false},
    {"vcut11_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 11, largest non-DC peak, frequency", false},
    {"vcut12_amp_m", "m", "6.4.1.3: vertical cut 12, largest non-DC peak, amplitude", false},
    {"vcut12_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 12, largest non-DC peak, frequency", false},
    {"vcut13_amp_m", "m", "6.4.1.3: vertical cut 13, largest non-DC peak, amplitude", false},
    {"vcut13_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 13, largest non-DC peak, frequency", false},
    {"vcut14_amp_m", "m", "6.4.1.3: vertical cut 14, largest non-DC peak, amplitude", false},
    {"vcut14_freq_cpm", "1/m", "6.4.1.3 eq. 6.1: vertical cut 14, largest non-DC peak, frequency", false},
    {"hu1", "", "2.2.1 I1 of the depth image (eq. 2.2-2.7)", false},
    {"hu2", "", "2.2.1 I2 of the depth image (eq. 2.2-2.7)", false},
    {"hu3", "", "2.2.1 I3 of the depth image (eq. 2.2-2.7)", true},
    {"hu4", "", "2.2.1 I4 of the depth image (eq. 2.2-2.7)", true},
    {"hu5", "", "2.2.1 I5 of the depth image (eq. 2.2-2.7)", true},
    {"hu6", "", "2.2.1 I6 of the depth image (eq. 2.2-2.7)", true},
    {"hu7", "", "2.2.1 I7 of the depth image (eq. 2.2-2.7)", true},
    {"hu8", "", "2.2.1 I8 of the depth image (eq. 2.2-2.7)", true},
    {"area_m2", "m2", "6.4.1.4: occupied pixels x cell^2", false},
    {"eccentricity", "", "2.2.1: sqrt(1 - l2/l1) of the occupied-pixel covariance (eq. 2.5)", false},
    {"hist_energy", "", "eq. 2.12 on the occupied depth histogram", false},
    {"hist_entropy_bits", "bit", "eq. 2.13 on the occupied depth histogram", false},
}};

static_assert(kHistEntropyIndex + 1 == kFeatureCount, "feature groups must fill the table exactly");

[[nodiscard]] constexpr std::string_view feature_name(int index) {
  return kFeatureTable[static_cast<std::size_t>(index)].name;
}
// Index of a feature name, or -1.
[[nodiscard]] int feature_index(std::string_view name);

struct FeatureParams {
  double cell_m = 0.0022;              // pixel pitch of the depth image = grid resolution
  double depth_full_scale_m = 0.4004;  // depth-image value 255 stands for this depth (grid nz x resolution)
};
[[nodiscard]] FeatureParams feature_params_for(const GridSpec& spec);

// In-place iterative radix-2 FFT of a fixed power-of-two size. Own code rather than cv::dft because the thesis
// FFT needs 2^N samples anyway (2.2.2.2) and cv::dft's scratch (AutoBuffer -> fastMalloc) would put a heap call
// in every scan; here the twiddles and bit-reversal table are built once and transform() never allocates.
class RadixTwoFft {
 public:
  RadixTwoFft() = default;
  explicit RadixTwoFft(int size);  // start-up: allocates; size must be a power of two >= 2
  // Forward DFT of eq. 2.10: X[k] = sum x[n] exp(-j 2 pi k n / N); data.size() must equal size().
  void transform(std::span<std::complex<double>> data) const;
  [[nodiscard]] int size() const { return size_; }

 private:
  int size_ = 0;
  std::vector<std::complex<double>> twiddles_;  // exp(-j 2 pi k / N), k < N/2
  std::vector<int> reversed_;                   // bit-reversed index of each position
};

// The largest non-DC peak of one cut's spectrum (thesis 6.4.1.3).
struct SpectralPeak {
  double amplitude_m = 0.0;    // 2 |X[k]| / sum(window): the amplitude of a sinusoid at that frequency, metres
  double frequency_cpm = 0.0;  // eq. 6.1: k Fs / N with Fs = 1 / cell, in cycles per metre
  int bin = 0;                 // k; 0 when the cut was too short to analyse
};

// Depth profile -> linear-regression trend removal -> Hamming window -> zero padding to the FFT size -> FFT ->
// largest peak with k >= 1. Holds the scratch for the longest cut; analyse() does not allocate.
class CutAnalyser {
 public:
  static constexpr int kMinSamples = 8;  // shorter cuts (slivers) carry no pattern: peak 0

  CutAnalyser() = default;
  explicit CutAnalyser(int max_samples);  // start-up: FFT size = smallest power of two >= max_samples
  [[nodiscard]] SpectralPeak analyse(std::span<const double> profile_m, double spacing_m);
  [[nodiscard]] int fft_size() const { return fft_.size(); }
  // |X[k]| of the last analysed cut, k = 0 .. fft_size()/2 (for plots and tests).
  [[nodiscard]] std::span<const double> magnitude() const { return magnitude_; }

 private:
  RadixTwoFft fft_;
  std::vector<std::complex<double>> spectrum_;
  std::vector<double> magnitude_;
};

// Object limits found on the depth image (thesis 6.4.1.2), pixel indices (row 0 = top).
struct ObjectBounds {
  int top = 0, bottom = -1, left = 0, right = -1;  // bounding box of the occupied pixels; empty when bottom < top
  double mean_row_extent_px = 0.0;                 // mean over occupied rows of (right - left + 1)
  double mean_col_extent_px = 0.0;                 // mean over occupied columns of (bottom - top + 1)
  [[nodiscard]] bool empty() const { return bottom < top; }
};

enum class FeatureStatus : std::uint8_t {
  kOk,
  kEmptyImage,  // no occupied pixel: nothing to describe
  kWrongImage,  // not CV_8UC1 of the size the extractor was built for
};
[[nodiscard]] std::string_view to_string(FeatureStatus status);

// Computes the 74 features of one depth image (OccupancyGrid::depth_image: row 0 at the top, 0 = empty,
// 1..255 = front-most depth). Sized once for the image; compute() reuses its buffers and never allocates.
// Not thread-safe: one extractor per thread.
class FeatureExtractor {
 public:
  FeatureExtractor() = default;
  FeatureExtractor(int rows, int cols, const FeatureParams& params);  // start-up: allocates

  [[nodiscard]] FeatureStatus compute(const cv::Mat& depth_image, FeatureVector& out);

  [[nodiscard]] const ObjectBounds& bounds() const { return bounds_; }
  [[nodiscard]] int rows() const { return rows_; }
  [[nodiscard]] int cols() const { return cols_; }
  [[nodiscard]] const FeatureParams& params() const { return params_; }
  // Row (horizontal cut) or column (vertical cut) index of cut k of the last compute().
  [[nodiscard]] int cut_position(bool horizontal, int k) const {
    return (horizontal ? horizontal_cuts_ : vertical_cuts_)[static_cast<std::size_t>(k)];
  }

 private:
  void find_bounds();
  void compute_cuts(const cv::Mat& image, FeatureVector& out);

  int rows_ = 0, cols_ = 0;
  FeatureParams params_{};
  ObjectBounds bounds_{};
  std::vector<int> row_left_, row_right_, col_top_, col_bottom_;
  std::vector<double> profile_m_;
  CutAnalyser analyser_;
  std::array<int, kCutsPerDirection> horizontal_cuts_{}, vertical_cuts_{};
};

// Hu's seven invariants plus the thesis's eighth (2.2.1) from the normalised central moments eta_pq.
struct NormalisedMoments {
  double eta20, eta11, eta02, eta30, eta21, eta12, eta03;
};
[[nodiscard]] std::array<double, 8> hu_invariants(const NormalisedMoments& eta);

}  // namespace cellsight::algo
