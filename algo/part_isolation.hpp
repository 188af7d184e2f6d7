// Separates the part from material that is not connected to it (a neighbouring carrier's part entering the field of
// view, loose clutter) before features and matching: issue 10. Allocation-free after construction.
#pragma once

#include <Eigen/Core>
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
  // direction, where the neighbouring carriers hang; the first and last profiles of the pass) is a neighbour's part;
  // so is one between such a piece and the part, beside it in y (a glare band crossed the neighbour's edge).
  int border_cells = 3;
  // A piece with fewer cells than this share of the largest is clutter (specular outliers, a loose speck).
  double min_keep_share = 0.005;
  // The hanger (the chain or hook the part hangs from) is material connected to the part that rises to the top of the
  // scanned field and is narrower than this: it is cut off where it meets the part (remove_hanger). The shipped
  // chains are 6-10 mm; a part is wider than this wherever it could reach the field's top.
  double hanger_max_width_m = 0.016;
  // Depth: the part hangs in a plane and its relief (ribs, louvres, flanges seen on their face) fills the depths
  // between its sheet and its highest point, so a band of depth holding no more than depth_empty_share of the points
  // and at least depth_gap_m wide separates the part from what lies beyond it: a secondary reflection of the stripe
  // off bare metal triangulates to a ghost surface 100-600 mm in front of the part, over the part in x-y where the
  // x-y pieces cannot tell it apart (issue 11: 2 % of a pass's points, every template's Perfect Match error 10-50
  // times its limit, the pass unknown after all 15 candidates). The cluster grows from the most populated depth.
  double depth_gap_m = 0.04;
  double depth_empty_share = 1e-4;
  // A piece apart from the part in x-y that is also apart from it in depth is not the part's: fewer than
  // piece_depth_share of its points lie within piece_depth_margin_m of the part's depths (the largest piece's, from
  // its 1st to its 99th percentile). Such ghosts also come beside the part, in front of its edge, where the depth
  // gap cannot see them: the stripe's reflection runs on from the part's relief through every depth to 500 mm in
  // front (fresh random catalogue 11335, pass 1110009: 3 800 points, pieces of up to 1 150 cells 5-30 mm beside the
  // part, their nearest point 25 mm in front of its 99th percentile; every template's Perfect Match error 16 times
  // its limit). The part's own pieces share its depths: a strip a glare band cut off, a flange's column.
  double piece_depth_margin_m = 0.01;
  double piece_depth_share = 0.05;
  // A piece below min_keep_share is the part's own when a glare band cut it off: at least fragment_min_cells, within
  // fragment_gap_m of the largest piece's box (a band is 15-35 mm wide), not at the field's end, and at least
  // fragment_depth_share of its cells holding a point within fragment_sheet_tolerance_m of the sheet beside it (a plane
  // through the largest piece's points within fragment_gap_m of the piece's box, its relief left out): a piece of
  // sheet continues the sheet.
  // Shipped catalogue under `glare`, perforated_fine s1170003: a band across a corner left the corner's 300 points
  // (~150 cells, under the 0.5 % of the largest piece) beyond it; dropped as clutter, the corner looked cut off
  // (2 362 mm2 missing) and a twin with that corner chamfered would have matched. Specular outliers are single cells,
  // far below fragment_min_cells. A 90 deg flange seen edge-on shows only its outer part, a line 10 mm beside the
  // edge and 4-30 mm in front of the sheet: within the part's overall depths (its other flange), it was kept as a
  // fragment at poses where the taught passes never showed it (development catalogue 11360, rnd04 / rnd10 s1170002:
  // 397 mm2 of extra material, unknown). A larger piece that is a thin line beside the part's edge, beyond its
  // extent, must lie on that sheet too (is_edge_line): the same flange's end at a swing that shows more of it is above
  // min_keep_share (fresh shipped channel_u s1210001 / s1210002 and catalogue 11376 rnd03 s1210001: a line 40 mm
  // beside the edge and 60 mm in front of the sheet, 300-330 cells, kept; Perfect Match error 2-8 x every limit).
  // Only the first kMaxFragmentChecks such pieces of a scan are looked at.
  int fragment_min_cells = 20;
  double fragment_gap_m = 0.04;
  double fragment_depth_share = 0.5;
  double fragment_sheet_tolerance_m = 0.004;
  // A smaller piece (a speck) wholly inside the kept pieces' box, not at the field's end, with at least
  // fragment_depth_share of its points at the part's depths is the part's too: the residue a glare band leaves is
  // single points, and where it is sparse they lie farther apart than the bridging reaches. Dropped, they thinned the
  // residue exactly where it was already thin, and the check took the emptied stretch of the band for a hole
  // (shipped catalogue under `glare`, plate_4h s1180006: 6 of 13 residue points in the band's right third dropped,
  // an empty 11 x 53 cell rectangle protected as a hole, 6 505 mm2 missing). A specular outlier that happens to lie
  // there at the part's depth stays too: one cell, far below any gate.
  bool keep_inner_specks = true;
  // A ghost beside the part (drop_ghosts): a secondary reflection of the stripe copies a stretch of it shifted in the
  // image, so it triangulates to points tens of millimetres in front of (or behind) whatever the stripe lit. Beside
  // the part's edge, within the bridging's reach, it joined the part (fresh random catalogue 11391, rnd07
  // s1240008: 900 points two profiles beside its right edge, 38-133 mm in front of the sheet, the Perfect Match
  // error 1.2 and the outliers 2.3 times their limits: unknown; 11366 rnd08 s1180009 alike, 10-25 mm beside a flat
  // plate and 30-50 mm in front). Material of the part off its sheet (relief, a flange's face or rim) rises from the
  // sheet or lies over it; a ghost floats: a group of cells none of which holds a point within ghost_sheet_m of the
  // sheet plane, that no cell holding the sheet borders within ghost_touch_cells, with at least ghost_beyond_share of
  // its cells beyond the sheet's extent in their row or column and at least fragment_min_cells of them.
  double ghost_sheet_m = 0.02;
  int ghost_touch_cells = 2;
  double ghost_beyond_share = 0.8;
};

