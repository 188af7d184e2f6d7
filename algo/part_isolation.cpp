// Part isolation (see part_isolation.hpp).
#include "algo/part_isolation.hpp"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>
#include <span>

namespace cellsight::algo {

namespace {

// mark_off_depth_pieces: fragment_on_sheet costs a pass over the points; a scan has a corner or two cut off, not more.
constexpr int kMaxFragmentChecks = 8;
// is_edge_line: a line at most this many cells wide on average (its cells per cell of its length) ...
constexpr double kLineMaxWidthCells = 2.5;
// ... whose box is at least this many times longer than wide (along the part's edge: a part turns by +-5 deg) ...
constexpr int kLineMinAspect = 5;
// ... with at least this share of its cells beyond the largest piece's extent in their row (or column).
constexpr double kLineBeyondShare = 0.9;

// Least squares z = a + b (x - cx) + c (y - cy) about (cx, cy), the centre the caller picks for the conditioning:
// fragment_on_sheet's sheet beside a piece and sheet_plane's whole sheet.
// (Not algo::PlaneFit of calibration.hpp, a fitted plane's result; canonical.cpp's least_squares keeps its own sums
// and degenerate-case rule, which the features depend on.)
class PlaneLeastSquares {
 public:
  PlaneLeastSquares(double cx, double cy) : cx_(cx), cy_(cy) {}
  void add(const ScanPoint& p) {
    const Eigen::Vector3d v(1.0, p.x - cx_, p.y - cy_);
    normal_ += v * v.transpose();
    rhs_ += v * static_cast<double>(p.z);
    ++points_;
  }
  [[nodiscard]] int points() const { return points_; }
  // False (plane untouched) for points on one line, or none.
  [[nodiscard]] bool solve(Eigen::Vector3d& plane) const {
    const Eigen::LDLT<Eigen::Matrix3d> solver(normal_);
    if (solver.info() != Eigen::Success || !solver.isPositive() || !(std::abs(normal_.determinant()) > 1e-18)) {
      return false;
    }
    plane = solver.solve(rhs_);
    return true;
  }

 private:
  double cx_, cy_;
  Eigen::Matrix3d normal_ = Eigen::Matrix3d::Zero();
  Eigen::Vector3d rhs_ = Eigen::Vector3d::Zero();
  int points_ = 0;
};

// How far a point lies off a PlaneLeastSquares plane about (cx, cy), along z.
[[nodiscard]] double plane_offset(const ScanPoint& p, const Eigen::Vector3d& plane, double cx, double cy) {
  return std::abs(static_cast<double>(p.z) - plane.dot(Eigen::Vector3d(1.0, p.x - cx, p.y - cy)));
}

// One line of a square dilation (or erosion) of src into dst over the box: half-width r cells along x or y; cells
// outside the box count as empty.
void line_pass(const std::vector<std::uint8_t>& src, std::vector<std::uint8_t>& dst, int nx, const CellBox& b, int r,
               bool dilate, bool along_x) {
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) {
      bool v = !dilate;
      for (int d = -r; d <= r; ++d) {
        const int xx = along_x ? x + d : x, yy = along_x ? y : y + d;
        const bool s =
            xx >= b.x0 && xx <= b.x1 && yy >= b.y0 && yy <= b.y1 &&
            src[static_cast<std::size_t>(yy) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(xx)] != 0;
        v = dilate ? (v || s) : (v && s);
      }
      dst[static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x)] = v ? 1 : 0;
    }
  }
}

}  // namespace

// Written here rather than with cv::dilate / cv::erode so the loop's buffers stay the preallocated ones and the box
// limits the work. (dst may be src: src is only read by the row pass.)
void square_morphology(const std::vector<std::uint8_t>& src, std::vector<std::uint8_t>& dst,
                       std::vector<std::uint8_t>& tmp, int nx, const CellBox& box, int r, bool dilate) {
  line_pass(src, tmp, nx, box, r, dilate, true);
  line_pass(tmp, dst, nx, box, r, dilate, false);
}

PartIsolator::PartIsolator(const GridSpec& grid, const IsolationParams& params)
    : grid_(grid), inv_resolution_(1.0 / grid.resolution_m), params_(params) {
  const auto cells = static_cast<std::size_t>(grid.nx) * static_cast<std::size_t>(grid.ny);
  occupied_.assign(cells, 0);
  bridged_.assign(cells, 0);
  label_.assign(cells, -1);
  stack_.assign(cells, 0);
  piece_cells_.assign(cells, 0);
  piece_border_.assign(cells, 0);
  for (auto* v : {&piece_x0_, &piece_x1_, &piece_y0_, &piece_y1_}) v->assign(cells, 0);
  piece_keep_.assign(cells, 0);
  piece_off_depth_.assign(cells, 0);
  piece_points_.assign(cells, 0);
  piece_on_depth_.assign(cells, 0);
  mask_.assign(cells, 0);
  closed_.assign(cells, 0);
  opened_.assign(cells, 0);
  scratch_.assign(cells, 0);
  depth_count_.assign(static_cast<std::size_t>(std::max(grid.nz, 1)), 0);
  local_count_.assign(static_cast<std::size_t>(std::max(grid.nz, 1)), 0);
  for (auto* v : {&row_lo_, &row_hi_}) v->assign(static_cast<std::size_t>(grid.ny), 0);
  for (auto* v : {&col_lo_, &col_hi_}) v->assign(static_cast<std::size_t>(grid.nx), 0);
}

