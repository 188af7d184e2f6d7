// libFuzzer target: the configuration (app/config, formats/yaml_reader): YAML text parsed and validated as
// `cellsight --config` does, in memory. Whatever is accepted must satisfy the cross-field rules the reader states.
#include <cstddef>
#include <cstdint>
#include <string>

#include "app/config.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight;

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  auto config = app::parse_config(text, "fuzz.yaml");
  if (!config) return 0;
  CS_FUZZ_EXPECT(config->camera.exposure_min_us <= config->camera.exposure_max_us);
  CS_FUZZ_EXPECT(config->exposure.width_min_px < config->exposure.width_max_px);
  CS_FUZZ_EXPECT(config->grid.nx >= 8 && config->grid.ny >= 8 && config->grid.nz >= 8);
  return 0;
}
