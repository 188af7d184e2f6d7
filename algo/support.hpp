// Carrier ("support") removal (thesis 6.4.1.1): a plane fitted once on an empty-carrier scan, then every scan
// loses the points within a threshold of it.
#pragma once

#include <cstdint>
#include <span>

#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"

namespace cellsight::algo {

struct SupportFitParams {
  double inlier_threshold_m = 0.002;  // RANSAC consensus band
  int ransac_iterations = 500;
  std::uint64_t seed = 1;            // deterministic sampling
  std::size_t min_points = 500;      // an empty-carrier scan with fewer points is refused
  double min_inlier_fraction = 0.6;  // the carrier must dominate its own scan
};

struct SupportFit {
  Plane plane;
  double rms_m = 0.0;  // of the inliers, after the least-squares refinement
  double inlier_fraction = 0.0;
  std::size_t inliers = 0;
};

// Robust fit: RANSAC on point triples, then least squares (SVD) on the consensus set. The normal points to +z
// (toward the camera) so "in front of the carrier" is a positive distance. Refuses scans that do not show a plane.
[[nodiscard]] Expected<SupportFit> fit_support_plane(std::span<const ScanPoint> empty_carrier,
                                                     const SupportFitParams& params);

// Removes the points within threshold_m of the plane (in place); returns how many were removed.
std::size_t remove_support(ScanBuffer& scan, const Plane& plane, double threshold_m);

}  // namespace cellsight::algo
