// printf into a std::string of whatever length the text needs (report text, labels of plots, progress lines).
#pragma once

#include <string>

namespace cellsight::base {

[[nodiscard]] std::string string_printf(const char* format, ...) __attribute__((format(printf, 1, 2)));

}  // namespace cellsight::base