int PartIsolator::depth_layer(const ScanPoint& p) const {
  const int nz = static_cast<int>(depth_count_.size());
  const double f = (static_cast<double>(p.z) - grid_.origin_m.z()) * inv_resolution_;
  if (!(f >= 0.0)) return -1;
  return f < nz ? static_cast<int>(f) : nz;
}

std::size_t PartIsolator::drop_depth_outliers(ScanBuffer& part) {
  const int nz = static_cast<int>(depth_count_.size());
  std::fill(depth_count_.begin(), depth_count_.end(), 0);
  std::size_t counted = 0;
  for (const ScanPoint& p : part.points()) {
    const int z = depth_layer(p);
    if (z < 0 || z >= nz) continue;
    ++depth_count_[static_cast<std::size_t>(z)];
    ++counted;
  }
  if (counted == 0) return 0;
  const auto densest =
      static_cast<int>(std::max_element(depth_count_.begin(), depth_count_.end()) - depth_count_.begin());
  const double empty = params_.depth_empty_share * static_cast<double>(counted);
  const int gap = std::max(1, static_cast<int>(std::ceil(params_.depth_gap_m * inv_resolution_)));
  // The last populated layer before `gap` empty ones, walking from the densest layer in direction step.
  const auto reach = [&](int step) {
    int last = densest;
    for (int z = densest + step; z >= 0 && z < nz && std::abs(z - last) <= gap; z += step) {
      if (static_cast<double>(depth_count_[static_cast<std::size_t>(z)]) > empty) last = z;
    }
    return last;
  };
  const int lo = reach(-1), hi = reach(+1);
  // Points beyond the grid's depth stay when the part reaches that end (the outside-the-grid check judges them).
  const int keep_lo = lo == 0 ? -1 : lo, keep_hi = hi == nz - 1 ? nz : hi;
  return part.filter([&](const ScanPoint& p) {
    const int z = depth_layer(p);
    return z >= keep_lo && z <= keep_hi;
  });
}

int PartIsolator::piece_of(const ScanPoint& p, int& x, int& y) const {
  if (!border_cell_of(p, x, y)) return -1;
  return label_[static_cast<std::size_t>(y) * static_cast<std::size_t>(grid_.nx) + static_cast<std::size_t>(x)];
}

bool PartIsolator::cell_of(const ScanPoint& p, int& x, int& y) const {
  const double fx = (static_cast<double>(p.x) - grid_.origin_m.x()) * inv_resolution_;
  const double fy = (static_cast<double>(p.y) - grid_.origin_m.y()) * inv_resolution_;
  if (!(fx >= 0.0 && fy >= 0.0 && fx < grid_.nx && fy < grid_.ny)) return false;  // NaN fails too
  x = static_cast<int>(fx);
  y = static_cast<int>(fy);
  return true;
}

bool PartIsolator::cell_of(const ScanPoint& p, std::size_t& index) const {
  int x = 0, y = 0;
  if (!cell_of(p, x, y)) return false;
  index = static_cast<std::size_t>(y) * static_cast<std::size_t>(grid_.nx) + static_cast<std::size_t>(x);
  return true;
}

bool PartIsolator::border_cell_of(const ScanPoint& p, int& x, int& y) const {
  const double fx = (static_cast<double>(p.x) - grid_.origin_m.x()) * inv_resolution_;
  const double fy = (static_cast<double>(p.y) - grid_.origin_m.y()) * inv_resolution_;
  if (!std::isfinite(fx) || !std::isfinite(fy)) return false;
  x = static_cast<int>(std::clamp(std::floor(fx), 0.0, static_cast<double>(grid_.nx - 1)));
  y = static_cast<int>(std::clamp(std::floor(fy), 0.0, static_cast<double>(grid_.ny - 1)));
  return true;
}

CellBox PartIsolator::occupied_box(const ScanBuffer& part, bool count) {
  const auto nx = static_cast<std::size_t>(grid_.nx);
  if (count) std::fill(occupied_.begin(), occupied_.end(), 0);
  CellBox b{grid_.nx, -1, grid_.ny, -1};
  for (const ScanPoint& p : part.points()) {
    int x = 0, y = 0;
    if (!(count ? border_cell_of(p, x, y) : cell_of(p, x, y))) continue;
    if (count) ++occupied_[static_cast<std::size_t>(y) * nx + static_cast<std::size_t>(x)];
    b.x0 = std::min(b.x0, x);
    b.x1 = std::max(b.x1, x);
    b.y0 = std::min(b.y0, y);
    b.y1 = std::max(b.y1, y);
  }
  return b;
}

