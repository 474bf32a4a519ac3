// Tests for core/process_env.h: the re-exec that keeps Debian's OpenBLAS off its
// Prescott (SSE3) fallback on CPUs with AVX, and leaves a user's choice alone.
// Run through `motionctl bench blas`, which prints OpenBLAS's configuration (the
// kernel set is in it) and the verdict.
#include <catch2/catch.hpp>

#include <cstdlib>
#include <string>

#include "core/process_env.h"
#include "test_util.h"

namespace {

// `motionctl bench blas` at one thread under an environment prefix (`env ...`).
std::string bench_blas(const std::string& env) {
  auto r = mc::test::run_shell(
      fmt::format("cd '{}' && {} '{}' bench blas --threads 1 2>&1", MOTIONCTL_SOURCE_DIR, env, MOTIONCTL_BINARY));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  return r.output;
}

bool has_core(const std::string& out, const std::string& core) {
  // openblas_get_config(): "OpenBLAS 0.3.21 NO_LAPACKE DYNAMIC_ARCH ... <Core> MAX_THREADS=64"
  return out.find(" " + core + " MAX_THREADS") != std::string::npos;
}

bool cpu_has_avx() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx");
}

}  // namespace

TEST_CASE("process_env: without a user setting OpenBLAS never runs its SSE3 kernels on a CPU with AVX", "[core][blas]") {
  if (mc::openblas_corename().empty()) {
    WARN("OpenBLAS is not the loaded BLAS: nothing to check");
    return;
  }
  const std::string out = bench_blas("env -u OPENBLAS_CORETYPE -u MOTIONCTL_NO_REEXEC");
  INFO(out);
  if (cpu_has_avx()) CHECK_FALSE(has_core(out, "Prescott"));
  CHECK(out.find("SLOW KERNELS") == std::string::npos);
}

TEST_CASE("process_env: a user's OPENBLAS_CORETYPE wins and bench blas names the better set", "[core][blas]") {
  if (mc::openblas_corename().empty() || !cpu_has_avx()) {
    WARN("OpenBLAS is not the loaded BLAS or the CPU has no AVX: nothing to check");
    return;
  }
  // Forcing the SSE3 set by hand is kept, and the verdict says what it costs.
  const std::string slow = bench_blas("env -u MOTIONCTL_NO_REEXEC OPENBLAS_CORETYPE=Prescott");
  INFO(slow);
  CHECK(has_core(slow, "Prescott"));
  CHECK(slow.find("SLOW KERNELS") != std::string::npos);
  CHECK(slow.find("OPENBLAS_CORETYPE=") != std::string::npos);
  // The same with no re-exec at all: the kernels are whatever OpenBLAS picked.
  const std::string none = bench_blas("env -u OPENBLAS_CORETYPE MOTIONCTL_NO_REEXEC=1");
  INFO(none);
  CHECK(has_core(none, "Prescott") == (none.find("SLOW KERNELS") != std::string::npos));
}

TEST_CASE("process_env: the override is empty whenever the user set OPENBLAS_CORETYPE", "[core][blas]") {
  const char* old = std::getenv("OPENBLAS_CORETYPE");
  const std::string saved = old ? old : "";
  ::setenv("OPENBLAS_CORETYPE", "Haswell", 1);
  CHECK(mc::openblas_coretype_override().empty());
  if (old)
    ::setenv("OPENBLAS_CORETYPE", saved.c_str(), 1);
  else
    ::unsetenv("OPENBLAS_CORETYPE");
  // This test process started through reexec_with_runtime_environment: it runs on
  // the set the re-exec chose, or needed none (no re-exec was allowed: nothing to say).
  const bool chosen = saved == "SkylakeX" || saved == "Haswell" || saved == "Sandybridge";
  if (chosen || (!old && !std::getenv("MOTIONCTL_NO_REEXEC"))) CHECK(mc::openblas_better_coretype().empty());
}
