// Seeded perturbations of raw scans (carrier included): the artefacts a plant's scans have, one cause at a time,
// so a regression of the recogniser is seen per cause (issue 10). Pure and deterministic given the seed; a tool and
// test path (allocates), never the production loop.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "algo/result.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"

namespace cellsight::algo {

// The kinds, in the order they are applied whatever order they are listed in: the scene first (the part swings,
// stray objects appear), then what the sensor loses (glare, resolution, dropout), last its noise on what is left.
// Strength s (default 1) scales the stated default; share is the fraction of scans a kind hits (default 1).
enum class PerturbKind : std::uint8_t {
  // An extra rotation of the part's points about the vertical (y) axis through their x-z centroid, drawn uniform
  // in ±2°·s (right-handed about +y: a point at +x moves toward -z). The carrier is not moved.
  kSwing,
  // A neighbouring carrier's part entering the field of view at the left or right end of the scanned x range: a
  // flat sheet strip (20–80 mm·s wide, 300–700 mm high) at a part's depth in front of the carrier, sampled on the
  // scan's profiles and point spacing along y, at least 15 mm (x-y) from the part; it hides the carrier behind it.
  // Narrowed where the part comes nearer; the other end when the drawn one has no room for two profiles; not
  // applied (PerturbReport::applied) when neither has.
  kStrayEdge,
  // The chain and hook: a 6–10 mm·s wide vertical strip from the part's top edge up to the top of the scan, at the
  // depth of the part's top there; plus 0.2 %·s of the scan's point count as isolated specular outliers anywhere in
  // the scanned x-y range, in front of the carrier up to the part's greatest depth.
  kStrayPoints,
  // Glare: a band 15–35 mm·s wide across the part (through a random part point; vertical, horizontal or oblique,
  // one third each) where a fraction drawn in 90–100 % of the part's points is lost. Carrier points are kept.
  kGlare,
  // A sensor with 1/(1 + round(s)) of the resolution: in each profile (points of one x, sorted by y) only every
  // (1 + round(s))-th point is kept (s = 1: every other point dropped).
  kThin,
  // Lost points: 3 %·s of the scan's points, half of them single points and half short runs (2–6 points) along a
  // profile.
  kDropout,
  // Gaussian noise, sigma 0.35 mm·s along the viewing ray (z) and 0.3 of that in y; x (the encoder) is exact.
  kNoise,
};
inline constexpr std::size_t kPerturbKinds = 7;

struct PerturbSetting {
  bool on = false;
  double strength = 1.0;  // multiplier of the default strength
  double share = 1.0;     // fraction of scans it hits, drawn per scan from the seed
};

struct PerturbSpec {
  std::array<PerturbSetting, kPerturbKinds> kinds{};
  double carrier_band_m = 0.006;  // nearer the carrier plane than this is carrier (config support.distance_threshold)
  std::string text;               // as given, for logs ("none" when nothing is on)

  [[nodiscard]] bool empty() const;
  [[nodiscard]] const PerturbSetting& operator[](PerturbKind k) const { return kinds[static_cast<std::size_t>(k)]; }
  PerturbSetting& operator[](PerturbKind k) { return kinds[static_cast<std::size_t>(k)]; }
};

[[nodiscard]] std::string_view to_string(PerturbKind kind);

// "KIND[:STRENGTH][@SHARE],..." with KIND one of noise, dropout, glare, stray_edge, stray_points, thin, swing, or:
//   mixed  the hard case: noise and dropout on every scan, glare and stray_edge on 30 % of the scans each
//          (mixed:S scales all four; it sets its own shares);
//   none   nothing (a baseline).
// STRENGTH in (0, 10], SHARE in [0, 1]. A kind given twice, or an unknown one, is refused naming the valid kinds.
[[nodiscard]] Expected<PerturbSpec> parse_perturb(std::string_view text);

// Drawn parameters of one call (valid for the kinds with applied[k] set), for logs and tests.
struct PerturbReport {
  std::array<bool, kPerturbKinds> applied{};
  std::size_t points_in = 0, points_out = 0;
  double swing_rad = 0.0;
  Eigen::Vector2d swing_axis_xz = Eigen::Vector2d::Zero();
  struct Strip {  // an added flat strip: x, y extent (metres), signed distance from the carrier
    double x_min_m = 0, x_max_m = 0, y_min_m = 0, y_max_m = 0, depth_m = 0;
    std::size_t points = 0;
  };
  Strip stray_edge;
  bool stray_edge_from_left = false;
  Strip chain;
  std::size_t outliers = 0;
  Eigen::Vector2d glare_centre_xy = Eigen::Vector2d::Zero();
  Eigen::Vector2d glare_normal_xy = Eigen::Vector2d::UnitX();  // |normal . (p - centre)| <= width / 2: in the band
  double glare_width_m = 0.0, glare_loss = 0.0;
  std::size_t glare_removed = 0, thinned = 0, dropped = 0;
  double noise_sigma_z_m = 0.0, noise_sigma_y_m = 0.0;
};

// One line for logs: what each applied kind drew ("nothing applied" when none).
[[nodiscard]] std::string describe(const PerturbReport& report);

// Applies the kinds that are on (each with its own random stream from seed and kind, so adding a kind does not
// change another's draw). Part points are those at least spec.carrier_band_m in front of `support`. A scan with no
// part points is left to the kinds that do not need one (noise, dropout, thin).
PerturbReport perturb_scan(std::vector<ScanPoint>& points, const PerturbSpec& spec, const Plane& support,
                           std::uint64_t seed);

// Points grouped into profiles (one sensor frame each) by their x alone, as in a PLY that lost the frame numbers:
// a new profile starts where sorted x jumps by more than gap_m. Each profile's indices sorted by y.
[[nodiscard]] std::vector<std::vector<std::size_t>> profiles_by_x(const std::vector<ScanPoint>& points, double gap_m);

}  // namespace cellsight::algo
