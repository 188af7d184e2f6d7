// Tests of algo/part_isolation: material not connected to the part is dropped before features and matching, the
// part itself is never cut. Synthetic point sets on the real grid spacing; the truth is which points were drawn as
// what.
#include <algorithm>
#include <catch2/catch.hpp>
#include <cstdint>
#include <iterator>
#include <random>
#include <string>
#include <vector>

#include "algo/grid.hpp"
#include "algo/part_isolation.hpp"
#include "algo/scan.hpp"

using namespace cellsight;
using algo::ScanPoint;

namespace {

algo::GridSpec grid() {
  algo::GridSpec g;
  g.origin_m = {0.0, 0.0, 0.0};
  g.resolution_m = 0.0022;
  g.nx = 296;
  g.ny = 500;
  g.nz = 182;
  return g;
}

// A sheet on the scan's sampling (one profile per 2.2 mm along x, a point per 1.6 mm along y); `tag` goes to `row`
// so the test knows what each point was drawn as.
void add_sheet(std::vector<ScanPoint>& out, double x0, double x1, double y0, double y1, double z, std::uint16_t tag) {
  for (double x = x0; x < x1; x += 0.0022) {
    for (double y = y0; y < y1; y += 0.0016) {
      out.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, tag});
    }
  }
}

algo::ScanBuffer buffer_of(const std::vector<ScanPoint>& points) {
  algo::ScanBuffer b(points.size() + 16);
  for (const ScanPoint& p : points) b.push(p);
  return b;
}

int count_tag(const algo::ScanBuffer& b, std::uint16_t tag) {
  int n = 0;
  for (const ScanPoint& p : b.points()) n += p.row == tag ? 1 : 0;
  return n;
}

constexpr std::uint16_t kPart = 1, kStray = 2, kSpeck = 3;

}  // namespace

