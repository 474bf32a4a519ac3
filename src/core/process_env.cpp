// Runtime environment set before the libraries start, by one re-exec (see
// process_env.h for why a re-exec and not a setenv in main()).
#include "core/process_env.h"

#include <dlfcn.h>
#include <strings.h>
#include <unistd.h>

#include <cstdlib>

namespace mc {

std::string openblas_corename() {
  using CoreFn = char* (*)();
  // dlsym, not a link-time reference: where libblas.so.3 is another BLAS the
  // symbol is absent and there is nothing to tune.
  auto fn = reinterpret_cast<CoreFn>(::dlsym(RTLD_DEFAULT, "openblas_get_corename"));
  if (!fn) return "";
  const char* name = fn();
  return name ? name : "";
}

std::string openblas_better_coretype() {
  // Only the known fallback: a CPU OpenBLAS recognised keeps OpenBLAS's choice.
  if (::strcasecmp(openblas_corename().c_str(), "Prescott") != 0) return "";
  // __builtin_cpu_supports also checks that the OS saves the AVX / AVX-512 state
  // (XGETBV), so a hypervisor that hides it keeps the SSE3 kernels.
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512cd") && __builtin_cpu_supports("avx512bw") &&
      __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl"))
    return "SkylakeX";
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return "Haswell";
  if (__builtin_cpu_supports("avx")) return "Sandybridge";
  return "";
}

std::string openblas_coretype_override() {
  if (std::getenv("OPENBLAS_CORETYPE")) return "";  // the user's choice wins
  return openblas_better_coretype();
}

void reexec_with_runtime_environment(char** argv) {
  if (std::getenv("MOTIONCTL_NO_REEXEC")) return;
  bool changed = false;
  if (!std::getenv("OMP_WAIT_POLICY")) {
    const char* n = std::getenv("OMP_NUM_THREADS");
    if (!(n && std::string(n) == "1")) {
      ::setenv("OMP_WAIT_POLICY", "PASSIVE", 1);
      changed = true;
    }
  }
  if (const std::string core = openblas_coretype_override(); !core.empty()) {
    ::setenv("OPENBLAS_CORETYPE", core.c_str(), 1);
    changed = true;
  }
  if (!changed) return;  // the re-exec loads libtorch twice (~0.4 s of CPU): only when it buys something
  ::setenv("MOTIONCTL_NO_REEXEC", "1", 1);  // never loop, whatever the exec does
  ::execv("/proc/self/exe", argv);
  // exec failed (no /proc): carry on with the libraries' defaults.
}

}  // namespace mc