struct GhostReport {
  std::size_t removed_points = 0;
  int pieces = 0;
};

struct IsolationReport {
  int pieces = 0;  // connected pieces found (before dropping)
  int dropped_pieces = 0;
  int edge_pieces = 0;             // of the dropped: large enough, dropped only for reaching the field's edge
  int fragments = 0;               // pieces below min_keep_share kept as cut off the part (fragment_*)
  int specks = 0;                  // pieces below fragment_min_cells kept inside the part's box (keep_inner_specks)
  int depth_pieces = 0;            // of the dropped: large enough, apart from the part's depths (piece_depth_*)
  int edge_lines = 0;              // of the dropped: a line beside the part's edge, off its sheet (a flange's end)
  std::size_t dropped_points = 0;  // of the dropped pieces and beyond the depth gap
  std::size_t depth_points = 0;    // of them, beyond the depth gap
};

struct CellBox {
  int x0, x1, y0, y1;  // inclusive grid cells; x1 < 0: empty
};

// Square dilation (or erosion) of a 0/1 cell mask src into dst over the box, half-width r cells, separable (rows into
// tmp, then columns); cells outside the box count as empty. dst may be src. All three span the grid's nx-wide raster.
// Never allocates.
void square_morphology(const std::vector<std::uint8_t>& src, std::vector<std::uint8_t>& dst,
                       std::vector<std::uint8_t>& tmp, int nx, const CellBox& box, int r, bool dilate);

struct HangerReport {
  std::size_t removed_points = 0;
  int removed_cells = 0;
};

// First the points beyond a depth gap go (IsolationParams::depth_gap_m). Then connected pieces of the part points' x-y
// occupancy on the grid's raster: the largest always stays; another piece is dropped when it touches an end of the
// scanned x range or is tiny. Points beyond the grid in x-y count in the border cell they lie out of (border_cell_of):
// they go or stay with the piece they touch there, and the caller's outside-the-grid check judges the part's.
// A glare band that cuts the part in two leaves two large inner pieces: both stay.
class PartIsolator {
 public:
  PartIsolator(const GridSpec& grid, const IsolationParams& params);  // allocates

