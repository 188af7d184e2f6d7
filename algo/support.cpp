// Support plane fit (RANSAC + SVD refinement) and removal.
#include "algo/support.hpp"

#include <Eigen/SVD>
#include <cmath>
#include <string>

#include "algo/splitmix.hpp"

namespace cellsight::algo {
namespace {

Eigen::Vector3d as_vector(const ScanPoint& p) {
  return {p.x, p.y, p.z};
}

}  // namespace

Expected<SupportFit> fit_support_plane(std::span<const ScanPoint> points, const SupportFitParams& params) {
  if (points.size() < params.min_points) {
    return make_error("support: the empty-carrier scan has " + std::to_string(points.size()) + " points, at least " +
                      std::to_string(params.min_points) + " are needed (is the laser on and the carrier in view?)");
  }
  std::uint64_t state = params.seed;
  Plane best;
  std::size_t best_count = 0;
  for (int it = 0; it < params.ransac_iterations; ++it) {
    const Eigen::Vector3d a = as_vector(points[splitmix64(state) % points.size()]);
    const Eigen::Vector3d b = as_vector(points[splitmix64(state) % points.size()]);
    const Eigen::Vector3d c = as_vector(points[splitmix64(state) % points.size()]);
    Eigen::Vector3d n = (b - a).cross(c - a);
    if (n.norm() < 1e-9) continue;
    n.normalize();
    const Plane candidate{n, n.dot(a)};
    std::size_t count = 0;
    for (const ScanPoint& p : points) {
      count += std::abs(candidate.signed_distance(as_vector(p))) < params.inlier_threshold_m ? 1 : 0;
    }
    if (count > best_count) {
      best_count = count;
      best = candidate;
    }
  }
  // Least squares on the consensus set: the plane through the centroid normal to the smallest singular vector.
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  std::size_t n_in = 0;
  for (const ScanPoint& p : points) {
    if (std::abs(best.signed_distance(as_vector(p))) < params.inlier_threshold_m) {
      centroid += as_vector(p);
      ++n_in;
    }
  }
  const double fraction = points.empty() ? 0.0 : static_cast<double>(n_in) / static_cast<double>(points.size());
  if (n_in < 3 || fraction < params.min_inlier_fraction) {
    return make_error("support: no dominant plane in the empty-carrier scan (" + std::to_string(int(fraction * 100)) +
                      " % of points on the best plane); scan the carrier with no part hanging on it");
  }
  centroid /= static_cast<double>(n_in);
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (const ScanPoint& p : points) {
    const Eigen::Vector3d v = as_vector(p);
    if (std::abs(best.signed_distance(v)) < params.inlier_threshold_m)
      scatter += (v - centroid) * (v - centroid).transpose();
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(scatter, Eigen::ComputeFullU);
  Eigen::Vector3d normal = svd.matrixU().col(2);
  if (normal.z() < 0) normal = -normal;
  SupportFit fit;
  fit.plane = {normal, normal.dot(centroid)};
  double sum2 = 0.0;
  for (const ScanPoint& p : points) {
    const double d = fit.plane.signed_distance(as_vector(p));
    if (std::abs(d) < params.inlier_threshold_m) sum2 += d * d;
  }
  fit.inliers = n_in;
  fit.inlier_fraction = fraction;
  fit.rms_m = std::sqrt(sum2 / static_cast<double>(n_in));
  return fit;
}

std::size_t remove_support(ScanBuffer& scan, const Plane& plane, double threshold_m) {
  return scan.filter([&](const ScanPoint& p) { return std::abs(plane.signed_distance(as_vector(p))) >= threshold_m; });
}

}  // namespace cellsight::algo
