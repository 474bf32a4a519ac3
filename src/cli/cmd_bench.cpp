// `motionctl bench blas [--threads N]`: speed checks (more benchmarks join as the systems land).
#include <iostream>

#include "bench/bench.h"
#include "cli/commands.h"

namespace mc {

void add_bench_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("bench", "benchmarks");
  cmd->require_subcommand(1);
  auto* blas = cmd->add_subcommand("blas", "sgemm GFLOP/s of torch::mm (12544x256x256) at the configured threads");
  auto threads = std::make_shared<int>(0);
  blas->add_option("--threads", *threads, "torch threads (0 = all cores)")->check(CLI::NonNegativeNumber);
  blas->callback([threads] {
    BlasBenchResult r = bench_sgemm(*threads);
    std::cout << fmt::format("sgemm 12544x256x256: {:.1f} GFLOP/s at {} thread(s) ({:.2f} ms per call)\n", r.gflops,
                             r.threads, r.seconds_per_call * 1e3);
    if (r.gflops < kMinHealthyGflops)
      std::cout << fmt::format(
          "WARNING: below {:.0f} GFLOP/s: torch is probably using Debian's reference BLAS. Install "
          "libopenblas0-openmp (make deps does) and check `update-alternatives --display libblas.so.3-x86_64-linux-gnu`.\n",
          kMinHealthyGflops);
  });
}

}  // namespace mc
