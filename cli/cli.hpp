// Command-line front end (DESIGN.md "Command line"): parses arguments and runs one mode.
#pragma once

namespace cellsight::cli {

constexpr int kExitOk = 0;
constexpr int kExitFailure = 1;  // a run that started and failed
constexpr int kExitUsage = 2;    // bad input: arguments, config, data files

[[nodiscard]] int run_cli(int argc, char** argv);

}  // namespace cellsight::cli
