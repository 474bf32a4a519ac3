// What a trained run was built on. A run names the components its model is built on
// (a ControlNet's frozen base, a token prior's tokenizer, an adapter's TMD prior, a
// flow prior's text encoder) by their training config + overrides, and its own run
// directory is named by its own config only; so a dependency retrained with other
// weights (its config file changed, run.force=true, a newly shipped version) left the
// dependent's directory finished, and it was reused although built on the old
// weights. <run>/dependencies.yaml records, when a run starts training, every
// dependency as resolved then (what, run directory, SHA-1 of its checkpoints/final.pt);
// a finished (or resumed) run whose record no longer matches the dependencies its
// config resolves to now is stale and is trained again (train/trainer.cpp;
// docs/choices.md, "Stale dependents").
#pragma once
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace mc {
namespace fs = std::filesystem;

// One trained component a run is built on, as resolved for it.
struct ResolvedDependency {
  std::string what;                    // as the config section declares it, e.g. "model.tokenizer"
  std::string run;                     // its finished run directory
  std::string config;                  // its training config ("" when named by run directory)
  std::vector<std::string> overrides;  // overrides of `config`
  std::string sha1;                    // SHA-1 of its checkpoints/final.pt: the weights it was built on
};

// The record's file name in a run directory.
inline constexpr const char* kDependencyRecord = "dependencies.yaml";

// SHA-1 (hex) of <run_dir>/checkpoints/final.pt, "" when there is none: the same
// fingerprint pretrained/manifest.yaml records (file_sha1). Computed once per file
// version in a process (keyed by the file's device, inode, size and mtime), so
// checking a dependency again costs a stat.
std::string weights_sha1(const fs::path& run_dir);

// "<experiment>/<name>" of a run directory: a dependency's identity in a record,
// independent of the runs root (run.root is no part of a run's identity).
std::string run_key(const std::string& run_dir);

// Writes <run_dir>/dependencies.yaml atomically. `note` (may be empty) says how a
// record not written at training time came about (an adopted legacy run).
void write_dependency_record(const fs::path& run_dir, const std::vector<ResolvedDependency>& deps,
                             const std::string& note = "");

// The record of a run; nullopt when it has none (trained before records existed).
// UserError naming the file when it does not parse.
std::optional<std::vector<ResolvedDependency>> read_dependency_record(const fs::path& run_dir);

// One clause per dependency in `now` that differs from what `recorded` says the run
// was built on ("prior runs/prior/flow_tiny-x 1a2b3c4d5e6f, which is now
// 6f5e4d3c2b1a"); empty when none does. Dependencies are matched by run_key, then by
// `what`, so a dependency whose config changed (another run directory) is named too.
std::vector<std::string> changed_dependencies(const std::vector<ResolvedDependency>& recorded,
                                              const std::vector<ResolvedDependency>& now);

// Whether a run built on `now` may be reused.
struct DependencyCheck {
  enum class State {
    fresh,       // its record matches `now` (or it has no dependency)
    stale,       // built on other weights: train it again
    unrecorded,  // no record, nothing shows it stale (a run trained before records existed)
  };
  State state = State::fresh;
  std::vector<std::string> reasons;  // stale: what changed (changed_dependencies' clauses)
};

// The check of a run directory against the dependencies resolved now: its record
// when it has one. Without one (a run trained before records existed) it is stale
// when a dependency finished after it did (their DONE times), or when the runs its
// outputs/*.yaml name (`*_run` keys, pretrained.h run_dependencies) include another
// run of a dependency's experiment than the one resolved now (its config changed
// since); otherwise it is unrecorded.
DependencyCheck check_dependencies(const fs::path& run_dir, const std::vector<ResolvedDependency>& now);

// "what run (sha1 1a2b3c4d5e6f)" of each dependency, comma separated, for messages.
std::string describe_dependencies(const std::vector<ResolvedDependency>& deps);

}  // namespace mc
