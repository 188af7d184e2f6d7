// cellsight executable entry point.
#include "cli/cli.hpp"

int main(int argc, char** argv) {
  return cellsight::cli::run_cli(argc, argv);
}
