// motionctl: the command-line entry point; subcommands are thin wrappers.
#include <CLI/CLI.hpp>
#include <iostream>

#include "core/error.h"

int main(int argc, char** argv) {
  CLI::App app{"motionctl: spatially controlled human motion generation"};
  app.require_subcommand(1);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : mc::kExitUserError;
  }
  return 0;
}
