// Seeded generator of part catalogues nobody designed for: random sheet-metal parts plus deliberate near twins.
#pragma once

#include <Eigen/Geometry>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "drivers/sim/scene.hpp"

namespace cellsight::sim {

// How a near twin differs from the part it is made from. Every difference is physically visible to the 2.2 mm
// grid (hole >= 25 mm, slot >= 20 mm wide, rib >= 12 mm rise) except kHeightPlus5mm, the deliberately hard case
// (about two grid cells), which a catalogue holds at most once.
enum class TwinRelation { kOneHoleMore, kOneRibLess, kMirrored, kOtherRelief, kHeightPlus5mm, kOneSlotMore };

struct TwinPair {
  std::size_t base = 0, twin = 0;  // indices into RandomCatalogue::parts; the twin is the base changed by `relation`
  TwinRelation relation = TwinRelation::kOneHoleMore;
};

struct RandomCatalogue {
  std::vector<PartSpec> parts;  // named rnd00, rnd01, ...; family and role set
  std::vector<TwinPair> twins;
};

constexpr int kRandomCatalogueMinParts = 2;
constexpr int kRandomCatalogueMaxParts = 300;
// Sizes of generated parts: the thesis's range, narrowed in width to what fits the 0.65 m grid at the pose extremes
// (+-50 mm, +-5 deg; tests/test_config.cpp checks the shipped catalogue the same way).
constexpr double kRandomWidthMinMm = 400.0, kRandomWidthMaxMm = 480.0;
constexpr double kRandomHeightMinMm = 650.0, kRandomHeightMaxMm = 800.0;
// Clear sheet kept between features, between a feature and the outline and between a feature and a bent flange.
constexpr double kLayoutMarginMm = 20.0;
// Smallest visible differences of the twin relations (see TwinRelation).
constexpr double kTwinHoleMinDiameterMm = 25.0, kTwinSlotMinWidthMm = 20.0, kTwinRibMinRiseMm = 12.0;
constexpr double kTwinHeightStepMm = 5.0;

// The catalogue of `count` parts for `seed` (count is clamped to [kRandomCatalogueMinParts, kRandomCatalogueMaxParts]).
// Deterministic on every platform: only sim::Rng and exactly representable rounding are used.
[[nodiscard]] RandomCatalogue generate_random_catalogue(int count, std::uint64_t seed);
[[nodiscard]] std::vector<PartSpec> random_catalogue(int count, std::uint64_t seed);

// How many near-twin pairs and untaught parts a catalogue of `count` parts has: 3 untaught from 5 parts on (one the
// twin of a taught part, the others unrelated); twin pairs 1 from 4 parts, 2 from 8, max(3, count / 10) from 12.
[[nodiscard]] int twin_pair_count(int count);
[[nodiscard]] int untaught_count(int count);
[[nodiscard]] const char* twin_relation_text(TwinRelation relation);

// The area of the sheet a feature covers with all its repeats (part frame, mm); for a flange the strip along its
// edge that stays clear (its inward lean, at least 1 mm).
[[nodiscard]] Eigen::AlignedBox2d feature_footprint_mm(const PartSpec& part, const FeatureSpec& feature);
// Empty when every feature keeps `margin_mm` from the outline, from flanges and from every other feature, and the
// repeats of a feature do not touch each other; else what is wrong.
[[nodiscard]] std::string check_layout(const PartSpec& part, double margin_mm);

}  // namespace cellsight::sim
