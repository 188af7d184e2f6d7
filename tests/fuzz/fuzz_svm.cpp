// libFuzzer target: the SVM model file (models/svm.bin, algo::SvmModel::deserialize, which load_svm calls on the
// file's bytes). Input: a mode byte, then the file (tests/fuzz/fuzz_util.hpp). Whatever is accepted must predict
// without fault and serialize back to the same bytes.
#include <cstddef>
#include <cstdint>
#include <string>

#include "algo/svm.hpp"
#include "base/crc32.hpp"
#include "tests/fuzz/fuzz_util.hpp"

namespace {

using namespace cellsight;

constexpr std::size_t kCrcBytes = 4;  // the blob's trailer: CRC-32 of everything before it

}  // namespace

// NOLINTNEXTLINE(readability-identifier-naming): the name is libFuzzer's entry point
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::ChecksummedInput in = fuzz::split_mode_byte(data, size);
  if (in.repair && in.file.size() >= kCrcBytes) {
    const std::size_t body = in.file.size() - kCrcBytes;
    fuzz::store_u32(in.file, body, base::crc32(std::string_view(in.file).substr(0, body)));
  }
  auto model = algo::SvmModel::deserialize(in.file);
  if (!model) return 0;
  CS_FUZZ_EXPECT(model->serialize() == in.file);
  algo::FeatureVector features{};
  for (const float value : {0.0F, 1.0F, -1e30F}) {
    features.fill(value);
    const auto probabilities = model->predict(features);
    CS_FUZZ_EXPECT(probabilities.size() == model->classes().size());
  }
  return 0;
}
