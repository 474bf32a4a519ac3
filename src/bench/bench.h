// Benchmarks behind `motionctl bench ...` (measure speed here, never in tests).
#pragma once
#include <cstdint>

namespace mc {

struct BlasBenchResult {
  int threads = 0;
  double gflops = 0;
  double seconds_per_call = 0;
};
// Single-precision GEMM throughput of torch::mm at `threads` (0 = all cores).
BlasBenchResult bench_sgemm(int threads, int64_t m = 12544, int64_t n = 256, int64_t k = 256, double min_seconds = 1.0);

inline constexpr double kMinHealthyGflops = 20.0;

}  // namespace mc
