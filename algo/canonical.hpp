// The part's own frame for the features: a part's points moved so that its x-y centroid sits at the grid centre,
// its in-plane turn is undone and its sheet is levelled, whatever pose and swing it hung in. Allocation-free: the
// caller sizes the scratch and the output once.
#pragma once

#include <cstdint>
#include <numbers>
#include <span>
#include <string_view>
#include <vector>

#include "algo/grid.hpp"
#include "algo/scan.hpp"

namespace cellsight::algo {

struct CanonicalParams {
  // The outline's dominant edge direction is measured modulo 90 deg (so a 90 or 180 deg ambiguity cannot flip the
  // part); a turn beyond this is not believed and clipped to it. The cell hangs parts within +-5 deg.
  double max_turn_rad = 10.0 * std::numbers::pi / 180.0;
  // Sheet plane z = a x + b y + c: RANSAC consensus band, then least squares on the consensus. Planes steeper than
  // max_slope are not hypotheses (a rib's flank is not the sheet; the swing is +-2 deg).
  double level_band_m = 0.003;
  double max_slope = 0.2;
  int level_hypotheses = 64;
  std::size_t level_sample_points = 4000;  // the fit uses an even subsample of at most this many points
  // Where the levelled sheet lands, as a fraction of the grid depth from its back (relief in front keeps its height
  // above the sheet, parts behind it keep their depth below).
  double sheet_depth_fraction = 0.5;
};

// What the mapping found and undid (carrier frame).
struct CanonicalPose {
  double centroid_x_m = 0.0, centroid_y_m = 0.0;        // of the occupied x-y cells
  double turn_rad = 0.0;                                // in-plane turn undone (counter-clockwise seen from +z)
  double measured_turn_rad = 0.0;                       // before the clip to max_turn_rad
  double slope_x = 0.0, slope_y = 0.0, offset_m = 0.0;  // the sheet plane z = slope_x x + slope_y y + offset
  double sheet_inlier_fraction = 0.0;                   // of the fit's subsample within level_band_m
};

enum class CanonicalStatus : std::uint8_t {
  kOk,
  kEmpty,           // no point inside the grid's x-y extent
  kOutputTooSmall,  // out.size() < in.size()
};
[[nodiscard]] std::string_view to_string(CanonicalStatus status);

// Carrier-frame depth z at which the levelled sheet lands.
[[nodiscard]] double canonical_sheet_depth_m(const GridSpec& spec, const CanonicalParams& params);

// Buffers of the mapping, sized once for a grid (allocates; start-up only).
class CanonicalScratch {
 public:
  CanonicalScratch() = default;
  explicit CanonicalScratch(const GridSpec& spec);

 private:
  friend CanonicalStatus canonicalise(std::span<const ScanPoint>, const GridSpec&, const CanonicalParams&,
                                      CanonicalScratch&, std::span<ScanPoint>, CanonicalPose&);
  std::vector<std::uint8_t> mask_;     // x-y occupancy, nx x ny, row iy
  std::vector<std::uint8_t> rows_;     // 3 x 1 box sums of the mask
  std::vector<std::uint8_t> smooth_;   // 3 x 3 box sums of the mask (0 .. 9)
  std::vector<std::uint32_t> sample_;  // indices of the plane fit's subsample
};

// Maps `in` (one part, carrier removed, carrier frame) into its canonical frame, point by point into out[0 ..
// in.size()): p' = R_z(-turn) (p_xy - centroid) + grid x-y centre, z' = z - (slope_x x + slope_y y + offset) +
// sheet depth. frame and row are kept. Never allocates.
[[nodiscard]] CanonicalStatus canonicalise(std::span<const ScanPoint> in, const GridSpec& spec,
                                           const CanonicalParams& params, CanonicalScratch& scratch,
                                           std::span<ScanPoint> out, CanonicalPose& pose);

}  // namespace cellsight::algo
