// Trained components committed with the repository (pretrained/): a manifest of
// finished run directories, each named as run_train names it (<config stem>-<config
// hash>). run_train installs a shipped run into runs/ instead of training it when
// the run it is about to train has the same experiment and name, so `reproduce`
// and `make demo` train only what is missing or changed.
#pragma once
#include <filesystem>
#include <optional>
#include <ostream>
#include <string>
#include <utility>
#include <vector>

namespace mc {
namespace fs = std::filesystem;

struct PretrainedEntry {
  std::string experiment;  // runs/<experiment>/...
  std::string name;        // <config stem>-<config hash>
  std::string config;      // training config it was trained from (repo-relative)
  std::vector<std::string> overrides;  // key=value overrides it was trained with (a table's ablation variant)
  std::string config_hash; // hash of its resolved config (without run.threads/force): installs only on a match
  std::string sha1;        // of checkpoints/final.pt
  std::string retrain;     // the command that retrains it from scratch
  fs::path dir;            // pretrained/<experiment>/<name>
};

// The shipped folder: $MOTIONCTL_PRETRAINED when set ("" or "none" disables it),
// else <source dir>/pretrained.
fs::path pretrained_root();
// Entries of <root>/manifest.yaml (none when the file is absent). UserError naming
// the file and entry when it is malformed.
std::vector<PretrainedEntry> read_pretrained_manifest(const fs::path& root);
std::optional<PretrainedEntry> find_pretrained(const fs::path& root, const std::string& experiment,
                                               const std::string& name);

// SHA-1 of a file's bytes (hex); UserError when unreadable.
std::string file_sha1(const fs::path& file);

// When `experiment/name` is shipped with the same config hash and `run_dir` does
// not exist, copies the shipped run there (through a temporary sibling renamed
// into place, after checking the checkpoint's SHA-1) and returns true, with the
// shipped runs it was trained on beside it (same runs root). A shipped run of
// another config (a named run whose config changed) is not installed. One shipped
// before runs recorded their dependencies (train/dependency_record.h) gets a record
// naming the shipped runs its outputs name, when all of them are shipped.
// `log` (may be null) gets one line per installed run.
bool install_pretrained(const std::string& experiment, const std::string& name, const std::string& config_hash,
                        const fs::path& run_dir, std::ostream* log);

// Run directories a finished run was trained on, as its outputs/*.yaml record them
// (every top-level key ending in `_run`: base_run, tokenizer_run, tmd_run), sorted.
std::vector<std::string> run_dependencies(const fs::path& run_dir);
// The same with each one's key (("base_run", "runs/prior/flow_tiny-...")).
std::vector<std::pair<std::string, std::string>> run_dependency_fields(const fs::path& run_dir);

// Copies the files a user of a finished run needs (config.yaml, overrides.txt,
// seed.txt, summary.csv, metrics.csv, DONE, dependencies.yaml, checkpoints/final.pt,
// outputs/, health.*) into <root>/<experiment>/<name> and adds or replaces its
// manifest entry. UserError when the run is not finished, or when its dependency
// record names a shipped component with other weights (ship that one first). `log`
// (may be null) gets a warning for each shipped run built on the version of this
// component it replaces.
PretrainedEntry ship_run(const fs::path& run_dir, const fs::path& root, const std::string& config,
                         const std::vector<std::string>& overrides, const std::string& config_hash,
                         const std::string& retrain, std::ostream* log = nullptr);

}  // namespace mc
