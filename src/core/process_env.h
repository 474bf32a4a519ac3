// The runtime environment a motionctl process needs before its libraries start.
// libgomp (OMP_WAIT_POLICY) and OpenBLAS (OPENBLAS_CORETYPE) read their settings in
// load-time constructors, before main() runs, so the only way to change them from
// inside the program is to set them and re-execute the binary once. Both entry
// points (motionctl and the test suite) call reexec_with_runtime_environment first.
#pragma once
#include <string>

namespace mc {

// The OpenBLAS kernel set to force, or "" when nothing needs forcing.
// Debian's OpenBLAS 0.3.21 (DYNAMIC_ARCH) falls back to its Prescott (SSE3)
// kernels on every Intel CPU model it does not know (OpenBLAS issue #4267, fixed
// in 0.3.25): on this 2-core Xeon (family 6, model 207, AVX-512) sgemm then runs at
// ~25 instead of ~85 GFLOP/s per thread, and a flow-prior training step takes
// 2.5x as long (`motionctl bench blas` / `bench train`, docs/choices.md,
// "OpenBLAS's Prescott fallback"). Returns a kernel set only when all of these hold:
// OpenBLAS is the loaded BLAS, it chose "Prescott", the user did not set
// OPENBLAS_CORETYPE, and the CPU (with OS support) has the instructions of a better
// set: AVX-512 F/CD/BW/DQ/VL -> "SkylakeX", AVX2 + FMA -> "Haswell",
// AVX -> "Sandybridge".
std::string openblas_coretype_override();

// The better kernel set as above whatever the environment says ("" when OpenBLAS
// is not on its Prescott fallback or the CPU has nothing better): `bench blas`
// warns with it when the fallback is still in force (a user's OPENBLAS_CORETYPE or
// MOTIONCTL_NO_REEXEC kept it).
std::string openblas_better_coretype();

// The core OpenBLAS runs on ("" when OpenBLAS is not the loaded BLAS).
std::string openblas_corename();

// Sets what this process still needs and re-executes /proc/self/exe with the same
// arguments, at most once (MOTIONCTL_NO_REEXEC=1 is set for the child, and a
// user's MOTIONCTL_NO_REEXEC=1 skips all of it, e.g. under a debugger):
// - OMP_WAIT_POLICY=PASSIVE when the variable is unset and
//   OMP_NUM_THREADS is not 1 (a lone thread cannot spin against a neighbour);
// - OPENBLAS_CORETYPE=openblas_coretype_override() when that is not "".
// Returns only when nothing needed changing or the exec failed (no /proc).
void reexec_with_runtime_environment(char** argv);

}  // namespace mc
