// What a cached table row was computed with, and whether it may still be reused.
// A row's run directory is named by its config (generator, protocol, sizes, seed, the
// data's and evaluator's bytes), but a trained component it used can be retrained in
// place (run.force=true, or by the freshness check when its own dependencies changed:
// train/dependency_record.h), and the cached row would then report numbers from the
// old weights. So a row records, beside its results, every trained component it used
// with the SHA-1 of its final weights (<row>/dependencies.yaml, the record format of
// trained runs), and a replay compares that record with the components the row
// resolves to now before reusing it (docs/choices.md, "Table replay: rows keyed by
// their weights"; docs/formats.md).
#pragma once
#include <filesystem>
#include <string>
#include <vector>

#include "core/config.h"
#include "train/dependency_record.h"

namespace mc {
namespace fs = std::filesystem;

// The trained components a row's generator uses, as resolved now.
struct RowComponents {
  // Every one with its weights' SHA-1: the runs trained or found for the generator,
  // its components' own dependencies included (the freshness check resolves those
  // too), in the order they were resolved, then any the generator names by run
  // directory. `what` is the declaring section's name (e.g. "prior") for the
  // generator's own, the run's experiment folder (e.g. "tokenizer") for the rest.
  std::vector<ResolvedDependency> all;
  // The run directories trained or found for it (take_trained_runs order): what the
  // row lists in components.txt, and what reports and health checks read.
  std::vector<std::string> trained;
};

// Resolves `generator`'s trained components: trains what is missing or stale
// (resolve_dependencies, quietly: training logs itself), then fingerprints each.
RowComponents resolve_row_components(Component& generator);

// The evaluator a row is scored with, as a record entry (what "evaluator").
ResolvedDependency evaluator_component(const std::string& run_dir, const std::string& config);

// Whether a finished row may be reused.
struct RowReuse {
  enum class State {
    reuse,      // its record matches what it resolves to now
    adopt,      // no record (computed before rows kept one), nothing shows it stale
    recompute,  // computed on other weights or another component set
  };
  State state = State::reuse;
  std::vector<std::string> reasons;  // recompute: what changed, one clause each
};

// The check of the finished row in `row_dir` against its components now. With a
// record (dependencies.yaml): each component and the evaluator are matched by run
// (experiment/name), then by `what`; a changed SHA-1, another run, a component
// added or no longer used is a reason to recompute; an unreadable record is one too.
// Without one (a legacy row): every run its components.txt lists must still be among
// the components resolved now (they listed only the generator's own components, so
// the rest are not required to be listed), and no component may have finished after
// the row did (make's rule on the DONE times, check_dependencies); else adopt (no
// component at all: reuse). The evaluator is not checked by time: its bytes are part
// of the row's key, so another evaluator is another row directory.
RowReuse check_row(const fs::path& row_dir, const RowComponents& now, const ResolvedDependency& evaluator);

// Writes <row_dir>/dependencies.yaml (the components, then the evaluator), atomically.
// components.txt is the row's own (written when it is computed) and is left alone.
void write_row_record(const fs::path& row_dir, const RowComponents& now, const ResolvedDependency& evaluator,
                      const std::string& note = "");

// The run directories a row's components.txt lists (empty when it has none).
std::vector<std::string> read_row_components(const fs::path& row_dir);

}  // namespace mc