SCENARIO("A neighbour's part at the field's edge and loose specks are separated from the part", "[isolation]") {
  algo::PartIsolator isolator(grid(), algo::IsolationParams{});
  GIVEN("a 450 x 700 mm plate in the middle of the grid") {
    std::vector<ScanPoint> points;
    add_sheet(points, 0.10, 0.55, 0.20, 0.90, 0.20, kPart);
    const int part_points = static_cast<int>(points.size());
    WHEN("the same strip ends 30 mm before the scanned range does (a piece of the part's own cut-off?)") {
      add_sheet(points, 0.57, 0.61, 0.30, 0.80, 0.21, kStray);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      THEN("it stays: only material at the field's edge is a neighbour's") {
        CHECK(r.dropped_pieces == 0);
      }
    }
    WHEN("a 40 mm sheet strip enters from the scanned range's right end, 20 mm away from the plate") {
      add_sheet(points, 0.57, 0.61, 0.30, 0.80, 0.21, kStray);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.61);
      THEN("the strip is dropped, counted as an edge piece, and every plate point stays") {
        CHECK(r.pieces == 2);
        CHECK(r.dropped_pieces == 1);
        CHECK(r.edge_pieces == 1);
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("a neighbour's sheet edge at the right end is crossed by a 12 mm glare band 10 mm in from the end") {
      // (Shipped catalogue under `mixed`, ribbed_v3 s1010008: the piece beyond the band was kept, 9 027 mm2 of it.)
      add_sheet(points, 0.575, 0.613, 0.30, 0.80, 0.21, kStray);
      add_sheet(points, 0.625, 0.635, 0.30, 0.80, 0.21, kStray);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("the piece beyond the band, beside the end piece, goes with it; every plate point stays") {
        CHECK(r.pieces == 3);
        CHECK(r.dropped_pieces == 2);
        CHECK(r.edge_pieces == 2);
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("a glare band that leaves no point cuts the plate's right 95 mm off, a neighbour's sheet at the right end") {
      // (Fresh shipped catalogue under `mixed`, s1570009: the plate's far half lay between the neighbour's piece and
      // the part, beside both in y, and was dropped as the neighbour's.)
      std::vector<ScanPoint> cut;
      std::copy_if(points.begin(), points.end(), std::back_inserter(cut),
                   [](const ScanPoint& p) { return p.x < 0.44F || p.x > 0.455F; });
      const int kept_part = static_cast<int>(cut.size());
      add_sheet(cut, 0.575, 0.635, 0.05, 0.60, 0.21, kStray);
      algo::ScanBuffer b = buffer_of(cut);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("the plate's far half stays (its y range is the plate's), the neighbour's sheet goes") {
        CHECK(r.pieces == 3);
        CHECK(r.dropped_pieces == 1);
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == kept_part);
      }
    }
    WHEN("a strip beyond the plate's end has an end piece beside it only above it (another neighbour's corner)") {
      add_sheet(points, 0.575, 0.613, 0.30, 0.80, 0.21, kStray);
      add_sheet(points, 0.625, 0.635, 0.85, 0.95, 0.21, kSpeck);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("the strip stays (it does not continue that piece), the end piece goes") {
        CHECK(r.dropped_pieces == 1);
        CHECK(count_tag(b, kStray) > 0);
        CHECK(count_tag(b, kSpeck) == 0);
      }
    }
    WHEN("the same scan is isolated for the second look (a glare band may have cut the part's end off)") {
      add_sheet(points, 0.57, 0.61, 0.30, 0.80, 0.21, kStray);
      add_sheet(points, 0.30, 0.302, 0.97, 0.972, 0.2, kSpeck);  // at the plate's depth: a piece, not a depth outlier
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.61, true);
      THEN("the strip stays, the speck still goes") {
        CHECK(r.edge_pieces == 0);
        CHECK(r.dropped_pieces == 1);
        CHECK(count_tag(b, kStray) > 0);
        CHECK(count_tag(b, kSpeck) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("a neighbour's sheet edge enters at the scanned range's right end below the grid's bottom (y < 0)") {
      add_sheet(points, 0.606, 0.635, -0.035, 0.0, 0.21, kStray);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("it is dropped (its points count in the grid's bottom row there), and every plate point stays") {
        CHECK(r.dropped_pieces == 1);
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("a few specular specks float in front of the carrier away from it") {
      add_sheet(points, 0.02, 0.024, 0.05, 0.052, 0.1, kSpeck);
      add_sheet(points, 0.30, 0.302, 0.97, 0.972, 0.1, kSpeck);
      algo::ScanBuffer b = buffer_of(points);
      (void)isolator.isolate(b, 0.0165, 0.635);
      THEN("they go, the plate stays whole") {
        CHECK(count_tag(b, kSpeck) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
  }
  GIVEN("the same plate cut in two by a 30 mm glare band that left no point") {
    std::vector<ScanPoint> points;
    add_sheet(points, 0.10, 0.30, 0.20, 0.90, 0.20, kPart);
    add_sheet(points, 0.33, 0.55, 0.20, 0.90, 0.20, kPart);
    const int part_points = static_cast<int>(points.size());
    WHEN("it is isolated") {
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("both halves stay: neither reaches the field's edge") {
        CHECK(r.pieces == 2);
        CHECK(r.dropped_pieces == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
  }
  GIVEN("the plate with its corner cut off by a 21 mm glare band: a triangle of 50 mm legs, under 0.5 % of the rest") {
    // (Shipped catalogue under `glare`, perforated_fine s1170003: the corner beyond the band, dropped as clutter,
    // looked cut off: 2 362 mm2 missing, and the pass was unknown; a twin with that corner chamfered would match.)
    auto corner_points = [](double dy, double dz) {
      std::vector<ScanPoint> all, points;
      add_sheet(all, 0.10, 0.55, 0.20, 0.90, 0.20, kPart);
      for (ScanPoint p : all) {
        const double d = (p.x - 0.10) + (0.90 - p.y);  // along the diagonal from the top-left corner
        if (d >= 0.05 && d < 0.08) continue;           // the band left no point
        if (d < 0.05) {
          p.row = kStray;
          p.y += static_cast<float>(dy);
          p.z += static_cast<float>(dz);
        }
        points.push_back(p);
      }
      return points;
    };
    WHEN("it is isolated") {
      const auto points = corner_points(0.0, 0.0);
      algo::ScanBuffer b = buffer_of(points);
      const int corner = count_tag(b, kStray);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("the corner stays, a fragment of the part") {
        CHECK(r.pieces == 2);
        CHECK(r.dropped_pieces == 0);
        CHECK(r.fragments == 1);
        CHECK(corner > 200);
        CHECK(b.size() == points.size());
      }
    }
    struct Apart {
      const char* where;
      double dy, dz;
    };
    for (const Apart& apart : {Apart{"30 mm in front of the part's depths", 0.0, 0.03},
                               Apart{"60 mm above the part's box, farther than a glare band is wide", 0.11, 0.0}}) {
      WHEN(std::string("the same piece lies ") + apart.where) {
        const auto points = corner_points(apart.dy, apart.dz);
        algo::ScanBuffer b = buffer_of(points);
        const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
        THEN("it goes: not the part's") {
          CHECK(r.fragments == 0);
          CHECK(count_tag(b, kStray) == 0);
        }
      }
    }
  }
  GIVEN("the plate with a 30 mm flange at 90 deg on each side edge, the left one joined to it (so its depths count)") {
    // (Development catalogue 11360, rnd04 s1170002: the right flange seen edge-on showed only its outer part, a line
    // 10 mm beside the edge and 10-30 mm in front of the sheet; kept as a fragment, 397 mm2 of extra material.)
    auto flanged = [](double line_z0, double line_z1) {
      std::vector<ScanPoint> points;
      add_sheet(points, 0.10, 0.55, 0.20, 0.90, 0.20, kPart);
      for (double z = 0.20; z < 0.23; z += 0.002) add_sheet(points, 0.10, 0.1022, 0.20, 0.90, z, kPart);
      for (double z = line_z0; z < line_z1; z += 0.002) add_sheet(points, 0.565, 0.566, 0.30, 0.80, z, kStray);
      return points;
    };
    struct Line {
      const char* where;
      double z0, z1;
      bool kept;
    };
    for (const Line& line :
         {Line{"5-25 mm in front of the sheet (the right flange's outer part)", 0.205, 0.225, false},
          Line{"on the sheet's plane (a strip a glare band cut off the edge)", 0.2, 0.201, true},
          Line{"from the sheet's plane to 20 mm in front (a strip cut off with a flange's wall)", 0.2, 0.22, true}}) {
      WHEN(std::string("a line 15 mm beside the right edge lies ") + line.where) {
        const auto points = flanged(line.z0, line.z1);
        algo::ScanBuffer b = buffer_of(points);
        const int drawn = count_tag(b, kStray);
        const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
        THEN(std::string(line.kept
                             ? "it stays, a fragment of the part"
                             : "it goes: within the part's depths (the left flange's), not on the sheet beside it")) {
          CHECK(r.pieces == 2);
          CHECK(r.fragments == (line.kept ? 1 : 0));
          CHECK(count_tag(b, kStray) == (line.kept ? drawn : 0));
          CHECK(drawn > 300);
        }
      }
    }
  }
  GIVEN("the plate with its left flange, and beside its right edge a piece along the whole edge, larger than clutter") {
    // (Fresh shipped catalogue, channel_u s1210001 / s1210002, and fresh random catalogue 11376, rnd03 s1210001: a
    // part swung 2.7 deg showed its right 90 deg flange's end edge-on, a line 40 mm beside the edge and 60 mm in
    // front of the sheet, 300-330 cells, above min_keep_share of the part: kept, and every template's Perfect Match
    // error was 2-8 x its limit.)
    auto beside = [](double x1, double z0, double z1) {
      std::vector<ScanPoint> points;
      add_sheet(points, 0.10, 0.55, 0.20, 0.90, 0.20, kPart);
      for (double z = 0.20; z < 0.23; z += 0.002) add_sheet(points, 0.10, 0.1022, 0.20, 0.90, z, kPart);
      for (double z = z0; z < z1; z += 0.002) add_sheet(points, 0.57, x1, 0.20, 0.90, z, kStray);
      return points;
    };
    struct Piece {
      const char* what;
      double x1, z0, z1;
      bool kept;
    };
    for (const Piece& piece :
         {Piece{"a line two cells wide, 5-25 mm in front of the sheet (a flange's end)", 0.574, 0.205, 0.225, false},
          Piece{"the same line on the sheet's plane (a strip a glare band cut off)", 0.574, 0.2, 0.201, true},
          Piece{"a strip 20 mm wide, 5-25 mm in front of the sheet (a flange's face cut off by a band)", 0.59, 0.205,
                0.225, true}}) {
      WHEN(std::string("the piece is ") + piece.what) {
        const auto points = beside(piece.x1, piece.z0, piece.z1);
        algo::ScanBuffer b = buffer_of(points);
        const int drawn = count_tag(b, kStray);
        const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
        THEN(std::string(piece.kept ? "it stays" : "it goes: a line beside the edge, not on the sheet")) {
          CHECK(r.pieces == 2);
          CHECK(r.fragments == 0);
          CHECK(r.edge_lines == (piece.kept ? 0 : 1));
          CHECK(count_tag(b, kStray) == (piece.kept ? drawn : 0));
          CHECK(count_tag(b, kPart) == count_tag(buffer_of(points), kPart));
          CHECK(drawn > 600);
        }
      }
    }
  }
  GIVEN("the plate crossed by a 30 mm glare band whose residue is single points 15 mm apart along its middle") {
    // (Shipped catalogue under `glare`, plate_4h s1180006: residue points out of the bridging's reach were dropped as
    // clutter where the residue was sparse, and the check took that emptied stretch of the band for a hole.)
    auto banded = [](double dz) {
      std::vector<ScanPoint> points;
      add_sheet(points, 0.10, 0.55, 0.20, 0.50, 0.20, kPart);
      add_sheet(points, 0.10, 0.55, 0.53, 0.90, 0.20, kPart);
      for (double x = 0.11; x < 0.55; x += 0.015) {
        points.push_back({static_cast<float>(x), 0.515F, static_cast<float>(0.20 + dz), 0, kSpeck});
      }
      return points;
    };
    WHEN("it is isolated") {
      const auto points = banded(0.0);
      algo::ScanBuffer b = buffer_of(points);
      const int residue = count_tag(b, kSpeck);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("every residue point stays, each a speck of the part") {
        CHECK(residue == 30);
        CHECK(r.specks == residue);
        CHECK(r.dropped_pieces == 0);
        CHECK(b.size() == points.size());
      }
    }
    WHEN("the same points lie 30 mm in front of the plate (outliers off its depths)") {
      const auto points = banded(0.03);
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("they go") {
        CHECK(r.specks == 0);
        CHECK(count_tag(b, kSpeck) == 0);
        CHECK(count_tag(b, kPart) == static_cast<int>(points.size()) - 30);
      }
    }
  }
  GIVEN("a plate hanging 20 mm out of the grid's bottom, and a loose speck 100 mm below the grid beside it") {
    // (Beyond the grid only the column is known: a speck below the part's own columns would join the part.)
    std::vector<ScanPoint> points;
    add_sheet(points, 0.10, 0.55, -0.02, 0.68, 0.20, kPart);
    const int part_points = static_cast<int>(points.size());
    add_sheet(points, 0.59, 0.592, -0.10, -0.098, 0.20, kSpeck);
    WHEN("it is isolated") {
      algo::ScanBuffer b = buffer_of(points);
      (void)isolator.isolate(b, 0.0165, 0.635);
      THEN("the part keeps the strip beyond the grid (it touches the part there), the speck goes") {
        CHECK(count_tag(b, kPart) == part_points);
        CHECK(count_tag(b, kSpeck) == 0);
      }
    }
  }
  GIVEN("a plate whose profiles lost 3 % of their points and one whole profile") {
    std::vector<ScanPoint> all;
    add_sheet(all, 0.10, 0.55, 0.20, 0.90, 0.20, kPart);
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    std::vector<ScanPoint> points;
    for (const ScanPoint& p : all) {
      if (u(rng) < 0.03 || std::abs(p.x - 0.3) < 0.0011) continue;
      points.push_back(p);
    }
    WHEN("it is isolated") {
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.635);
      THEN("it is one piece and nothing is dropped") {
        CHECK(r.pieces == 1);
        CHECK(b.size() == points.size());
      }
    }
  }
}

SCENARIO("The chain the part hangs from is cut off where it meets the part, the part's own features stay",
         "[isolation]") {
  algo::PartIsolator isolator(grid(), algo::IsolationParams{});
  constexpr std::uint16_t kChain = 4, kTab = 5;
  constexpr double kFieldTop = 1.0;  // the highest y the pass saw
  GIVEN("a 450 x 500 mm plate whose top edge is at y 0.70 m") {
    std::vector<ScanPoint> points;
    add_sheet(points, 0.10, 0.55, 0.20, 0.70, 0.20, kPart);
    const int part_points = static_cast<int>(points.size());
    WHEN("an 8 mm chain rises from its top edge to the field's top") {
      add_sheet(points, 0.30, 0.308, 0.70, kFieldTop, 0.20, kChain);
      algo::ScanBuffer b = buffer_of(points);
      const algo::HangerReport r = isolator.remove_hanger(b, kFieldTop);
      THEN("every chain point goes and every plate point stays") {
        CHECK(count_tag(b, kChain) == 0);
        CHECK(count_tag(b, kPart) == part_points);
        CHECK(r.removed_points > 0);
      }
    }
    WHEN("the chain runs on beyond the grid's top (1.1 m) to a field's top at 1.3 m") {
      // (Shipped catalogue under `stray_points`, ribbed_v3 s1190002: the chain's 200 mm beyond the grid stayed with
      // the part, and every template's Perfect Match error was 4.5 times its limit.)
      add_sheet(points, 0.30, 0.308, 0.70, 1.3, 0.20, kChain);
      algo::ScanBuffer b = buffer_of(points);
      int beyond = 0;
      for (const ScanPoint& p : b.points()) beyond += p.row == kChain && p.y > 1.1F ? 1 : 0;
      (void)isolator.remove_hanger(b, 1.3);
      THEN("its points beyond the grid go with it, and every plate point stays") {
        CHECK(beyond > 100);
        CHECK(count_tag(b, kChain) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("the chain is 12 mm wide, lost a profile and 5 % of its points") {
      std::vector<ScanPoint> chain;
      add_sheet(chain, 0.30, 0.312, 0.70, kFieldTop, 0.20, kChain);
      std::mt19937_64 rng(3);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      for (const ScanPoint& p : chain) {
        if (u(rng) >= 0.05 && std::abs(p.x - 0.3044) > 0.0011) points.push_back(p);
      }
      algo::ScanBuffer b = buffer_of(points);
      (void)isolator.remove_hanger(b, kFieldTop);
      THEN("it still goes whole, the plate stays whole") {
        CHECK(count_tag(b, kChain) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("the plate has a 10 mm tab on top that ends 100 mm below the field's top") {
      add_sheet(points, 0.30, 0.310, 0.70, 0.90, 0.20, kTab);
      algo::ScanBuffer b = buffer_of(points);
      const std::size_t before = b.size();
      const algo::HangerReport r = isolator.remove_hanger(b, kFieldTop);
      THEN("the tab is the part's: nothing is cut") {
        CHECK(r.removed_points == 0);
        CHECK(b.size() == before);
      }
    }
    WHEN("a 40 mm wide arm of the part itself reaches the field's top") {
      add_sheet(points, 0.30, 0.34, 0.70, kFieldTop, 0.20, kTab);
      algo::ScanBuffer b = buffer_of(points);
      const std::size_t before = b.size();
      (void)isolator.remove_hanger(b, kFieldTop);
      THEN("it is wider than any hanger and stays") {
        CHECK(b.size() == before);
      }
    }
    WHEN("nothing rises above the plate") {
      algo::ScanBuffer b = buffer_of(points);
      const algo::HangerReport r = isolator.remove_hanger(b, kFieldTop);
      THEN("nothing is cut") {
        CHECK(r.removed_cells == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
  }
}

SCENARIO("A ghost of the stripe in front of the part is dropped, the part's own relief and flanges stay",
         "[isolation]") {
  algo::PartIsolator isolator(grid(), algo::IsolationParams{});
  constexpr std::uint16_t kRelief = 4;
  GIVEN("a 450 x 700 mm plate at 100 mm depth (its sheet plane, as a pass sees it)") {
    std::vector<ScanPoint> points;
    add_sheet(points, 0.10, 0.55, 0.20, 0.90, 0.10, kPart);
    const int part_points = static_cast<int>(points.size());
    WHEN("a secondary reflection puts a slanted ghost surface 150-450 mm in front of it, over the plate in x-y") {
      // What the simulated cell's bare-metal ghosts left in two passes (issue 11): a few percent of the points.
      for (double y = 0.32; y < 0.90; y += 0.0016) {
        for (double x = 0.45; x < 0.55; x += 0.0066) {
          const double z = 0.25 + 0.4 * (y - 0.32) / 0.58;
          points.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, kStray});
        }
      }
      const int ghost_points = static_cast<int>(points.size()) - part_points;
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      THEN("every ghost point and no plate point is dropped, counted as beyond the depth gap") {
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == part_points);
        CHECK(r.depth_points == static_cast<std::size_t>(ghost_points));
        CHECK(r.dropped_points == static_cast<std::size_t>(ghost_points));
      }
    }
    WHEN("it has an 80 mm flange bent toward the camera at its bottom and a 20 mm rib, seen on their faces") {
      // The flange's face: from the sheet's depth to 80 mm in front of it, sampled like the sheet.
      for (double x = 0.10; x < 0.55; x += 0.0022) {
        for (double z = 0.10; z < 0.18; z += 0.0016) {
          points.push_back({static_cast<float>(x), 0.20F, static_cast<float>(z), 0, kRelief});
        }
      }
      add_sheet(points, 0.20, 0.40, 0.50, 0.52, 0.12, kRelief);
      const int relief_points = static_cast<int>(points.size()) - part_points;
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      THEN("nothing is dropped") {
        CHECK(r.depth_points == 0);
        CHECK(count_tag(b, kRelief) == relief_points);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
    WHEN("a reflection's ghost lies beside its right edge, 20 mm apart, from 25 mm in front of its rib to 400 mm") {
      // (Fresh random catalogue 11335, pass 1110009: the stripe's reflection off louvres, in front of the part's edge,
      // its depths running on from just before the part's relief, so no depth gap sets it apart.)
      add_sheet(points, 0.20, 0.40, 0.50, 0.52, 0.12, kRelief);
      const int relief_points = static_cast<int>(points.size()) - part_points;
      for (double x = 0.57; x < 0.62; x += 0.0022) {
        for (double y = 0.35; y < 0.85; y += 0.0016) {
          const double z = 0.145 + 0.3 * (y - 0.35) / 0.5;
          points.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, kStray});
        }
      }
      algo::ScanBuffer b = buffer_of(points);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      THEN("the ghost goes as a piece apart in depth; the plate and its rib stay whole") {
        CHECK(count_tag(b, kStray) == 0);
        CHECK(r.depth_pieces == 1);
        CHECK(r.edge_pieces == 0);
        CHECK(count_tag(b, kPart) == part_points);
        CHECK(count_tag(b, kRelief) == relief_points);
      }
    }
    WHEN("a glare band 15 mm wide cuts off a 40 mm strip at its right edge that has a 20 mm rib on it") {
      std::vector<ScanPoint> cut;
      for (const ScanPoint& p : points) {
        if (p.x < 0.495F || p.x > 0.51F) cut.push_back(p);
      }
      add_sheet(cut, 0.52, 0.54, 0.30, 0.80, 0.12, kRelief);
      algo::ScanBuffer b = buffer_of(cut);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      THEN("the strip is the part's: nothing is dropped") {
        CHECK(r.pieces == 2);
        CHECK(r.dropped_pieces == 0);
        CHECK(b.size() == cut.size());
      }
    }
    WHEN("a few stray points sit 300 mm in front of it") {
      for (int i = 0; i < 5; ++i) points.push_back({0.3F + 0.01F * static_cast<float>(i), 0.5F, 0.40F, 0, kSpeck});
      algo::ScanBuffer b = buffer_of(points);
      (void)isolator.isolate(b, 0.0165, 0.64);
      THEN("they go with the depth gap, the plate stays whole") {
        CHECK(count_tag(b, kSpeck) == 0);
        CHECK(count_tag(b, kPart) == part_points);
      }
    }
  }
}

SCENARIO("A ghost of the stripe floating beside the part's edge goes though the bridging joined it, relief stays",
         "[isolation]") {
  algo::PartIsolator isolator(grid(), algo::IsolationParams{});
  constexpr std::uint16_t kRelief = 4;
  // A 450 x 700 mm plate hanging tilted: 30 mm deeper at its top than at its bottom (2.5 deg), one profile per
  // 2.2 mm along x; its last profile at x = 0.5478 m.
  const auto sheet_z = [](double y) { return 0.10 + 0.03 * (y - 0.20) / 0.70; };
  std::vector<ScanPoint> points;
  for (double x = 0.10; x < 0.549; x += 0.0022) {
    for (double y = 0.20; y < 0.90; y += 0.0016) {
      points.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(sheet_z(y)), 0, kPart});
    }
  }
  // A rib 20 mm in front of the sheet on it, seen on its top only (its walls shaded): relief that does not touch
  // the sheet's depth, inside the sheet's extent.
  for (double x = 0.20; x < 0.40; x += 0.0022) {
    for (double y = 0.50; y < 0.53; y += 0.0016) {
      points.push_back(
          {static_cast<float>(x), static_cast<float>(y), static_cast<float>(sheet_z(y) + 0.025), 0, kRelief});
    }
  }
  std::erase_if(points, [](const ScanPoint& p) {
    return p.row == kPart && p.x > 0.195F && p.x < 0.405F && p.y > 0.495F && p.y < 0.535F;
  });
  const auto kept_part =
      static_cast<int>(std::count_if(points.begin(), points.end(), [](const ScanPoint& p) { return p.row == kPart; }));
  const auto relief_points = static_cast<int>(points.size()) - kept_part;
  GIVEN("the plate with a rib on it") {
    WHEN("a ghost begins two empty profiles beside its right edge, 38 mm in front of the sheet, rising to 110 mm") {
      // Fresh random catalogue 11391, rnd07 s1240008: 900 points over x 0.588-0.643, y 0.50-0.76, 38-133 mm in
      // front of the sheet, the part's last profile at 0.582: unknown (Perfect Match error and outliers over their
      // limits).
      std::vector<ScanPoint> scan = points;
      for (double x = 0.5544; x < 0.600; x += 0.0022) {
        for (double y = 0.50; y < 0.76; y += 0.0032) {
          const double z = sheet_z(y) + 0.038 + 1.5 * (x - 0.5544);
          scan.push_back({static_cast<float>(x), static_cast<float>(y), static_cast<float>(z), 0, kStray});
        }
      }
      const int ghost_points = static_cast<int>(scan.size() - points.size());
      algo::ScanBuffer b = buffer_of(scan);
      const algo::IsolationReport r = isolator.isolate(b, 0.0165, 0.64);
      REQUIRE(count_tag(b, kStray) == ghost_points);  // the bridging joined it to the part: isolate keeps it
      const algo::GhostReport g = isolator.drop_ghosts(b);
      THEN("drop_ghosts takes every ghost point and nothing of the plate or its rib") {
        CHECK(r.dropped_points == 0);
        CHECK(g.pieces == 1);
        CHECK(g.removed_points == static_cast<std::size_t>(ghost_points));
        CHECK(count_tag(b, kStray) == 0);
        CHECK(count_tag(b, kPart) == kept_part);
        CHECK(count_tag(b, kRelief) == relief_points);
      }
    }
    WHEN("a flange bent toward the camera along its right edge is seen on its face, 60 mm from the sheet out") {
      std::vector<ScanPoint> scan = points;
      for (double y = 0.20; y < 0.90; y += 0.0016) {
        for (double d = 0.0; d < 0.060; d += 0.0016) {
          // 75 deg: its face leans out, 16 mm beyond the edge at its rim.
          scan.push_back({static_cast<float>(0.5478 + 0.0022 + d * 0.27), static_cast<float>(y),
                          static_cast<float>(sheet_z(y) + d), 0, kRelief});
        }
      }
      const auto relief = static_cast<int>(scan.size() - points.size()) + relief_points;
      algo::ScanBuffer b = buffer_of(scan);
      (void)isolator.isolate(b, 0.0165, 0.64);
      const algo::GhostReport g = isolator.drop_ghosts(b);
      THEN("it rises from the sheet: nothing is dropped") {
        CHECK(g.pieces == 0);
        CHECK(count_tag(b, kRelief) == relief);
        CHECK(count_tag(b, kPart) == kept_part);
      }
    }
    WHEN("nothing else is in the scan") {
      algo::ScanBuffer b = buffer_of(points);
      const algo::GhostReport g = isolator.drop_ghosts(b);
      THEN("the rib, off the sheet but inside its extent, stays") {
        CHECK(g.pieces == 0);
        CHECK(b.size() == points.size());
      }
    }
  }
}
