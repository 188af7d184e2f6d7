// Logging: one line per event with level and CLOCK_MONOTONIC time; cheap enough for start-up and per-part events.
#pragma once

#include <cstdarg>

namespace cellsight::log {

enum class Level { kDebug = 0, kInfo = 1, kWarn = 2, kError = 3, kOff = 4 };

// Lines below this level are dropped before formatting.
void set_level(Level level);
[[nodiscard]] Level level();
// Parses "debug|info|warn|error|off"; returns false on anything else.
[[nodiscard]] bool parse_level(const char* text, Level& out);

// printf-style; writes "<monotonic s.ms> <LEVEL> <component>: <message>\n" to stderr in one write(2),
// so lines from several threads never interleave. Formats into a stack buffer: no allocation.
void write(Level level, const char* component, const char* format, ...) __attribute__((format(printf, 3, 4)));

}  // namespace cellsight::log

#define CS_LOG_DEBUG(component, ...) ::cellsight::log::write(::cellsight::log::Level::kDebug, component, __VA_ARGS__)
#define CS_LOG_INFO(component, ...) ::cellsight::log::write(::cellsight::log::Level::kInfo, component, __VA_ARGS__)
#define CS_LOG_WARN(component, ...) ::cellsight::log::write(::cellsight::log::Level::kWarn, component, __VA_ARGS__)
#define CS_LOG_ERROR(component, ...) ::cellsight::log::write(::cellsight::log::Level::kError, component, __VA_ARGS__)
