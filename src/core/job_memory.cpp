// The peak-memory lower bounds of core/job_memory.h.
#include "core/job_memory.h"

namespace mc {

long double generated_motions_bytes(long double samples, long double frames, long double joints) {
  return samples * frames * joints * 3 /*xyz*/ * 4 /*float32*/ * 4 /*copies*/;
}

long double replicated_values_bytes(long double repeats, long double values_per_repeat) {
  return repeats * values_per_repeat * 8 /*double*/;
}

}  // namespace mc
