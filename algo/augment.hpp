// Synthetic training variants of a taught scan (training only, allocates): the part re-posed within the cell's pose
// range, thinned, with dropouts, a missing band and extra noise, so a dozen taught scans stand for the passes the
// cell will see.
#pragma once

#include <cstdint>
#include <numbers>
#include <span>
#include <vector>

#include "algo/scan.hpp"

namespace cellsight::algo {

struct AugmentParams {
  // Re-pose (DESIGN.md pose: shift and turn about the part's centroid; swing about the vertical axis through it).
  double shift_m = 0.05;
  double turn_rad = 5.0 * std::numbers::pi / 180.0;
  double swing_rad = 2.0 * std::numbers::pi / 180.0;
  // Thinning: each point kept with a probability drawn uniformly in [keep_min, 1] per variant.
  double keep_min = 0.6;
  // Dropouts: up to this many discs (radius uniform in the range) where the stripe was lost.
  int dropouts_max = 6;
  double dropout_radius_min_m = 0.005;
  double dropout_radius_max_m = 0.025;
  // A band of missing profiles (constant x) or rows (constant y), with this probability and width range.
  double band_probability = 0.5;
  double band_width_min_m = 0.004;
  double band_width_max_m = 0.02;
  // Extra depth noise: Gaussian with a standard deviation uniform in [0, noise_max_m].
  double noise_max_m = 0.0008;
};

// One variant of `in` (a part's points, carrier removed, carrier frame) into `out` (replaced); deterministic for
// `seed`.
void augment_scan(std::span<const ScanPoint> in, const AugmentParams& params, std::uint64_t seed,
                  std::vector<ScanPoint>& out);

}  // namespace cellsight::algo
