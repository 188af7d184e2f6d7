// What the template builder and the template file share about the grid (internal to formats/): its dimensions as
// algo/distance_map takes them, the check that a template can be built and stored for it, and the number format of
// their messages.
#pragma once

#include <cstdio>
#include <string>

#include "algo/distance_map.hpp"
#include "algo/grid.hpp"
#include "algo/result.hpp"

namespace cellsight::formats::template_grid {

inline algo::GridDims dims_of(const algo::GridSpec& grid) {
  return {grid.nx, grid.ny, grid.nz, grid.resolution_m};
}

// "%.9g": short enough for a message, exact enough to tell grids apart.
inline std::string number(double v) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.9g", v);
  return buf;
}

inline Status validate_grid(const algo::GridSpec& grid) {
  if (Status dims = algo::validate_dims(dims_of(grid)); !dims) return dims;
  if (!grid.origin_m.allFinite()) return make_error("template: grid origin must be finite");
  return {};
}

}  // namespace cellsight::formats::template_grid