IsolationReport PartIsolator::isolate(ScanBuffer& part, double scanned_x0_m, double scanned_x1_m,
                                      bool keep_edge_pieces) {
  IsolationReport report;
  report.depth_points = drop_depth_outliers(part);
  report.dropped_points = report.depth_points;
  const int nx = grid_.nx;
  const int ny = grid_.ny;
  const CellBox box = occupied_box(part, true);
  const int x_lo = box.x0, x_hi = box.x1, y_lo = box.y0, y_hi = box.y1;
  if (x_hi < 0) return report;
  // The scanned range's end cells (clamped to the grid): a piece reaching within border_cells of them is at the edge.
  const auto cell_x = [&](double x_m) {
    const double f = (x_m - grid_.origin_m.x()) / grid_.resolution_m;
    return std::isfinite(f) ? static_cast<int>(std::clamp(std::floor(f), 0.0, static_cast<double>(nx - 1))) : 0;
  };
  const int edge_lo = cell_x(scanned_x0_m) + params_.border_cells;
  const int edge_hi = cell_x(scanned_x1_m) - params_.border_cells;
  // Dilation by a square of bridge_cells over the occupied box plus the radius.
  const int r = std::max(0, params_.bridge_cells);
  const int bx0 = std::max(0, x_lo - r), bx1 = std::min(nx - 1, x_hi + r);
  const int by0 = std::max(0, y_lo - r), by1 = std::min(ny - 1, y_hi + r);
  auto at = [nx](int x, int y) {
    return static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x);
  };
  const CellBox b{bx0, bx1, by0, by1};
  for (int y = by0; y <= by1; ++y) {
    for (int x = bx0; x <= bx1; ++x) {
      mask_[at(x, y)] = occupied_[at(x, y)] > 0 ? 1 : 0;
      label_[at(x, y)] = -1;
    }
  }
  square_morphology(mask_, bridged_, scratch_, nx, b, r, true);
  // Pieces: 4-connected flood fill of the bridged cells; each piece counts its occupied cells and whether it reaches
  // the x border.
  int pieces = 0;
  for (int y = by0; y <= by1; ++y) {
    for (int x = bx0; x <= bx1; ++x) {
      const std::size_t seed = at(x, y);
      if (bridged_[seed] == 0 || label_[seed] >= 0) continue;
      const int id = pieces++;
      piece_cells_[static_cast<std::size_t>(id)] = 0;
      piece_border_[static_cast<std::size_t>(id)] = 0;
      piece_x0_[static_cast<std::size_t>(id)] = piece_y0_[static_cast<std::size_t>(id)] = std::max(nx, ny);
      piece_x1_[static_cast<std::size_t>(id)] = piece_y1_[static_cast<std::size_t>(id)] = -1;
      std::size_t top = 0;
      stack_[top++] = static_cast<std::int32_t>(seed);
      label_[seed] = id;
      while (top > 0) {
        const auto c = static_cast<std::size_t>(stack_[--top]);
        const int cx = static_cast<int>(c % static_cast<std::size_t>(nx));
        const int cy = static_cast<int>(c / static_cast<std::size_t>(nx));
        if (occupied_[c] > 0) {
          const auto u = static_cast<std::size_t>(id);
          ++piece_cells_[u];
          if (cx < edge_lo || cx > edge_hi) piece_border_[u] = 1;
          piece_x0_[u] = std::min(piece_x0_[u], cx);
          piece_x1_[u] = std::max(piece_x1_[u], cx);
          piece_y0_[u] = std::min(piece_y0_[u], cy);
          piece_y1_[u] = std::max(piece_y1_[u], cy);
        }
        const int nxs[4] = {cx - 1, cx + 1, cx, cx};
        const int nys[4] = {cy, cy, cy - 1, cy + 1};
        for (int k = 0; k < 4; ++k) {
          if (nxs[k] < bx0 || nxs[k] > bx1 || nys[k] < by0 || nys[k] > by1) continue;
          const std::size_t n = at(nxs[k], nys[k]);
          if (bridged_[n] == 0 || label_[n] >= 0) continue;
          label_[n] = id;
          stack_[top++] = static_cast<std::int32_t>(n);
        }
      }
    }
  }
  report.pieces = pieces;
  if (pieces <= 1) return report;
  int largest = 0;
  for (int i = 1; i < pieces; ++i) {
    if (piece_cells_[static_cast<std::size_t>(i)] > piece_cells_[static_cast<std::size_t>(largest)]) largest = i;
  }
  choose_pieces(part, pieces, largest, keep_edge_pieces, report);
  if (report.dropped_pieces == 0) return report;
  report.dropped_points += part.filter([&](const ScanPoint& p) {
    int x = 0, y = 0;
    const int id = piece_of(p, x, y);
    return id < 0 || piece_keep_[static_cast<std::size_t>(id)] != 0;
  });
  return report;
}

void PartIsolator::choose_pieces(const ScanBuffer& part, int pieces, int largest, bool keep_edge_pieces,
                                 IsolationReport& report) {
  const double min_cells = params_.min_keep_share * piece_cells_[static_cast<std::size_t>(largest)];
  mark_end_pieces(pieces, largest, min_cells);
  mark_off_depth_pieces(part, pieces, largest, min_cells);
  // The kept pieces' box (a band that cut the part in two leaves two large pieces, its residue between them).
  CellBox kept{piece_x0_[static_cast<std::size_t>(largest)], piece_x1_[static_cast<std::size_t>(largest)],
               piece_y0_[static_cast<std::size_t>(largest)], piece_y1_[static_cast<std::size_t>(largest)]};
  for (int i = 0; i < pieces; ++i) {
    const auto u = static_cast<std::size_t>(i);
    const bool large = piece_cells_[u] >= min_cells;
    const bool off_depth = piece_off_depth_[u] != 0;
    const bool fragment = !large && is_fragment(i, largest);
    const bool keep = i == largest || fragment || (large && !off_depth && (piece_border_[u] == 0 || keep_edge_pieces));
    piece_keep_[u] = keep ? 1 : 0;
    report.fragments += fragment ? 1 : 0;
    report.depth_pieces += !keep && large && off_depth && piece_off_depth_[u] != kOffSheetLine ? 1 : 0;
    report.edge_lines += piece_off_depth_[u] == kOffSheetLine ? 1 : 0;
    report.edge_pieces += !keep && large && !off_depth ? 1 : 0;
    if (keep)
      kept = {std::min(kept.x0, piece_x0_[u]), std::max(kept.x1, piece_x1_[u]), std::min(kept.y0, piece_y0_[u]),
              std::max(kept.y1, piece_y1_[u])};
  }
  for (int i = 0; i < pieces; ++i) {
    const auto u = static_cast<std::size_t>(i);
    if (piece_keep_[u] == 0 && piece_cells_[u] < params_.fragment_min_cells && is_inner_speck(i, kept)) {
      piece_keep_[u] = 1;
      ++report.specks;
    }
    report.dropped_pieces += piece_keep_[u] != 0 ? 0 : 1;
  }
}

