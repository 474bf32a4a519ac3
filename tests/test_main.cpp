// Catch2 entry point for the whole suite. Like motionctl, it first puts the
// runtime environment in place (core/process_env.h): on a CPU model Debian's
// OpenBLAS does not know, every torch matmul in the suite would otherwise run on
// SSE3 kernels.
#define CATCH_CONFIG_RUNNER
#include <catch2/catch.hpp>

#include "core/process_env.h"

int main(int argc, char** argv) {
  mc::reexec_with_runtime_environment(argv);
  return Catch::Session().run(argc, argv);
}
