// SplitMix64: the one tiny deterministic generator and seed mixer of algo/, so fits and training runs do not depend
// on a library's RNG and are reproducible for a seed.
#pragma once

#include <cstdint>

namespace cellsight::algo {

// The next number of the sequence of `state` (Steele, Lea and Flood 2014).
constexpr std::uint64_t splitmix64(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9E3779B97F4A7C15ULL);
  z = (z ^ (z >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27U)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31U);
}

// An independent, reproducible seed for purpose or index b derived from seed a (training's streams; the simulator
// mixes its seeds with algo/random.hpp's mix_seed, whose sequence its rendered passes depend on).
constexpr std::uint64_t stream_seed(std::uint64_t a, std::uint64_t b) {
  std::uint64_t state = a + 0x9E3779B97F4A7C15ULL * b;  // splitmix64 adds one more step: b + 1 as before
  return splitmix64(state);
}

}  // namespace cellsight::algo