void PartIsolator::mark_end_pieces(int pieces, int largest, double min_cells) {
  // A neighbour's sheet edge that a glare band crossed near the field's end leaves a piece at the end and one beyond
  // the band that no longer reaches it: shipped catalogue under `mixed`, ribbed_v3 s1010008, 274 cells at the end,
  // 1 865 beyond a 12 mm band and 15 mm short of the part, kept (9 027 mm2 of material against ribbed_v3's template).
  // A piece that lies between an end piece and the part in x, beside the end piece in y (their y ranges overlapping
  // by half the shorter), continues it. A strip of the part a glare band cut off near its end has no end piece
  // beside it; and should a piece marked here be the part's, the second look (ScanPreparer::prepare with
  // keep_edge_pieces) keeps it.
  const auto l = static_cast<std::size_t>(largest);
  for (int i = 0; i < pieces; ++i) {
    const auto u = static_cast<std::size_t>(i);
    // (Specks go anyway: only pieces large enough to be kept are looked at, so a scan of many specks costs little.)
    if (i == largest || piece_border_[u] != 0 || piece_cells_[u] < min_cells) continue;
    const bool before = piece_x1_[u]<piece_x0_[l], after = piece_x0_[u]> piece_x1_[l];
    if (!before && !after) continue;
    for (int j = 0; j < pieces && piece_border_[u] == 0; ++j) {
      const auto b = static_cast<std::size_t>(j);
      if (j == largest || piece_border_[b] == 0) continue;
      const bool beyond = before ? piece_x1_[b] < piece_x0_[u] : piece_x0_[b] > piece_x1_[u];
      const int overlap = std::min(piece_y1_[u], piece_y1_[b]) - std::max(piece_y0_[u], piece_y0_[b]) + 1;
      const int shorter = std::min(piece_y1_[u] - piece_y0_[u], piece_y1_[b] - piece_y0_[b]) + 1;
      // ... unless it continues the part across the band rather than the end piece: a glare band that cut the part
      // in two beside a neighbour's sheet at the field's end leaves the part's far half between the two, where its y
      // range is the part's (fresh shipped catalogue under `mixed`, s1570009: an 8 mm band with no residue through
      // plate_5h, louvred_panel and slotted_plate, a neighbour's sheet 20 mm beyond; the far half was dropped and
      // 75 000-130 000 mm2 were missing against every template).
      const int to_end = std::abs(piece_y0_[u] - piece_y0_[b]) + std::abs(piece_y1_[u] - piece_y1_[b]);
      const int to_part = std::abs(piece_y0_[u] - piece_y0_[l]) + std::abs(piece_y1_[u] - piece_y1_[l]);
      if (beyond && 2 * overlap >= shorter && to_end <= to_part) piece_border_[u] = 1;
    }
  }
}

void PartIsolator::mark_off_depth_pieces(const ScanBuffer& part, int pieces, int largest, double min_cells) {
  std::fill_n(piece_off_depth_.begin(), pieces, std::uint8_t{0});
  const double least =
      params_.keep_inner_specks ? 1.0 : std::min(min_cells, static_cast<double>(params_.fragment_min_cells));
  bool any = false;  // (no other piece that could be kept: nothing to count)
  for (int i = 0; i < pieces; ++i) {
    any = any || (i != largest && piece_cells_[static_cast<std::size_t>(i)] >= least);
  }
  if (!any) return;
  int x = 0, y = 0;  // (piece_of's cell, unused here)
  // The part's depths: the largest piece's points per layer (those beyond the grid's depth in its end layers).
  const int nz = static_cast<int>(depth_count_.size());
  std::fill(depth_count_.begin(), depth_count_.end(), 0);
  std::fill_n(piece_points_.begin(), pieces, 0);
  std::fill_n(piece_on_depth_.begin(), pieces, 0);
  std::int64_t counted = 0;
  for (const ScanPoint& p : part.points()) {
    if (piece_of(p, x, y) != largest) continue;
    ++depth_count_[static_cast<std::size_t>(std::clamp(depth_layer(p), 0, nz - 1))];
    ++counted;
  }
  if (counted == 0) return;
  int lo = 0, hi = nz - 1;
  std::int64_t below = 0;
  for (int z = 0; z < nz; ++z) {
    if (100 * below <= counted) lo = z;  // the 1st percentile's layer
    below += depth_count_[static_cast<std::size_t>(z)];
    if (100 * below >= 99 * counted) {  // the 99th's
      hi = z;
      break;
    }
  }
  const int margin = static_cast<int>(std::ceil(params_.piece_depth_margin_m * inv_resolution_));
  for (const ScanPoint& p : part.points()) {
    const int id = piece_of(p, x, y);
    if (id < 0 || id == largest) continue;
    const int z = depth_layer(p);
    ++piece_points_[static_cast<std::size_t>(id)];
    if (z >= lo - margin && z <= hi + margin) ++piece_on_depth_[static_cast<std::size_t>(id)];
  }
  int fragment_checks = 0;
  for (int i = 0; i < pieces; ++i) {
    const auto u = static_cast<std::size_t>(i);
    const double share = piece_cells_[u] >= min_cells ? params_.piece_depth_share : params_.fragment_depth_share;
    piece_off_depth_[u] = piece_points_[u] > 0 && piece_on_depth_[u] < share * piece_points_[u];
    // A fragment's candidate on the part's depths: also on the sheet beside it (see IsolationParams::fragment_*); so
    // is a line beside the part's edge (is_edge_line), or it is a flange's end seen edge-on (kOffSheetLine).
    const bool fragment = i != largest && piece_cells_[u] < min_cells && is_fragment(i, largest);
    const bool line = !fragment && i != largest && fragment_checks < kMaxFragmentChecks && is_edge_line(i, largest);
    if (!fragment && !line) continue;
    const bool on_sheet = fragment_checks < kMaxFragmentChecks && fragment_on_sheet(part, i, largest);
    piece_off_depth_[u] = on_sheet ? 0 : (line ? kOffSheetLine : 1);
    ++fragment_checks;
  }
}

