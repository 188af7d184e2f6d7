// Random part catalogues: reproducible from a seed, buildable, inside the grid, near twins that differ by exactly
// their stated relation, and a file that reads back into the same parts.
#include <unistd.h>

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <tuple>

#include "app/catalogue.hpp"
#include "app/config.hpp"
#include "app/sim_setup.hpp"
#include "cli/sim_mode.hpp"
#include "drivers/sim/random_catalogue.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {

app::Config shipped_config() {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  REQUIRE(cfg.ok());
  return *cfg;
}

fs::path fresh_dir() {
  return test::numbered_scratch_dir("random-catalogue");
}

// One physical feature on the sheet (repeats expanded, independently of the generator): kind, centre and size in
// micrometres, direction, edge. Rise and angle are kept apart so "other relief" can compare footprints alone.
using Footprint = std::tuple<int, long, long, long, long, long, long, bool, int>;
struct Instance {
  Footprint footprint;
  double rise_mm = 0, angle_deg = 0;
  auto operator<=>(const Instance&) const = default;
};

long um(double mm) {
  return std::lround(mm * 1000.0);
}

std::vector<Instance> instances(const sim::PartSpec& part, bool mirror = false) {
  std::vector<Instance> out;
  const double sign = mirror ? -1.0 : 1.0;
  for (const auto& f : part.features) {
    sim::Edge edge = f.edge;
    if (mirror && edge == sim::Edge::kLeft) {
      edge = sim::Edge::kRight;
    } else if (mirror && edge == sim::Edge::kRight) {
      edge = sim::Edge::kLeft;
    }
    const bool single = f.kind == sim::FeatureKind::kFlange;
    for (int iy = 0; iy < (single ? 1 : f.count_y); ++iy) {
      for (int ix = 0; ix < (single ? 1 : f.count_x); ++ix) {
        const double x = f.x_mm + (ix - 0.5 * (f.count_x - 1)) * f.pitch_x_mm;
        const double y = f.y_mm + (iy - 0.5 * (f.count_y - 1)) * f.pitch_y_mm;
        out.push_back({{static_cast<int>(f.kind), um(single ? 0 : sign * x), um(single ? 0 : y), um(f.diameter_mm),
                        um(f.width_mm), um(f.height_mm), um(f.length_mm), f.vertical, static_cast<int>(edge)},
                       f.rise_mm,
                       f.angle_deg});
      }
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<Instance> minus(const std::vector<Instance>& a, const std::vector<Instance>& b) {
  std::vector<Instance> out;
  std::set_difference(a.begin(), a.end(), b.begin(), b.end(), std::back_inserter(out));
  return out;
}

std::vector<Eigen::Vector2d> outline_set(const sim::PartSpec& part, bool mirror = false) {
  std::vector<Eigen::Vector2d> out = part.outline_mm;
  for (auto& p : out) p.x() *= mirror ? -1.0 : 1.0;
  std::sort(out.begin(), out.end(),
            [](const auto& p, const auto& q) { return std::pair(p.x(), p.y()) < std::pair(q.x(), q.y()); });
  return out;
}

int kind_of(const Instance& i) {
  return std::get<0>(i.footprint);
}

// Checks that `twin` is `base` changed by exactly `relation`, against the feature instances.
void check_relation(const sim::PartSpec& base, const sim::PartSpec& twin, sim::TwinRelation relation) {
  INFO(base.name << " -> " << twin.name << ": " << sim::twin_relation_text(relation));
  const auto b = instances(base), t = instances(twin);
  const auto added = minus(t, b), removed = minus(b, t);
  if (relation != sim::TwinRelation::kHeightPlus5mm) CHECK(twin.height_mm == base.height_mm);
  CHECK(twin.width_mm == base.width_mm);
  switch (relation) {
    case sim::TwinRelation::kOneHoleMore:
    case sim::TwinRelation::kOneSlotMore:
    case sim::TwinRelation::kOneRibLess: {
      // One instance more (hole, slot) or less (rib), nothing else changed.
      const bool less = relation == sim::TwinRelation::kOneRibLess;
      const auto& changed = less ? removed : added;
      CHECK(twin.outline_mm == base.outline_mm);
      CHECK((less ? added : removed).empty());
      REQUIRE(changed.size() == 1);
      const Instance& i = changed[0];
      if (relation == sim::TwinRelation::kOneHoleMore) {
        CHECK(kind_of(i) == static_cast<int>(sim::FeatureKind::kHole));
        CHECK(std::get<3>(i.footprint) >= um(sim::kTwinHoleMinDiameterMm));
      } else if (relation == sim::TwinRelation::kOneSlotMore) {
        CHECK(kind_of(i) == static_cast<int>(sim::FeatureKind::kSlot));
        CHECK(std::min(std::get<4>(i.footprint), std::get<5>(i.footprint)) >= um(sim::kTwinSlotMinWidthMm));
      } else {
        CHECK(kind_of(i) == static_cast<int>(sim::FeatureKind::kRib));
        CHECK(i.rise_mm >= sim::kTwinRibMinRiseMm);
      }
      break;
    }
    case sim::TwinRelation::kMirrored:
      CHECK(outline_set(twin) == outline_set(base, true));
      CHECK(t == instances(base, true));
      CHECK((t != b || outline_set(twin) != outline_set(base)));  // an asymmetric part: the mirror image is new
      break;
    case sim::TwinRelation::kOtherRelief: {
      CHECK(twin.outline_mm == base.outline_mm);
      // Same footprints everywhere; every rib became a louvre and every louvre a rib, nothing else changed.
      auto swapped = b;
      int relief = 0;
      for (auto& i : swapped) {
        auto& kind = std::get<0>(i.footprint);
        if (kind == static_cast<int>(sim::FeatureKind::kRib) || kind == static_cast<int>(sim::FeatureKind::kLouvre)) {
          kind = kind == static_cast<int>(sim::FeatureKind::kRib) ? static_cast<int>(sim::FeatureKind::kLouvre)
                                                                  : static_cast<int>(sim::FeatureKind::kRib);
          ++relief;
        }
      }
      CHECK(relief > 0);
      std::vector<Footprint> expected, actual;
      for (const auto& i : swapped) expected.push_back(i.footprint);
      for (const auto& i : t) actual.push_back(i.footprint);
      std::sort(expected.begin(), expected.end());
      CHECK(actual == expected);
      for (const auto& i : t) {
        if (kind_of(i) == static_cast<int>(sim::FeatureKind::kRib)) CHECK(i.rise_mm >= sim::kTwinRibMinRiseMm);
      }
      break;
    }
    case sim::TwinRelation::kHeightPlus5mm:
      CHECK(twin.height_mm == base.height_mm + 5.0);
      CHECK(twin.outline_mm == base.outline_mm);
      CHECK(t == b);
      break;
  }
}

}  // namespace

TEST_CASE(
    "Given a seed, when the catalogue is generated twice, then the files are byte-identical, another seed "
    "gives another catalogue") {
  const std::string first = app::catalogue_yaml(sim::random_catalogue(12, 7), "");
  const std::string again = app::catalogue_yaml(sim::random_catalogue(12, 7), "");
  const std::string other = app::catalogue_yaml(sim::random_catalogue(12, 8), "");
  CHECK(first == again);
  CHECK(first != other);
  CHECK(first.size() > 2000);
}

TEST_CASE(
    "Given random catalogues, when every part is checked, then it is in the size range, buildable, laid out "
    "with margins, and inside the grid at the pose extremes") {
  const app::Config config = shipped_config();
  for (const auto& [count, seed] : {std::pair{12, 1ULL}, std::pair{12, 7ULL}, std::pair{40, 99ULL}}) {
    const auto parts = sim::random_catalogue(count, seed);
    REQUIRE(parts.size() == static_cast<std::size_t>(count));
    std::set<std::string> names, outlines_and_sizes;
    for (const auto& p : parts) {
      INFO("N " << count << " seed " << seed << " part " << p.name << ": " << p.description);
      CHECK(names.insert(p.name).second);
      CHECK(p.width_mm >= sim::kRandomWidthMinMm);
      CHECK(p.width_mm <= sim::kRandomWidthMaxMm);
      CHECK(p.height_mm >= sim::kRandomHeightMinMm);
      CHECK(p.height_mm <= sim::kRandomHeightMaxMm);
      CHECK(sim::validate_part(p) == "");
      CHECK(sim::check_layout(p, sim::kLayoutMarginMm) == "");
      CHECK(sim::build_part(p).size() >= 1);
      CHECK(!p.features.empty());
    }
    const auto fits = app::check_catalogue_fits_grid(config, parts);
    INFO((fits.ok() ? std::string() : fits.error().message));
    CHECK(fits.ok());
  }
  // Many more seeds for the rare combinations (flanges on the widest, tallest parts): the grid check alone.
  for (std::uint64_t seed = 100; seed < 300; ++seed) {
    const auto fits = app::check_catalogue_fits_grid(config, sim::random_catalogue(12, seed));
    INFO("seed " << seed << ": " << (fits.ok() ? std::string() : fits.error().message));
    CHECK(fits.ok());
  }
}

TEST_CASE(
    "Given a catalogue of 40 parts, when parts outside the twin pairs are compared, then no two share a shape, "
    "and every outline and feature kind occurs") {
  const auto cat = sim::generate_random_catalogue(40, 11);
  std::set<std::size_t> paired;
  for (const auto& t : cat.twins) paired.insert({t.base, t.twin});
  std::set<std::tuple<double, double, std::vector<std::pair<double, double>>, std::vector<Instance>>> shapes;
  std::set<int> kinds;
  std::set<std::size_t> outline_sizes;
  for (std::size_t i = 0; i < cat.parts.size(); ++i) {
    const auto& p = cat.parts[i];
    for (const auto& f : p.features) kinds.insert(static_cast<int>(f.kind));
    outline_sizes.insert(p.outline_mm.size());
    if (paired.count(i) != 0) continue;
    std::vector<std::pair<double, double>> outline;
    for (const auto& q : outline_set(p)) outline.emplace_back(q.x(), q.y());
    INFO(p.name);
    CHECK(shapes.insert({p.width_mm, p.height_mm, outline, instances(p)}).second);
  }
  CHECK(kinds.size() == 7);  // hole, slot, window, hole_array, rib, louvre, flange
  // Rectangle (none), trapezoid (4), notched (6 or 8), chamfered (5 to 8), round-topped (15).
  CHECK(outline_sizes.count(0) == 1);
  CHECK(outline_sizes.count(4) == 1);
  CHECK(outline_sizes.count(15) == 1);
  CHECK(outline_sizes.size() >= 4);
}

TEST_CASE("Given a hand-made layout with a clash, when it is checked, then the clash and the edge are named") {
  sim::PartSpec part;
  part.name = "clash";
  part.width_mm = 400;
  part.height_mm = 700;
  sim::FeatureSpec hole;
  hole.diameter_mm = 40;
  part.features = {hole, hole};
  part.features[1].x_mm = 50;  // 10 mm of sheet between the two holes
  CHECK(sim::check_layout(part, sim::kLayoutMarginMm).find("feature 0 (hole) comes within 20 mm of feature 1") == 0);
  part.features = {hole};
  part.features[0].x_mm = 170;  // 10 mm from the right edge
  CHECK(sim::check_layout(part, sim::kLayoutMarginMm).find("of the outline") != std::string::npos);
  part.outline_mm = {{-200, -350}, {200, -350}, {200, 250}, {100, 350}, {-200, 350}};  // a chamfer cuts the corner
  part.features[0].x_mm = 140;
  part.features[0].y_mm = 280;
  CHECK(sim::check_layout(part, sim::kLayoutMarginMm).find("of the outline") != std::string::npos);
  part.features[0].y_mm = 0;
  CHECK(sim::check_layout(part, sim::kLayoutMarginMm) == "");
}

TEST_CASE(
    "Given catalogues of several sizes, when twins and roles are counted, then the pairs and the untaught "
    "parts are as specified and each pair differs by exactly its relation") {
  for (int count : {2, 3, 4, 5, 8, 11, 12, 30}) {
    for (std::uint64_t seed : {1ULL, 2ULL, 3ULL}) {
      INFO("N " << count << " seed " << seed);
      const auto cat = sim::generate_random_catalogue(count, seed);
      REQUIRE(cat.parts.size() == static_cast<std::size_t>(count));
      if (count >= 12) CHECK(cat.twins.size() >= 3);
      if (count >= 8) CHECK(cat.twins.size() >= 2);
      CHECK(cat.twins.size() == static_cast<std::size_t>(sim::twin_pair_count(count)));
      const auto hard = std::count_if(cat.twins.begin(), cat.twins.end(),
                                      [](const auto& t) { return t.relation == sim::TwinRelation::kHeightPlus5mm; });
      CHECK(hard <= 1);
      std::set<std::size_t> paired;
      for (const auto& t : cat.twins) {
        REQUIRE(t.base < cat.parts.size());
        REQUIRE(t.twin < cat.parts.size());
        CHECK(paired.insert(t.base).second);
        CHECK(paired.insert(t.twin).second);
        const auto& base = cat.parts[t.base];
        const auto& twin = cat.parts[t.twin];
        CHECK(base.family == twin.family);
        CHECK(twin.description.find("twin of " + base.name + ": " + sim::twin_relation_text(t.relation)) == 0);
        if (t.relation == sim::TwinRelation::kHeightPlus5mm) CHECK(twin.description.find("hard") != std::string::npos);
        check_relation(base, twin, t.relation);
      }
      int untaught = 0, untaught_twins = 0;
      std::set<std::string> families;
      for (std::size_t i = 0; i < cat.parts.size(); ++i) {
        const auto& p = cat.parts[i];
        CHECK(p.role != sim::PartRole::kUnspecified);
        if (paired.count(i) == 0) CHECK(families.insert(p.family).second);  // unrelated parts: a family of one
        if (p.role != sim::PartRole::kUntaught) continue;
        ++untaught;
        const auto pair = std::find_if(cat.twins.begin(), cat.twins.end(), [&](const auto& t) { return t.twin == i; });
        if (pair != cat.twins.end()) {
          ++untaught_twins;
          CHECK(cat.parts[pair->base].role == sim::PartRole::kTaught);
        } else {
          CHECK(paired.count(i) == 0);  // not the base of a pair either: unrelated to every taught part
        }
      }
      CHECK(untaught == sim::untaught_count(count));
      if (count >= 5) CHECK(untaught == 3);
      CHECK(untaught_twins == (cat.twins.empty() || untaught == 0 ? 0 : 1));
    }
  }
}

TEST_CASE(
    "Given a generated catalogue, when it is written and loaded back, then the specs are exactly the same, "
    "the CLI path refuses to overwrite") {
  const app::Config config = shipped_config();
  const fs::path dir = fresh_dir();
  const std::string path = (dir / "random.yaml").string();
  REQUIRE(cli::write_random_catalogue(config, 30, 5, path).ok());
  const auto loaded = app::load_catalogue(path);
  INFO((loaded.ok() ? std::string() : loaded.error().message));
  REQUIRE(loaded.ok());
  const auto generated = sim::random_catalogue(30, 5);
  REQUIRE(loaded->size() == generated.size());
  for (std::size_t i = 0; i < generated.size(); ++i) {
    INFO(generated[i].name);
    CHECK((*loaded)[i] == generated[i]);
  }
  // Texts a person might type survive too: quotes, backslash, colon, hash, a line break, non-ASCII.
  auto odd = generated;
  odd.resize(2);
  odd[0].description = "say \"hi\": C:\\parts # not a comment\nsecond line, 45\u00b0";
  odd[1].family = "- [x]";
  const std::string odd_path = (dir / "odd.yaml").string();
  std::ofstream(odd_path) << app::catalogue_yaml(odd, "a header\n\nwith an empty line");
  const auto odd_loaded = app::load_catalogue(odd_path);
  INFO((odd_loaded.ok() ? std::string() : odd_loaded.error().message));
  REQUIRE(odd_loaded.ok());
  CHECK(*odd_loaded == odd);
  fs::remove(odd_path);

  const auto before = fs::last_write_time(path);
  const auto again = cli::write_random_catalogue(config, 12, 6, path);
  REQUIRE_FALSE(again.ok());
  CHECK(again.error().message.find("refusing to overwrite") != std::string::npos);
  CHECK(fs::last_write_time(path) == before);
  CHECK(std::distance(fs::directory_iterator(dir), fs::directory_iterator()) == 1);  // no temporary file left behind
  fs::remove_all(dir);
}

TEST_CASE("Given a generated part, when a simulated pass is rendered, then the stripe finds the part") {
  const app::Config config = shipped_config();
  const auto parts = sim::random_catalogue(8, 3);
  sim::SimCell cell(config.rig, parts, config.sim);
  auto pass = cell.random_pass(parts.front().name, 11);
  REQUIRE(pass.ok());
  pass->coating_a = pass->coating_b = sim::Coating{"primer", {0.55, 0.15, 20.0}, 1.0};  // not the dark coat's luck
  REQUIRE(cell.begin_pass(*pass).ok());
  cv::Mat image;
  std::size_t on_part = 0, bright = 0;
  for (int frame = 40; frame < cell.frame_count(); frame += 60) {  // a few frames across the part are enough
    std::vector<sim::TruthPoint> truth;
    cell.render_frame(frame, config.camera.exposure_us, image, &truth);
    for (const auto& t : truth) {
      if (!t.is_part) continue;
      ++on_part;
      bright += image.at<std::uint8_t>(static_cast<int>(std::lround(t.pixel.y())),
                                       static_cast<int>(std::lround(t.pixel.x()))) > 60;
    }
  }
  INFO(parts.front().name << ": " << on_part << " part points, " << bright << " bright");
  CHECK(on_part > 500);
  CHECK(bright > on_part * 3 / 4);
}

TEST_CASE(
    "Given the optional family and role keys, when a catalogue is loaded, then they are read, a bad role is "
    "named, and parts without them keep loading") {
  const fs::path dir = fresh_dir();
  auto load = [&](const std::string& yaml) {
    const std::string path = (dir / "parts.yaml").string();
    fs::remove(path);
    std::ofstream(path) << yaml;
    return app::load_catalogue(path);
  };
  auto parts = load(
      "parts:\n  - {name: a, width_mm: 400, height_mm: 700, family: f1, role: untaught}\n"
      "  - {name: b, width_mm: 400, height_mm: 700}\n");
  REQUIRE(parts.ok());
  CHECK((*parts)[0].family == "f1");
  CHECK((*parts)[0].role == sim::PartRole::kUntaught);
  CHECK((*parts)[1].family.empty());
  CHECK((*parts)[1].role == sim::PartRole::kUnspecified);
  auto bad = load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, role: guest}\n");
  REQUIRE_FALSE(bad.ok());
  CHECK(bad.error().message.find("parts[0].role: 'guest' is not valid, expected one of: taught | untaught") !=
        std::string::npos);
  auto typo = load("parts:\n  - {name: a, width_mm: 400, height_mm: 700, familly: f1}\n");
  REQUIRE_FALSE(typo.ok());
  CHECK(typo.error().message.find("parts[0].familly: unknown key") != std::string::npos);
  auto shipped = app::load_catalogue(CELLSIGHT_SOURCE_DIR "/config/parts.yaml");
  REQUIRE(shipped.ok());
  CHECK(std::all_of(shipped->begin(), shipped->end(),
                    [](const auto& p) { return p.role == sim::PartRole::kUnspecified; }));
  fs::remove_all(dir);
}
