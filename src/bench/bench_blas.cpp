// BLAS throughput check: Debian's reference BLAS is ~50x slower than OpenBLAS,
// and torch silently uses whichever libblas.so.3 the alternatives system picks.
// A low number alone cannot tell a wrong BLAS from a busy machine (issue 16: it
// blamed the BLAS while OpenMP threads of other jobs held the cores), so the check
// also reads which BLAS is mapped into the process and how much CPU it got.
#include "bench/bench.h"
#include "core/process_env.h"

#include <dlfcn.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <set>
#include <thread>

namespace mc {

BlasBenchResult bench_sgemm(int threads, int64_t m, int64_t n, int64_t k, double min_seconds) {
  if (threads <= 0) threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  torch::set_num_threads(threads);
  torch::manual_seed(0);
  auto a = torch::randn({m, k}), b = torch::randn({k, n});
  auto c = torch::mm(a, b);  // warm-up
  int reps = 0;
  auto cpu_seconds = [] {
    rusage u{};
    ::getrusage(RUSAGE_SELF, &u);
    return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
  };
  const double cpu0 = cpu_seconds();
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
  r.cpu_share = (cpu_seconds() - cpu0) / (elapsed * threads);
  return r;
}

LinkedBlas linked_blas() {
  LinkedBlas out;
  std::ifstream maps("/proc/self/maps");
  std::set<std::string> seen;
  for (std::string line; std::getline(maps, line);) {
    auto slash = line.find('/');
    if (slash == std::string::npos) continue;
    std::string path = line.substr(slash);
    std::string name = std::filesystem::path(path).filename().string();
    if (name.find("blas") == std::string::npos) continue;
    std::error_code ec;
    auto real = std::filesystem::canonical(path, ec);
    if (!ec) path = real.string();
    if (!seen.insert(path).second) continue;
    out.libraries.push_back(path);
    // Debian's netlib reference BLAS lives in .../blas/libblas.so.3 (OpenBLAS in .../openblas-*/).
    if (path.find("/blas/libblas.so") != std::string::npos) out.reference = true;
  }
  using ConfigFn = char* (*)();
  if (auto fn = reinterpret_cast<ConfigFn>(::dlsym(RTLD_DEFAULT, "openblas_get_config")))
    if (const char* c = fn()) out.openblas_config = c;
  out.better_coretype = openblas_better_coretype();
  return out;
}

std::string blas_verdict(const BlasBenchResult& r, const LinkedBlas& blas, double load_average, int cpus) {
  const bool busy = r.cpu_share < 0.7 || load_average > cpus;
  if (blas.reference)
    return "WRONG BLAS: torch calls Debian's reference BLAS (~50x slower than OpenBLAS). Install libopenblas0-openmp "
           "(make deps does) and check `update-alternatives --display libblas.so.3-x86_64-linux-gnu`.";
  // Before the GFLOP/s floor: the SSE3 kernels still pass it (~25 GFLOP/s a thread
  // on a CPU that gives ~85 with its AVX-512 set).
  if (!blas.better_coretype.empty())
    return fmt::format("SLOW KERNELS: OpenBLAS runs its Prescott (SSE3) kernels on this CPU, which has the instructions "
                       "of its {0} set (OpenBLAS before 0.3.25 falls back to Prescott on CPU models it does not know). "
                       "motionctl forces {0} itself unless OPENBLAS_CORETYPE or MOTIONCTL_NO_REEXEC is set: unset them, "
                       "or set OPENBLAS_CORETYPE={0}",
                       blas.better_coretype);
  if (r.gflops >= kMinHealthyGflops) return "ok";
  if (busy)
    return fmt::format("the machine is busy, not the BLAS: this process got {:.0f}% of the CPU time its {} thread(s) "
                       "could use (load average {:.1f} on {} CPUs); measure again when it is idle",
                       100 * r.cpu_share, r.threads, load_average, cpus);
  return fmt::format("slow although the machine is idle and the BLAS is {}: below {:.0f} GFLOP/s; check the CPU "
                     "frequency governor and `update-alternatives --display libblas.so.3-x86_64-linux-gnu`",
                     blas.openblas_config.empty() ? "not OpenBLAS" : "OpenBLAS", kMinHealthyGflops);
}

}  // namespace mc
