// The page's files (hmi/web/), compiled into the executable by hmi/embed_assets.cmake: the HMI works on a plant
// network without internet and without files to install beside the binary.
#pragma once

#include <cstddef>
#include <string_view>

namespace cellsight::hmi {

struct Asset {
  std::string_view path;  // "/app.js"; "/" is index.html
  std::string_view type;  // Content-Type
  const unsigned char* data;
  std::size_t size;
};

// nullptr when there is no such file.
[[nodiscard]] const Asset* find_asset(std::string_view path);

}  // namespace cellsight::hmi
