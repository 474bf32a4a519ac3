// Peak-memory lower bounds of the commands that generate and evaluate (issue 16):
// `generate`, `sample`, `eval` and `reproduce` check the sizes they are asked for
// with these before they train, load or allocate anything, and refuse what cannot
// fit through require_memory (core/resources.h), naming the key and its value.
// Each formula counts only buffers the command must hold at one time, so it is a
// lower bound: a job that fits is never refused. Formulas in docs/choices.md
// ("Runs that cannot be corrupted", memory estimates).
#pragma once

namespace mc {

// Generated motions, float32 [samples, frames, joints, 3], held four times at the
// peak of every generator: the sampler's state x_t and its velocity (or gradient),
// the output world joints, and the motion set copied out of it for writing.
long double generated_motions_bytes(long double samples, long double frames, long double joints);

// Replications: `repeats` x `values_per_repeat` doubles kept until the summary
// (eval's per-metric bootstrap values; a replay's per-row values and per-sample
// records, kept for the paired tests and results.h5).
long double replicated_values_bytes(long double repeats, long double values_per_repeat);

}  // namespace mc
