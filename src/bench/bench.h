// Benchmarks behind `motionctl bench ...` (measure speed here, never in tests).
#pragma once
#include <cstdint>
#include <ostream>
#include <string>
#include <vector>

namespace mc {

struct BlasBenchResult {
  int threads = 0;
  double gflops = 0;
  double seconds_per_call = 0;
  double cpu_share = 1;  // CPU time this process got / (wall time x threads) while timing; < 1 = others took cores
};
// Single-precision GEMM throughput of torch::mm at `threads` (0 = all cores).
BlasBenchResult bench_sgemm(int threads, int64_t m = 12544, int64_t n = 256, int64_t k = 256, double min_seconds = 0.5);

// Which BLAS this process runs: the resolved path of every BLAS library mapped
// into it (/proc/self/maps) and OpenBLAS's own config string when it is loaded.
struct LinkedBlas {
  std::vector<std::string> libraries;  // e.g. /usr/lib/x86_64-linux-gnu/openblas-openmp/libblas.so.3
  std::string openblas_config;         // openblas_get_config(), "" when OpenBLAS is not loaded
  bool reference = false;              // Debian's reference BLAS (netlib) is among the libraries
  // Set when OpenBLAS is still on its Prescott fallback although the CPU has a
  // better kernel set (core/process_env.h): the set it should run, e.g. "SkylakeX".
  std::string better_coretype;
};
LinkedBlas linked_blas();

// The verdict `bench blas` prints: a wrong BLAS, a busy machine, or healthy.
std::string blas_verdict(const BlasBenchResult& r, const LinkedBlas& blas, double load_average, int cpus);

inline constexpr double kMinHealthyGflops = 20.0;

struct ProjflowBenchOptions {
  int depth = 8;              // ACMDM family rule: width 64 L, L heads (8 = the paper's S)
  int frames = 196;
  int samples = 2;
  int steps = 99;
  int keyframe_every = 5;     // hard keyframes on all joints every N frames
  std::vector<int> dense_frames = {12, 24, 49};
  int dno_steps = 5;          // DNO optimisation steps timed (0 = skip); reported per step and at 500
  bool inequalities = true;       // time the inequality QP (floor, speed limit) against equality-only
  bool inequalities_only = false;  // that section alone
};
// Unconstrained vs ProjFlow sampling time (with and without pseudo-observations),
// DNO time per sample, structured vs dense projection solves, and the projection's
// time with inequality rows (a floor under the toes; plus a pelvis speed limit)
// against the same equality-only projection, warm and cold; prints a report to `out`.
void bench_projflow(const ProjflowBenchOptions& o, std::ostream& out);

struct TrainBenchOptions {
  std::string config;                  // any training config
  std::vector<std::string> overrides;  // key=value overrides of it
  int steps = 5;                       // timed steps
  int warmup = 2;                      // untimed steps first (allocator, threads)
  int threads = 0;                     // run.threads override (0 = the config's)
  bool compare_padded = true;          // also time the step padded to t_max without buckets
};
// One training step's time, FLOPs and FLOP rate against sgemm; prints a table to `out`.
void bench_train(const TrainBenchOptions& o, std::ostream& out);

struct DdpBenchOptions {
  std::string config;                  // any training config
  std::vector<std::string> overrides;  // key=value overrides of it
  int nproc = 2;                       // data-parallel processes
  int threads = 0;                     // threads in all (run.threads; 0 = all cores); each process takes threads / nproc
  int steps = 3;                       // timed steps per setup
  int warmup = 1;                      // untimed steps first
  double bucket_mb = 25;               // gradient bucket size
  bool worker = false;                 // internal: run as one of the ranks
  std::string report;                  // internal: where rank 0 writes its timings
};
// One process x all threads against nproc processes x threads / nproc (all-reduce
// overlapped with backward and after it) on the same global batch, and the
// all-reduce of every gradient alone; prints a table to `out`.
void bench_ddp(const DdpBenchOptions& o, std::ostream& out);

struct AnchorrouteBenchOptions {
  std::string generator = "experiments/generators/anchorroute.yaml";  // an anchorroute generator file
  std::vector<std::string> overrides;                                 // generator.* overrides of it
  std::string protocol = "experiments/protocols/anchors_all.yaml";
  std::string data = "data/fixture_smoke.h5";
  std::string fixture = "configs/data/smoke.yaml";  // builds `data` when it is missing
  int samples = 8;                                   // first test clips
  std::vector<int> route_steps = {100, 200, 500};
  int repeats = 1;                                   // the fastest of N runs per row
};
// Table VII in one run: generator-only time per sample, RSk cost ratios, and the
// generator's split into network calls and decoding beside one RouteSolver step.
void bench_anchorroute(const AnchorrouteBenchOptions& o, std::ostream& out);

}  // namespace mc
