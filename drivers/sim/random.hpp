// The simulator's seeded random numbers: the generator in algo/random.hpp, under the names the simulator uses.
#pragma once

#include "algo/random.hpp"

namespace cellsight::sim {

using algo::mix_seed;
using algo::Rng;
using algo::splitmix64;

}  // namespace cellsight::sim