bool PartIsolator::fragment_on_sheet(const ScanBuffer& part, int i, int largest) {
  // The sheet beside the piece: the largest piece's points within fragment_gap_m of its box, at most kSheetLayers
  // from their median depth layer (relief beside it left out), as a plane z = a + b x + c y (a part hangs tilted
  // by its swing, 35 mm per metre at 2 deg). Three passes over the points; fragments are rare (kMaxFragmentChecks).
  constexpr int kSheetLayers = 2;
  const auto u = static_cast<std::size_t>(i);
  const int gap = static_cast<int>(std::ceil(params_.fragment_gap_m * inv_resolution_));
  const int nz = static_cast<int>(local_count_.size());
  const auto nx = static_cast<std::size_t>(grid_.nx);
  int x = 0, y = 0;                                  // piece_of's cell of a point
  const auto near_piece = [&](const ScanPoint& p) {  // one of the largest piece's points within gap of piece i's box
    return piece_of(p, x, y) == largest && x >= piece_x0_[u] - gap && x <= piece_x1_[u] + gap &&
           y >= piece_y0_[u] - gap && y <= piece_y1_[u] + gap;
  };
  const auto layer = [&](const ScanPoint& p) { return std::clamp(depth_layer(p), 0, nz - 1); };
  std::fill(local_count_.begin(), local_count_.end(), 0);
  std::int64_t beside = 0;
  for (const ScanPoint& p : part.points()) {
    if (!near_piece(p)) continue;
    ++local_count_[static_cast<std::size_t>(layer(p))];
    ++beside;
  }
  if (beside == 0) return false;
  int median = 0;
  for (std::int64_t below = 0; median < nz; ++median) {
    below += local_count_[static_cast<std::size_t>(median)];
    if (2 * below >= beside) break;
  }
  // Least squares about the piece's box centre (for the conditioning).
  const double cx = grid_.origin_m.x() + 0.5 * (piece_x0_[u] + piece_x1_[u] + 1) * grid_.resolution_m;
  const double cy = grid_.origin_m.y() + 0.5 * (piece_y0_[u] + piece_y1_[u] + 1) * grid_.resolution_m;
  PlaneLeastSquares fit(cx, cy);
  for (const ScanPoint& p : part.points()) {
    if (near_piece(p) && std::abs(layer(p) - median) <= kSheetLayers) fit.add(p);
  }
  Eigen::Vector3d plane(grid_.origin_m.z() + (median + 0.5) * grid_.resolution_m, 0.0, 0.0);
  (void)fit.solve(plane);  // (points on one line, or none: the median's depth, level)
  // Its cells with a point on that plane (scratch_ is free once the pieces are labelled): a corner cut off with the
  // flange along its edge holds the flange's wall too, many points per cell in front of the sheet, but every cell
  // also holds the sheet (the shipped catalogue's bracket_l under `glare`, s1190010).
  for (int row = piece_y0_[u]; row <= piece_y1_[u]; ++row) {
    std::fill_n(scratch_.begin() + static_cast<std::ptrdiff_t>(static_cast<std::size_t>(row) * nx +
                                                               static_cast<std::size_t>(piece_x0_[u])),
                piece_x1_[u] - piece_x0_[u] + 1, std::uint8_t{0});
  }
  int on_sheet = 0;
  for (const ScanPoint& p : part.points()) {
    if (piece_of(p, x, y) != i) continue;
    const double sheet = plane.x() + plane.y() * (p.x - cx) + plane.z() * (p.y - cy);
    std::uint8_t& cell = scratch_[static_cast<std::size_t>(y) * nx + static_cast<std::size_t>(x)];
    if (cell != 0 || std::abs(static_cast<double>(p.z) - sheet) > params_.fragment_sheet_tolerance_m) continue;
    cell = 1;
    ++on_sheet;
  }
  return static_cast<double>(on_sheet) >= params_.fragment_depth_share * piece_cells_[u];
}

bool PartIsolator::is_fragment(int i, int largest) const {
  return piece_cells_[static_cast<std::size_t>(i)] >= params_.fragment_min_cells && beside_part(i, largest);
}

