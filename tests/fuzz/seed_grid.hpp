// The grid of the seed template (tests/fuzz/make_seeds.cpp writes it, fuzz_template opens files against it): 8 cells
// of 10 mm a side, so a whole valid template is 12 KiB.
#pragma once

#include "algo/grid.hpp"

namespace cellsight::fuzz {

inline algo::GridSpec seed_template_grid() {
  algo::GridSpec grid;
  grid.nx = grid.ny = grid.nz = 8;
  grid.resolution_m = 0.01;
  grid.origin_m = Eigen::Vector3d(0.0, 0.0, 0.0);
  return grid;
}

}  // namespace cellsight::fuzz
