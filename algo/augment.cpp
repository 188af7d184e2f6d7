// Synthetic training variants: re-pose, thinning, dropouts, a missing band, extra noise.
#include "algo/augment.hpp"

#include <algorithm>
#include <cmath>
#include <random>

namespace cellsight::algo {

namespace {

struct Disc {
  double x, y, r2;
};

}  // namespace

void augment_scan(std::span<const ScanPoint> in, const AugmentParams& params, std::uint64_t seed,
                  std::vector<ScanPoint>& out) {
  out.clear();
  if (in.empty()) return;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const auto uniform = [&](double lo, double hi) { return lo + (hi - lo) * unit(rng); };

  double cx = 0.0, cy = 0.0, cz = 0.0, x_lo = in[0].x, x_hi = in[0].x, y_lo = in[0].y, y_hi = in[0].y;
  for (const ScanPoint& p : in) {
    cx += p.x;
    cy += p.y;
    cz += p.z;
    x_lo = std::min<double>(x_lo, p.x);
    x_hi = std::max<double>(x_hi, p.x);
    y_lo = std::min<double>(y_lo, p.y);
    y_hi = std::max<double>(y_hi, p.y);
  }
  const double n = static_cast<double>(in.size());
  cx /= n;
  cy /= n;
  cz /= n;

  // Every random draw happens here, in a fixed order, so a variant depends on the seed alone.
  const double tx = uniform(-params.shift_m, params.shift_m), ty = uniform(-params.shift_m, params.shift_m);
  const double turn = uniform(-params.turn_rad, params.turn_rad);
  const double swing = uniform(-params.swing_rad, params.swing_rad);
  const double keep = uniform(std::clamp(params.keep_min, 0.0, 1.0), 1.0);
  const double noise_m = uniform(0.0, params.noise_max_m);
  std::vector<Disc> discs(
      static_cast<std::size_t>(std::uniform_int_distribution<int>(0, std::max(0, params.dropouts_max))(rng)));
  for (Disc& d : discs) {
    const ScanPoint& at = in[std::uniform_int_distribution<std::size_t>(0, in.size() - 1)(rng)];
    const double r = uniform(params.dropout_radius_min_m, params.dropout_radius_max_m);
    d = {at.x, at.y, r * r};
  }
  const bool band = unit(rng) < params.band_probability;
  const bool band_along_x = unit(rng) < 0.5;  // missing profiles (constant x) or rows (constant y)
  const double band_centre = band_along_x ? uniform(x_lo, x_hi) : uniform(y_lo, y_hi);
  const double band_half = 0.5 * uniform(params.band_width_min_m, params.band_width_max_m);
  std::normal_distribution<double> gauss(0.0, 1.0);

  const double cs = std::cos(swing), ss = std::sin(swing), ct = std::cos(turn), st = std::sin(turn);
  out.reserve(in.size());
  for (const ScanPoint& p : in) {
    if (unit(rng) >= keep) continue;
    if (band && std::abs((band_along_x ? p.x : p.y) - band_centre) < band_half) continue;
    bool dropped = false;
    for (const Disc& d : discs) {
      const double dx = p.x - d.x, dy = p.y - d.y;
      dropped = dropped || dx * dx + dy * dy < d.r2;
    }
    if (dropped) continue;
    // Swing about the vertical (y) axis through the centroid, then the in-plane turn about it, then the shift.
    const double dx = p.x - cx, dy = p.y - cy, dz = p.z - cz;
    const double sx = cs * dx + ss * dz, sz = -ss * dx + cs * dz;
    ScanPoint q = p;
    q.x = static_cast<float>(cx + ct * sx - st * dy + tx);
    q.y = static_cast<float>(cy + st * sx + ct * dy + ty);
    q.z = static_cast<float>(cz + sz + noise_m * gauss(rng));
    out.push_back(q);
  }
}

}  // namespace cellsight::algo
