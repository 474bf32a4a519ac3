// `motionctl sample CONFIG [overrides]`: text-to-motion samples from a flow prior
// (trained on demand from its config), written as a standard motion file.
#include <algorithm>
#include <chrono>
#include <iostream>

#include "cli/commands.h"
#include "cli/jobs.h"
#include "cli/sample_job.h"
#include "train/dependencies.h"
#include "train/train_job.h"
#include "core/error.h"
#include "core/job_memory.h"
#include "core/resources.h"
#include "core/run_dir.h"
#include "train/trainer.h"

namespace mc {

// Refuses, before the prior is trained or loaded, prompts whose samples cannot fit
// (core/job_memory.h). The prior's skeleton is not known yet, so one joint is
// counted (a lower bound); from_split takes clips of the data, whose lengths the
// prior's own limit bounds, and is checked against that limit after loading.
static void check_sample_memory(const SampleJobConfig& job, const std::string& file) {
  const auto& tx = job.texts;
  if (tx.prompts.empty()) return;
  int frames = tx.length;
  std::string key = fmt::format("texts.length={}", tx.length);
  if (!tx.lengths.empty()) {
    frames = *std::max_element(tx.lengths.begin(), tx.lengths.end());
    key = fmt::format("texts.lengths (longest {})", frames);
  }
  require_memory(generated_motions_bytes(tx.prompts.size(), frames, 1), fmt::format("{}: this sample job", file),
                 fmt::format("{} prompts x {} frames ({}) x at least 1 joint: float32 joints held 4 times while "
                             "sampling",
                             tx.prompts.size(), frames, key),
                 "lower texts.length / texts.lengths to at most the prior's frames (196 for HumanML3D)");
}

static void run_sample(const std::string& file, const std::vector<std::string>& overrides) {
  auto t0 = std::chrono::steady_clock::now();
  auto job = load_job<SampleJobConfig>(file, overrides);
  RunConfig rc;
  rc.seed = job.run.seed;
  rc.threads = job.run.threads;
  rc.device = job.run.device;
  if (std::string e = rc.validate(); !e.empty()) fail("{}: run.device: {}", file, e);

  check_sample_memory(job, file);
  resolve_dependencies(job.prior);  // a prior named by its training config is trained first
  const std::string prior_dir = job.prior.run();
  torch::Device device = setup_torch(rc);
  FlowPrior prior = FlowPrior::load(prior_dir, device);

  std::vector<std::string> captions, ids;
  std::vector<int> lengths;
  const auto& tx = job.texts;
  if (!tx.from_split.empty()) {
    std::string path = tx.data.empty() ? prior.data_path() : tx.data;
    if (path.empty()) fail("{}: texts.data is empty and the prior '{}' does not record its data", file, prior_dir);
    MotionSet set = read_motion_file(resolve_data_path(path));
    auto idx = set.indices_of_split(tx.from_split);
    if (idx.empty()) fail("{}: split '{}' of '{}' (texts.from_split) has no clips", file, tx.from_split, path);
    if (tx.num_samples > 0 && static_cast<size_t>(tx.num_samples) < idx.size()) idx.resize(tx.num_samples);
    for (size_t i : idx) {
      captions.push_back(set.captions[i][0]);
      lengths.push_back(std::min(set.lengths[i], prior.t_max()));
      ids.push_back(set.ids[i]);
    }
  } else {
    captions = tx.prompts;
    for (size_t i = 0; i < captions.size(); ++i) {
      lengths.push_back(tx.lengths.empty() ? tx.length : tx.lengths.size() == 1 ? tx.lengths[0] : tx.lengths[i]);
      ids.push_back(fmt::format("sample_{:04d}", i));
    }
  }
  for (size_t i = 0; i < lengths.size(); ++i)
    if (lengths[i] > prior.t_max())
      fail("{}: texts length {} of prompt {} exceeds the prior's {} frames", file, lengths[i], i, prior.t_max());

  auto ts = std::chrono::steady_clock::now();
  FlowSampleResult r = sample_flow(prior, captions, lengths, job.sampler, static_cast<uint64_t>(job.run.seed));
  double sample_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();

  MotionSet m = to_motion_set(prior, r, captions, ids);
  // The provenance holds a re-runnable config: the prior pinned to the run it used.
  SampleJobConfig resolved = job;
  resolved.prior.run_dir = prior_dir;
  resolved.prior.config.clear();
  resolved.prior.overrides.clear();
  m.provenance = Provenance{"motionctl sample", MOTIONCTL_VERSION, job.run.seed, dump_config(resolved),
                            utc_timestamp()};
  write_motion_file(job.output, m);
  double total = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::cout << fmt::format("wrote {} motions to {} (sampling {:.1f} s, {:.2f} s/motion, {} steps, cfg {}; total {:.1f} s)\n",
                           m.size(), job.output, sample_s, sample_s / std::max<size_t>(1, m.size()),
                           job.sampler.steps, job.sampler.cfg_scale, total);
}

void add_sample_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("sample", "sample motions from texts with a trained flow prior");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "sample config, e.g. configs/sample/t2m_smoke.yaml")->required();
  cmd->add_option("overrides", a->overrides, "key.path=value overrides, e.g. prior.run_dir=runs/prior/x output=y.h5");
  cmd->callback([a] { run_sample(a->file, a->overrides); });
}

}  // namespace mc
