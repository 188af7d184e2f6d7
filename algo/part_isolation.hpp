// Separates the part from material that is not connected to it (a neighbouring carrier's part entering the field of
// view, loose clutter) before features and matching: issue 10. Allocation-free after construction.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "algo/grid.hpp"
#include "algo/scan.hpp"

namespace cellsight::algo {

struct IsolationParams {
  // Occupied x-y cells closer than about 2 * bridge_cells cells belong to one piece: a dropout line or a sparse glare
  // band does not cut the part, a neighbour 15 mm away stays apart (2.2 mm cells: 2 -> gaps up to ~9 mm bridged).
  int bridge_cells = 2;
  // A piece that is not the largest and reaches within border_cells of the scanned x range's ends (the conveyor
  // direction, where the neighbouring carriers hang; the first and last profiles of the pass) is a neighbour's part.
  int border_cells = 3;
  // A piece with fewer cells than this share of the largest is clutter (specular outliers, a loose speck).
  double min_keep_share = 0.005;
};

struct IsolationReport {
  int pieces = 0;               // connected pieces found (before dropping)
  int dropped_pieces = 0;
  std::size_t dropped_points = 0;
};

// Connected pieces of the part points' x-y occupancy on the grid's raster: the largest always stays; another piece
// is dropped when it touches an end of the scanned x range or is tiny. Points outside the grid are left alone (the caller's
// outside-the-grid check judges them). A glare band that cuts the part in two leaves two large inner pieces: both
// stay.
class PartIsolator {
 public:
  PartIsolator(const GridSpec& grid, const IsolationParams& params);  // allocates

  // scanned_x0_m / scanned_x1_m: the x range the pass covered (its first and last profile: all points of the raw
  // scan, carrier included), carrier frame.
  IsolationReport isolate(ScanBuffer& part, double scanned_x0_m, double scanned_x1_m);  // never allocates

 private:
  [[nodiscard]] bool cell_of(const ScanPoint& p, std::size_t& index) const;

  GridSpec grid_;
  IsolationParams params_;
  std::vector<std::int32_t> occupied_;  // points per cell
  std::vector<std::uint8_t> bridged_;   // dilated occupancy
  std::vector<std::int32_t> label_;     // piece per cell of the dilated occupancy (-1 none)
  std::vector<std::int32_t> stack_;
  std::vector<std::int32_t> piece_cells_;  // occupied cells per piece
  std::vector<std::uint8_t> piece_border_;
  std::vector<std::uint8_t> piece_keep_;
};

}  // namespace cellsight::algo
