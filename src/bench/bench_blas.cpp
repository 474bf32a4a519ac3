// BLAS throughput check: Debian's reference BLAS is ~50x slower than OpenBLAS,
// and torch silently uses whichever libblas.so.3 the alternatives system picks.
#include "bench/bench.h"

#include <chrono>
#include <thread>

namespace mc {

BlasBenchResult bench_sgemm(int threads, int64_t m, int64_t n, int64_t k, double min_seconds) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  torch::set_num_threads(threads);
  torch::manual_seed(0);
  auto a = torch::randn({m, k}), b = torch::randn({k, n});
  auto c = torch::mm(a, b);  // warm-up
  int reps = 0;
  auto t0 = std::chrono::steady_clock::now();
  double elapsed = 0;
  while (elapsed < min_seconds || reps < 3) {
    c = torch::mm(a, b);
    ++reps;
    elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  BlasBenchResult r;
  r.threads = threads;
  r.seconds_per_call = elapsed / reps;
  r.gflops = 2.0 * m * n * k / r.seconds_per_call / 1e9;
  return r;
}

}  // namespace mc