bool PartIsolator::beside_part(int i, int largest) const {
  const auto u = static_cast<std::size_t>(i);
  if (piece_border_[u] != 0 || piece_off_depth_[u] != 0) return false;
  if (piece_points_[u] == 0) return false;  // (not counted: mark_off_depth_pieces found nothing to look at)
  return near_largest(i, largest);
}

bool PartIsolator::is_edge_line(int i, int largest) const {
  const auto u = static_cast<std::size_t>(i), l = static_cast<std::size_t>(largest);
  if (!beside_part(i, largest)) return false;
  const int w = piece_x1_[u] - piece_x0_[u] + 1, h = piece_y1_[u] - piece_y0_[u] + 1;
  const int length = std::max(w, h);
  if (std::min(w, h) * kLineMinAspect > length || piece_cells_[u] > kLineMaxWidthCells * length) return false;
  // Its cells beyond the largest piece's extent in their row (a line along y) or column (along x): a along the line,
  // b across it.
  const bool along_y = h >= w;
  const auto nx = static_cast<std::size_t>(grid_.nx);
  const auto holds = [&](int a, int b, int piece) {
    const std::size_t c = along_y ? static_cast<std::size_t>(a) * nx + static_cast<std::size_t>(b)
                                  : static_cast<std::size_t>(b) * nx + static_cast<std::size_t>(a);
    return occupied_[c] > 0 && label_[c] == piece;
  };
  const int a0 = along_y ? piece_y0_[u] : piece_x0_[u], a1 = along_y ? piece_y1_[u] : piece_x1_[u];
  const int b0 = along_y ? piece_x0_[u] : piece_y0_[u], b1 = along_y ? piece_x1_[u] : piece_y1_[u];
  const int l0 = along_y ? piece_x0_[l] : piece_y0_[l], l1 = along_y ? piece_x1_[l] : piece_y1_[l];
  int beyond = 0;
  for (int a = a0; a <= a1; ++a) {
    // The largest piece's extent across this row (column); a row it does not reach: every cell is beyond.
    int lo = std::numeric_limits<int>::max(), hi = std::numeric_limits<int>::min();
    for (int b = l0; b <= l1; ++b) {
      if (!holds(a, b, largest)) continue;
      lo = std::min(lo, b);
      hi = std::max(hi, b);
    }
    for (int b = b0; b <= b1; ++b) beyond += holds(a, b, i) && (b < lo || b > hi) ? 1 : 0;
  }
  return beyond >= kLineBeyondShare * piece_cells_[u];
}

bool PartIsolator::near_largest(int i, int largest) const {
  const auto u = static_cast<std::size_t>(i), l = static_cast<std::size_t>(largest);
  const int gap = static_cast<int>(std::ceil(params_.fragment_gap_m * inv_resolution_));
  const int dx = std::max({0, piece_x0_[l] - piece_x1_[u], piece_x0_[u] - piece_x1_[l]});
  const int dy = std::max({0, piece_y0_[l] - piece_y1_[u], piece_y0_[u] - piece_y1_[l]});
  return dx <= gap && dy <= gap;
}

bool PartIsolator::is_inner_speck(int i, const CellBox& kept) const {
  const auto u = static_cast<std::size_t>(i);
  if (!params_.keep_inner_specks || piece_border_[u] != 0 || piece_off_depth_[u] != 0) return false;
  if (piece_points_[u] == 0) return false;  // (not counted)
  return piece_x0_[u] >= kept.x0 && piece_x1_[u] <= kept.x1 && piece_y0_[u] >= kept.y0 && piece_y1_[u] <= kept.y1;
}