  // scanned_x0_m / scanned_x1_m: the x range the pass covered (its first and last profile: all points of the raw
  // scan, carrier included), carrier frame.
  // keep_edge_pieces: pieces at the field's edge stay (only tiny ones go): the second look when the part itself
  // may have been cut by a glare band near its end (see ScanPreparer::prepare).
  IsolationReport isolate(ScanBuffer& part, double scanned_x0_m, double scanned_x1_m,
                          bool keep_edge_pieces = false);  // never allocates

  // Cuts off the hanger: material that reaches within border_cells of the scanned field's top (scanned_y1_m, the
  // highest y the pass saw, carrier included; the grid's top if lower) and that an opening of the part's x-y
  // occupancy (closed by one cell for the sampling) with a square of hanger_max_width_m removes. What the opening
  // keeps (the part, its corners, any feature at least that wide) and thin features that do not reach the top
  // (a tab, a web between windows) stay. Returns at once when no part cell comes near the top. Never allocates.
  HangerReport remove_hanger(ScanBuffer& part, double scanned_y1_m);

  // Drops ghosts beside the part (IsolationParams::ghost_*), after isolate() and remove_hanger(): fits the sheet's
  // plane (sheet_plane), marks the cells holding the sheet and those holding only points off it, groups the latter
  // (8-neighbours, across one or two empty cells) and drops the groups that float beyond the sheet's extent. Never
  // allocates.
  GhostReport drop_ghosts(ScanBuffer& part);

 private:
  [[nodiscard]] bool cell_of(const ScanPoint& p, std::size_t& index) const;
  [[nodiscard]] bool cell_of(const ScanPoint& p, int& x, int& y) const;
  // isolate()'s cell of a point: beyond the grid in x-y, the border cell it lies out of, so that what hangs over the
  // grid's edge belongs to the piece it touches there (a part's corner turned out of the grid stays with the part; a
  // neighbour's sheet edge below the grid's bottom at the field's x end goes with the other edge pieces, where it
  // used to be kept unlabelled: shipped catalogue under `stray_edge`, pass 900004, 308 points 200 mm below the part
  // that brought every template's Perfect Match error to 3-6 x its limit). False only for a point that is not finite.
  [[nodiscard]] bool border_cell_of(const ScanPoint& p, int& x, int& y) const;
  // After isolate()'s labelling: the piece of a point (label_ at its border_cell_of cell, x and y), -1 for none.
  [[nodiscard]] int piece_of(const ScanPoint& p, int& x, int& y) const;
  // isolate()'s choice of the pieces to keep (piece_keep_), counted in the report.
  void choose_pieces(const ScanBuffer& part, int pieces, int largest, bool keep_edge_pieces, IsolationReport& report);
  // isolate()'s pieces of at least min_cells that continue a piece at the field's end toward the part: marked as at
  // the end too (see the definition).
  void mark_end_pieces(int pieces, int largest, double min_cells);
  // Drops the points beyond a depth gap (IsolationParams::depth_gap_m); returns how many.
  std::size_t drop_depth_outliers(ScanBuffer& part);
  // The grid's depth layer of a point: -1 below the grid (or NaN), nz above it.
  [[nodiscard]] int depth_layer(const ScanPoint& p) const;
  // isolate()'s pieces of at least min_cells apart from the largest one's depths (IsolationParams::piece_depth_*), and
  // the smaller ones (specks too, with keep_inner_specks) with under fragment_depth_share of their points at those
  // depths: piece_off_depth_ set for them.
  void mark_off_depth_pieces(const ScanBuffer& part, int pieces, int largest, double min_cells);
  // Whether piece i, below min_cells, is a fragment of the part (IsolationParams::fragment_*), after
  // mark_off_depth_pieces.
  [[nodiscard]] bool is_fragment(int i, int largest) const;
  // Whether piece i lies beside the part as its own pieces do: not at the field's end, at the part's depths, counted
  // (mark_off_depth_pieces) and near_largest. What a fragment (is_fragment) and an edge line (is_edge_line) share.
  [[nodiscard]] bool beside_part(int i, int largest) const;
  // Whether piece i (beside_part) is a thin line beside the largest piece's edge, outside its extent (see the
  // definition). mark_off_depth_pieces asks it of every piece that is not a fragment: meant for those above min_cells;
  // a smaller line it marks goes as clutter all the same unless it is a speck inside the kept pieces' box.
  [[nodiscard]] bool is_edge_line(int i, int largest) const;
  // Whether piece i lies within fragment_gap_m of the largest piece's box.
  [[nodiscard]] bool near_largest(int i, int largest) const;
  // Whether at least fragment_depth_share of piece i's cells hold a point within fragment_sheet_tolerance_m of the
  // sheet beside it (see the definition).
  [[nodiscard]] bool fragment_on_sheet(const ScanBuffer& part, int i, int largest);
  // Whether piece i, below fragment_min_cells, is a speck of the part's own (IsolationParams::keep_inner_specks)
  // inside the kept pieces' box, after mark_off_depth_pieces.
  [[nodiscard]] bool is_inner_speck(int i, const CellBox& kept) const;
  // drop_ghosts' sheet: z = a + b (x - cx) + c (y - cy) about the centre (cx, cy) of the part's box from points near
  // the densest depth, refitted twice to the points near the plane (a part hangs tilted by up to 2 deg: 24 mm over
  // 700 mm). False when too few points define it.
  [[nodiscard]] bool sheet_plane(const ScanBuffer& part, const CellBox& box, Eigen::Vector3d& plane, double& cx,
                                 double& cy);
  // drop_ghosts' flood fill of the group of off-sheet cells from `seed` (label_ = id, through bridged_), growing g
  // over its cells; returns how many of them hold points.
  int fill_off_group(std::size_t seed, int id, const CellBox& b, CellBox& g);
  // drop_ghosts' test of one group (label_ == id over its box): whether it floats beside the part.
  [[nodiscard]] bool ghost_group(int id, const CellBox& box, int cells) const;
  // The cell box of the part's points on the grid (points beyond it left out); with count (isolate's use), points
  // beyond the grid count in their border cell (border_cell_of, as isolate's labels take them) and occupied_ gets the
  // points per cell.
  CellBox occupied_box(const ScanBuffer& part, bool count);

