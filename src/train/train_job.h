// Running a training config the way `motionctl train` does: build missing data,
// name the run <config stem>-<hash>, train or resume or skip. Other commands use
// it to get a trained component (evaluator, prior, tokenizer) on demand.
#pragma once
#include <filesystem>
#include <string>
#include <vector>

#include "train/trainer.h"

namespace mc {

TrainResult run_train(const std::string& config_file, const std::vector<std::string>& overrides,
                      const TrainLoopOptions& loop = {});

// The hash that identifies the run of (config, overrides): its resolved config
// without run.threads and run.force (the suffix of its default run name).
std::string run_config_hash(const std::string& config_file, const std::vector<std::string>& overrides);

// The run directory run_train(config, overrides) trains or reuses (no training).
std::filesystem::path run_dir_of(const std::string& config_file, const std::vector<std::string>& overrides);

// The runs root of every component a command trains: while a scope is alive,
// run_train puts each run it trains (and the runs those need, trained inside it)
// under `root` unless its overrides set run.root themselves. run.root is no part
// of a run's identity, so names and hashes stay the same. An inner scope does not
// replace an outer one: `eval` with run.root=X trains its evaluator under X,
// `reproduce` every component under profile.runs_root, and run_train itself
// opens one with the job's run.root for the components its model needs.
class RunsRootScope {
 public:
  explicit RunsRootScope(const std::string& root);
  ~RunsRootScope();
  RunsRootScope(const RunsRootScope&) = delete;
  RunsRootScope& operator=(const RunsRootScope&) = delete;
  static const std::string& current();  // "" outside every scope

 private:
  bool owner_ = false;
};

// Builds the job's training data from data.fixture when data.path is missing.
void ensure_training_data(const TrainJobConfig& job);

// Run directories run_train has returned since the last call (distinct, in
// first-use order), and forgets them: lets the table replay record which trained
// components each row used.
std::vector<std::string> take_trained_runs();

// Training configs replaced process-wide, each "from=to" (paths as in configs):
// run_train(from) trains `to` instead, also where `from` is named inside another
// training config. The table replay's profiles use it to swap every tiny
// component for its standard-size counterpart. UserError naming `what` when an
// entry is malformed or a file is missing. An empty list clears the redirects.
void set_config_redirects(const std::vector<std::string>& from_to, const std::string& what);

// Whether run_train may train a component longer than its training config says
// (process-wide; default true). When false, overrides that raise optim.steps above the
// config's own (after the redirects) are capped there, with the cap as an override
// (and a warm-up of steps / 10 when its own is not shorter). Smoke and CI profiles
// turn it off so that rows asking for longer training (Table IV's 4,500-step adapter)
// stay at their scale.
void set_lengthened_training(bool allowed);

// The training config run_train(file) trains under the current redirects: `file`
// itself, or the resolved path of its redirect target.
std::string redirected_config(const std::string& file);

}  // namespace mc