HangerReport PartIsolator::remove_hanger(ScanBuffer& part, double scanned_y1_m) {
  HangerReport report;
  const int nx = grid_.nx;
  const int ny = grid_.ny;
  const double fy = (scanned_y1_m - grid_.origin_m.y()) / grid_.resolution_m;
  if (!std::isfinite(fy)) return report;
  const int top = static_cast<int>(std::clamp(std::floor(fy), 0.0, static_cast<double>(ny - 1)));
  const int reach = top - params_.border_cells;  // a hanger has cells at or above this row
  const CellBox box = occupied_box(part, false);
  const int x_lo = box.x0, x_hi = box.x1, y_lo = box.y0, y_hi = box.y1;
  if (x_hi < 0 || y_hi < reach) return report;  // the usual case: nothing comes near the top
  // A square of 2 r + 1 cells does not fit in a hanger up to hanger_max_width_m wide.
  const int r = std::max(1, static_cast<int>(std::ceil(0.5 * params_.hanger_max_width_m / grid_.resolution_m)));
  const CellBox b{std::max(0, x_lo - r - 2), std::min(nx - 1, x_hi + r + 2), std::max(0, y_lo - r - 2),
                  std::min(ny - 1, y_hi + r + 2)};
  auto at = [nx](int x, int y) {
    return static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x);
  };
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) mask_[at(x, y)] = 0;
  }
  for (const ScanPoint& p : part.points()) {
    std::size_t i = 0;
    if (cell_of(p, i)) mask_[i] = 1;
  }
  // Closing by one cell (the profiles' sampling gaps), then the opening.
  square_morphology(mask_, closed_, scratch_, nx, b, 1, true);
  square_morphology(closed_, closed_, scratch_, nx, b, 1, false);
  square_morphology(closed_, opened_, scratch_, nx, b, r, false);
  square_morphology(opened_, opened_, scratch_, nx, b, r, true);
  // The residue (occupied or closed, not kept by the opening) connected (8-way) to a residue cell near the top.
  const auto residue = [&](std::size_t c) { return (mask_[c] != 0 || closed_[c] != 0) && opened_[c] == 0; };
  std::size_t depth = 0;
  for (int y = std::max(b.y0, reach); y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) {
      const std::size_t c = at(x, y);
      if ((mask_[c] & 2U) != 0 || !residue(c)) continue;
      mask_[c] |= 2U;
      stack_[depth++] = static_cast<std::int32_t>(c);
      while (depth > 0) {
        const auto s = static_cast<std::size_t>(stack_[--depth]);
        ++report.removed_cells;
        const int sx = static_cast<int>(s % static_cast<std::size_t>(nx));
        const int sy = static_cast<int>(s / static_cast<std::size_t>(nx));
        for (int dy = -1; dy <= 1; ++dy) {
          for (int dx = -1; dx <= 1; ++dx) {
            const int xx = sx + dx, yy = sy + dy;
            if (xx < b.x0 || xx > b.x1 || yy < b.y0 || yy > b.y1) continue;
            const std::size_t n = at(xx, yy);
            if ((mask_[n] & 2U) != 0 || !residue(n)) continue;
            mask_[n] |= 2U;
            stack_[depth++] = static_cast<std::int32_t>(n);
          }
        }
      }
    }
  }
  if (report.removed_cells == 0) return report;
  // A point beyond the grid goes with the border cell it lies out of: a chain runs on above the grid's top to the
  // field's (shipped catalogue under `stray_points`, ribbed_v3 s1190002: its 200 mm beyond the grid stayed with the
  // part, and every template's Perfect Match error was 4.5 times its limit).
  report.removed_points = part.filter([&](const ScanPoint& p) {
    int x = 0, y = 0;
    const bool in_box = border_cell_of(p, x, y) && x >= b.x0 && x <= b.x1 && y >= b.y0 && y <= b.y1;
    return !in_box || (mask_[at(x, y)] & 2U) == 0;  // (mask_ beyond b holds other work's marks)
  });
  return report;
}

bool PartIsolator::sheet_plane(const ScanBuffer& part, const CellBox& box, Eigen::Vector3d& plane, double& cx,
                               double& cy) {
  // Start: the densest depth layer and the layers beside it, level; then least squares on the points near the last
  // plane, twice (the first band is a strip across a tilted part, the next ones the whole sheet). Relief and ghosts
  // lie beyond kSheetBandM. Every stride-th point: a plane needs no 100 000 of them (all of them cost 7 ms a scan).
  constexpr double kSheetBandM = 0.005;
  constexpr int kMinSheetPoints = 100;
  constexpr std::size_t kPlaneSamples = 4000;
  const std::span<const ScanPoint> points = part.points();
  const std::size_t stride = std::max<std::size_t>(1, points.size() / kPlaneSamples);
  cx = grid_.origin_m.x() + 0.5 * (box.x0 + box.x1 + 1) * grid_.resolution_m;
  cy = grid_.origin_m.y() + 0.5 * (box.y0 + box.y1 + 1) * grid_.resolution_m;
  const int nz = static_cast<int>(depth_count_.size());
  std::fill(depth_count_.begin(), depth_count_.end(), 0);
  for (std::size_t i = 0; i < points.size(); i += stride) {
    const int z = depth_layer(points[i]);
    if (z >= 0 && z < nz) ++depth_count_[static_cast<std::size_t>(z)];
  }
  const auto densest =
      static_cast<int>(std::max_element(depth_count_.begin(), depth_count_.end()) - depth_count_.begin());
  plane = {grid_.origin_m.z() + (densest + 0.5) * grid_.resolution_m, 0.0, 0.0};
  double band = std::max(kSheetBandM, 1.5 * grid_.resolution_m);
  for (int pass = 0; pass < 3; ++pass) {
    PlaneLeastSquares fit(cx, cy);
    for (std::size_t i = 0; i < points.size(); i += stride) {
      const ScanPoint& p = points[i];
      if (finite_point(p) && plane_offset(p, plane, cx, cy) <= band) fit.add(p);
    }
    if (fit.points() < kMinSheetPoints || !fit.solve(plane)) return pass > 0;
    band = kSheetBandM;
  }
  return true;
}