  GridSpec grid_;
  double inv_resolution_ = 0.0;  // 1 / grid_.resolution_m: a product per point, not a division
  IsolationParams params_;
  std::vector<std::int32_t> occupied_;  // points per cell
  std::vector<std::uint8_t> bridged_;   // dilated occupancy
  std::vector<std::int32_t> label_;     // piece per cell of the dilated occupancy (-1 none)
  std::vector<std::int32_t> stack_;
  std::vector<std::int32_t> piece_cells_;  // occupied cells per piece
  std::vector<std::uint8_t> piece_border_;
  std::vector<std::int32_t> piece_x0_, piece_x1_, piece_y0_, piece_y1_;  // occupied cells' box per piece
  std::vector<std::uint8_t> piece_keep_;
  std::vector<std::uint8_t> piece_off_depth_;  // 1: off the part's depths; kOffSheetLine: an edge line off its sheet
  static constexpr std::uint8_t kOffSheetLine = 2;
  std::vector<std::int32_t> piece_points_, piece_on_depth_;  // mark_off_depth_pieces: points, of them at the part's
  std::vector<std::uint8_t> mask_;                           // occupancy (bit 0); remove_hanger: cut off (bit 1)
  std::vector<std::uint8_t> closed_;                         // remove_hanger: the occupancy closed by one cell
  std::vector<std::uint8_t> opened_;                         // remove_hanger: its opening
  std::vector<std::uint8_t> scratch_;                        // square_morphology's rows; fragment_on_sheet's cells
  std::vector<std::int32_t> depth_count_;                    // drop_depth_outliers: points per grid depth layer
  std::vector<std::int32_t> local_count_;                    // fragment_on_sheet: the part's points per layer there
  // drop_ghosts: the sheet's extent per row (x) and per column (y), inclusive cells; lo > hi where it has none.
  std::vector<std::int32_t> row_lo_, row_hi_, col_lo_, col_hi_;
  static constexpr std::uint8_t kSheetCell = 1, kOffCell = 2;  // drop_ghosts' marks in mask_
};

}  // namespace cellsight::algo
