// run_train: a training config run the way `motionctl train` runs it, for every
// command, generator and experiment that needs a trained component on demand.
#include "train/train_job.h"

#include <algorithm>
#include <filesystem>
#include <map>

#include "core/error.h"
#include "data/fixture/fixture_build.h"
#include "train/distributed.h"
#include "train/pretrained.h"
#include "train/train_resources.h"

#include <iostream>

namespace mc {
namespace fs = std::filesystem;

static std::vector<std::string>& trained_runs_registry() {
  static std::vector<std::string> runs;
  return runs;
}

static std::map<std::string, std::string>& config_redirects() {
  static std::map<std::string, std::string> redirects;  // canonical from -> to
  return redirects;
}

static std::string canonical_config(const std::string& file) {
  return fs::weakly_canonical(fs::path(resolve_data_path(file))).string();
}

void set_config_redirects(const std::vector<std::string>& from_to, const std::string& what) {
  std::map<std::string, std::string> out;
  for (const auto& e : from_to) {
    const auto eq = e.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == e.size())
      fail("{}: entry '{}' is not from=to (e.g. configs/prior/flow_tiny.yaml=configs/prior/flow_standard.yaml)",
           what, e);
    const std::string from = e.substr(0, eq), to = e.substr(eq + 1);
    for (const auto& f : {from, to})
      if (!fs::exists(resolve_data_path(f))) fail("{}: entry '{}': the config '{}' does not exist", what, e, f);
    out[canonical_config(from)] = to;
  }
  config_redirects() = std::move(out);
}

static bool& lengthening_allowed() {
  static bool allowed = true;
  return allowed;
}

void set_lengthened_training(bool allowed) { lengthening_allowed() = allowed; }

// `overrides` plus optim.steps=<the config's own> (and a warm-up shorter than it) when
// lengthening is off and they ask for more steps than the config itself trains, so
// the run's overrides.txt, its name and its hash say what it trained.
static std::vector<std::string> with_steps_cap(const std::string& file, std::vector<std::string> overrides) {
  if (lengthening_allowed()) return overrides;
  const int own = load_job<TrainJobConfig>(file, {}).optim.steps;
  const auto job = load_job<TrainJobConfig>(file, overrides);
  if (job.optim.steps <= own) return overrides;
  overrides.push_back(fmt::format("optim.steps={}", own));
  if (job.optim.warmup >= own) overrides.push_back(fmt::format("optim.warmup={}", own / 10));
  return overrides;
}

static std::string& runs_root_slot() {
  static std::string root;
  return root;
}

RunsRootScope::RunsRootScope(const std::string& root) {
  if (!runs_root_slot().empty() || root.empty()) return;
  runs_root_slot() = root;
  owner_ = true;
}
RunsRootScope::~RunsRootScope() {
  if (owner_) runs_root_slot().clear();
}
const std::string& RunsRootScope::current() { return runs_root_slot(); }

// `overrides` plus run.root=<the scope's root>, unless they set run.root already.
static std::vector<std::string> with_runs_root(std::vector<std::string> overrides) {
  if (RunsRootScope::current().empty()) return overrides;
  for (const auto& o : overrides)
    if (o.rfind("run.root=", 0) == 0) return overrides;
  overrides.push_back("run.root=" + RunsRootScope::current());
  return overrides;
}

static std::string stem_of(const std::string& file) { return fs::path(file).stem().string(); }

// <config stem>-<hash>: the hash of the run's identity (RunConfig::non_identity_fields
// left out: a run trained on one thread is the run a two-thread job asks for).
static std::string default_run_name(const std::string& file, const TrainJobConfig& job) {
  return fmt::format("{}-{}", stem_of(file), identity_hash(job));
}

std::string run_config_hash(const std::string& requested, const std::vector<std::string>& overrides) {
  const std::string file = redirected_config(requested);
  return identity_hash(load_job<TrainJobConfig>(file, with_steps_cap(file, overrides)));
}

// Builds the training data from its fixture config when the file is missing.
void ensure_training_data(const TrainJobConfig& job) {
  if (fs::exists(resolve_data_path(job.data.path))) return;
  if (job.data.fixture.empty())
    fail("data.path '{}' does not exist and data.fixture is empty; build it with `motionctl fixture` or point "
         "data.path at a motion file",
         job.data.path);
  build_fixture(resolve_data_path(job.data.fixture), {fmt::format("output={}", job.data.path)}, false);
}

std::string redirected_config(const std::string& file) {
  if (config_redirects().empty()) return file;
  auto it = config_redirects().find(canonical_config(file));
  return it == config_redirects().end() ? file : resolve_data_path(it->second);
}

TrainResult run_train(const std::string& requested, const std::vector<std::string>& given,
                      const TrainLoopOptions& loop) {
  const std::string file = redirected_config(requested);
  const std::vector<std::string> overrides = with_steps_cap(file, with_runs_root(given));
  auto job = load_job<TrainJobConfig>(file, overrides);
  RunsRootScope components_root(job.run.root);  // the runs its model trains go beside it
  if (DataParallel* dp = loop.data_parallel) {
    // Every rank must train the same run the same way: refused at the rendezvous
    // otherwise (exit 2 on every rank). run.threads and run.root may differ per
    // machine; they are no part of the identity.
    dp->check_same_job({{"motionctl version", MOTIONCTL_VERSION},
                        {"config hash", identity_hash(job)},
                        {"processes", std::to_string(dp->world())},
                        {"--stop-after", std::to_string(loop.stop_after)},
                        {"--snapshot-every", std::to_string(loop.snapshot_every)},
                        {"overlap", dp->options().overlap ? "on" : "off"},
                        {"bucket bytes", std::to_string(dp->options().bucket_bytes)}});
  }
  const bool writer = !loop.data_parallel || loop.data_parallel->rank() == 0;
  check_train_resources(job);  // sizes and threads this machine cannot give: exit 2 before any work
  if (writer) ensure_training_data(job);  // ranks > 0 read it once rank 0 has started
  std::string name = default_run_name(file, job);
  // A component shipped in pretrained/ under this run's name and with this config
  // hash is installed, not retrained (named runs too: the hash guards them).
  const std::string dir_name = job.run.name.empty() ? name : job.run.name;
  if (!job.run.force && writer)
    install_pretrained(job.run.experiment, dir_name, identity_hash(job),
                       fs::path(job.run.root) / job.run.experiment / dir_name, &std::cerr);
  TrainLoopOptions with_file = loop;
  with_file.config_file = file;  // in messages: "retrain it with `motionctl train <file> ...`"
  TrainResult r = train(job, overrides, name, with_file);
  auto& used = trained_runs_registry();
  const std::string dir = r.run_dir.string();
  if (std::find(used.begin(), used.end(), dir) == used.end()) used.push_back(dir);
  return r;
}

fs::path run_dir_of(const std::string& requested, const std::vector<std::string>& overrides) {
  const std::string file = redirected_config(requested);
  auto job = load_job<TrainJobConfig>(file, with_steps_cap(file, with_runs_root(overrides)));
  std::string name = job.run.name.empty() ? default_run_name(file, job) : job.run.name;
  return fs::path(job.run.root) / job.run.experiment / name;
}

std::vector<std::string> take_trained_runs() {
  std::vector<std::string> out;
  out.swap(trained_runs_registry());
  return out;
}

}  // namespace mc
