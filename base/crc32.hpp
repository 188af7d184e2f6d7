// CRC-32 (IEEE 802.3, reflected, zlib's crc32) of the files cellsight writes: model database, templates, SVM blobs.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string_view>

namespace cellsight::base {

// The CRC of no bytes; the start value of crc32_update.
inline constexpr std::uint32_t kCrc32Empty = 0;

// Continues `crc` over `bytes` bytes at `data`: crc32_update(crc32(a), b) == crc32(a + b). Any length (zlib's
// uInt limit is handled inside).
[[nodiscard]] std::uint32_t crc32_update(std::uint32_t crc, const void* data, std::size_t bytes);

// CRC-32 of `bytes`: bit-identical to zlib's crc32(), so every file written before this file existed verifies.
[[nodiscard]] std::uint32_t crc32(std::string_view bytes);

}  // namespace cellsight::base