GhostReport PartIsolator::drop_ghosts(ScanBuffer& part) {
  GhostReport report;
  const CellBox box = occupied_box(part, false);
  Eigen::Vector3d plane;
  double cx = 0.0, cy = 0.0;
  if (box.x1 < 0 || !sheet_plane(part, box, plane, cx, cy)) return report;
  const int nx = grid_.nx;
  const int ny = grid_.ny;
  // One cell of room around the box: the groups are closed across one empty cell.
  const CellBox b{std::max(0, box.x0 - 1), std::min(nx - 1, box.x1 + 1), std::max(0, box.y0 - 1),
                  std::min(ny - 1, box.y1 + 1)};
  auto at = [nx](int x, int y) {
    return static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x);
  };
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) {
      mask_[at(x, y)] = 0;
      label_[at(x, y)] = -1;
    }
  }
  for (const ScanPoint& p : part.points()) {
    std::size_t i = 0;
    if (finite_point(p) && cell_of(p, i)) {
      mask_[i] |= plane_offset(p, plane, cx, cy) > params_.ghost_sheet_m ? kOffCell : kSheetCell;
    }
  }
  // The sheet's extent per row and column.
  std::fill(row_lo_.begin() + b.y0, row_lo_.begin() + b.y1 + 1, nx);
  std::fill(row_hi_.begin() + b.y0, row_hi_.begin() + b.y1 + 1, -1);
  std::fill(col_lo_.begin() + b.x0, col_lo_.begin() + b.x1 + 1, ny);
  std::fill(col_hi_.begin() + b.x0, col_hi_.begin() + b.x1 + 1, -1);
  bool any_off = false;
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) {
      const std::uint8_t m = mask_[at(x, y)];
      any_off = any_off || m == kOffCell;
      if ((m & kSheetCell) == 0) continue;
      const auto yu = static_cast<std::size_t>(y), xu = static_cast<std::size_t>(x);
      row_lo_[yu] = std::min(row_lo_[yu], x);
      row_hi_[yu] = std::max(row_hi_[yu], x);
      col_lo_[xu] = std::min(col_lo_[xu], y);
      col_hi_[xu] = std::max(col_hi_[xu], y);
    }
  }
  if (!any_off) return report;  // the usual case: every cell holds the sheet or relief rising from it
  // Groups of the cells holding only off-sheet points: 8-neighbours through their one-cell dilation (gaps of one or two
  // empty cells: the profiles' sampling).
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) scratch_[at(x, y)] = mask_[at(x, y)] == kOffCell ? 1 : 0;
  }
  square_morphology(scratch_, bridged_, closed_, nx, b, 1, true);
  int groups = 0;
  for (int y = b.y0; y <= b.y1; ++y) {
    for (int x = b.x0; x <= b.x1; ++x) {
      const std::size_t seed = at(x, y);
      if (mask_[seed] != kOffCell || label_[seed] >= 0) continue;
      const int id = groups++;
      CellBox g{x, x, y, y};
      const int cells = fill_off_group(seed, id, b, g);
      if (cells < params_.fragment_min_cells || !ghost_group(id, g, cells)) continue;
      // Marked for the filter below (kOffCell | 4): the group's cells hold no sheet point.
      for (int yy = g.y0; yy <= g.y1; ++yy) {
        for (int xx = g.x0; xx <= g.x1; ++xx) {
          if (label_[at(xx, yy)] == id && mask_[at(xx, yy)] == kOffCell) mask_[at(xx, yy)] |= 4U;
        }
      }
      ++report.pieces;
    }
  }
  if (report.pieces == 0) return report;
  report.removed_points = part.filter([&](const ScanPoint& p) {
    std::size_t i = 0;
    return !cell_of(p, i) || (mask_[i] & 4U) == 0;
  });
  return report;
}

int PartIsolator::fill_off_group(std::size_t seed, int id, const CellBox& b, CellBox& g) {
  const int nx = grid_.nx;
  auto at = [nx](int x, int y) {
    return static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x);
  };
  int cells = 0;
  std::size_t top = 0;
  stack_[top++] = static_cast<std::int32_t>(seed);
  label_[seed] = id;
  while (top > 0) {
    const auto c = static_cast<std::size_t>(stack_[--top]);
    const int sx = static_cast<int>(c % static_cast<std::size_t>(nx));
    const int sy = static_cast<int>(c / static_cast<std::size_t>(nx));
    if (mask_[c] == kOffCell) {
      ++cells;
      g = {std::min(g.x0, sx), std::max(g.x1, sx), std::min(g.y0, sy), std::max(g.y1, sy)};
    }
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dx = -1; dx <= 1; ++dx) {
        const int xx = sx + dx, yy = sy + dy;
        if (xx < b.x0 || xx > b.x1 || yy < b.y0 || yy > b.y1) continue;
        const std::size_t n = at(xx, yy);
        // Through the closed cells that hold no sheet: a cell of the sheet ends the group.
        if (bridged_[n] == 0 || (mask_[n] & kSheetCell) != 0 || label_[n] >= 0) continue;
        label_[n] = id;
        stack_[top++] = static_cast<std::int32_t>(n);
      }
    }
  }
  return cells;
}

bool PartIsolator::ghost_group(int id, const CellBox& g, int cells) const {
  const int nx = grid_.nx;
  const int ny = grid_.ny;
  const int r = std::max(0, params_.ghost_touch_cells);
  auto at = [nx](int x, int y) {
    return static_cast<std::size_t>(y) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(x);
  };
  int beyond = 0;
  for (int y = g.y0; y <= g.y1; ++y) {
    for (int x = g.x0; x <= g.x1; ++x) {
      if (label_[at(x, y)] != id || mask_[at(x, y)] != kOffCell) continue;
      // Borders the sheet: relief rising from it (a flange's face, a rib's wall), not a ghost.
      for (int yy = std::max(0, y - r); yy <= std::min(ny - 1, y + r); ++yy) {
        for (int xx = std::max(0, x - r); xx <= std::min(nx - 1, x + r); ++xx) {
          if ((mask_[at(xx, yy)] & kSheetCell) != 0) return false;
        }
      }
      const auto yu = static_cast<std::size_t>(y), xu = static_cast<std::size_t>(x);
      beyond += x < row_lo_[yu] || x > row_hi_[yu] || y < col_lo_[xu] || y > col_hi_[xu] ? 1 : 0;
    }
  }
  return beyond >= params_.ghost_beyond_share * cells;
}

}  // namespace cellsight::algo
