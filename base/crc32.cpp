// The one CRC-32 of the project: zlib's, which the existing files were written with.
#include "base/crc32.hpp"

#include <zlib.h>

namespace cellsight::base {

std::uint32_t crc32_update(std::uint32_t crc, const void* data, std::size_t bytes) {
  // zlib answers 0 for a null buffer whatever `crc` was: nothing to add must leave the CRC as it is.
  if (bytes == 0) return crc;
  // crc32_z takes a size_t length (zlib >= 1.2.9; Debian 12 ships 1.2.13), so no piecewise feeding is needed.
  return static_cast<std::uint32_t>(crc32_z(crc, static_cast<const Bytef*>(data), bytes));
}

std::uint32_t crc32(std::string_view bytes) {
  return crc32_update(kCrc32Empty, bytes.data(), bytes.size());
}

}  // namespace cellsight::base
