// `motionctl health RUN_DIR [--samples N] [--evaluator CFG] [--seed S] [--data FILE]
// [--split test|val] [--ground-truth] [key=value ...]`: is a trained prior fit to test claims on?
// Writes RUN_DIR/health.md and health.json (health_val.* with --split val); `--describe`
// lists every option and target.
#include <iostream>

#include "cli/commands.h"
#include "core/error.h"
#include "eval/health.h"

namespace mc {

void add_health_command(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "health", "prior health: samples of a trained prior (or tokenizer reconstructions) beside held-out ground truth, "
                "with pass/fail targets; writes RUN_DIR/health.md and health.json");
  struct Args {
    std::vector<std::string> positional;  // RUN_DIR, then key=value overrides
    std::string samples, evaluator, seed, data, split;
    bool ground_truth = false, describe = false;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("run_dir_and_overrides", a->positional,
                  "RUN_DIR (a flow_prior, tmd_prior, masked_prior or vq_tokenizer run), then key=value overrides "
                  "(e.g. targets.foot_skating_ratio=2 generator_overrides=[generator.sampler.steps=20])");
  cmd->add_option("--samples", a->samples, "N samples, reference test clips and floor clips (default 32)");
  cmd->add_option("--evaluator", a->evaluator,
                  "evaluator training config (default: configs/eval/evaluator_*.yaml trained on the run's data)");
  cmd->add_option("--seed", a->seed, "generation seed (default 0)");
  cmd->add_option("--data", a->data, "motion file whose --split is the reference (default: the run's data)");
  cmd->add_option("--split", a->split,
                  "reference split: test (default) or val, for choosing sampler settings off the test clips "
                  "(writes health_val.md / health_val.json)");
  cmd->add_flag("--ground-truth", a->ground_truth,
                "self-check: score the reference clips themselves through the same pipeline");
  cmd->add_flag("--describe", a->describe, "list every option and health target with its default");
  cmd->callback([a] {
    // Flags become overrides after the positional ones, so one parse validates all.
    std::vector<std::string> overrides;
    std::string run_dir;
    for (const auto& s : a->positional) {
      if (s.find('=') == std::string::npos) {
        if (!run_dir.empty()) fail("two run directories given ('{}' and '{}'); check one run at a time", run_dir, s);
        run_dir = s;
      } else {
        overrides.push_back(s);
      }
    }
    if (!run_dir.empty()) overrides.push_back("run_dir=" + run_dir);
    if (!a->samples.empty()) overrides.push_back("samples=" + a->samples);
    if (!a->evaluator.empty()) overrides.push_back("evaluator=" + a->evaluator);
    if (!a->seed.empty()) overrides.push_back("seed=" + a->seed);
    if (!a->data.empty()) overrides.push_back("data=" + a->data);
    if (!a->split.empty()) overrides.push_back("reference.split=" + a->split);
    if (a->ground_truth) overrides.push_back("ground_truth=true");
    HealthOptions opt;
    parse_config(config_from_string("{}", "motionctl health", overrides), opt);
    if (a->describe) {
      std::cout << describe_config(opt);
      return;
    }
    if (opt.run_dir.empty()) fail("motionctl health needs a run directory: motionctl health RUN_DIR [--samples N]");
    HealthReport r = check_health(opt);
    std::cout << health_markdown(r) << "\n"
              << fmt::format("wrote {0}/{1}.md and {0}/{1}.json: {2}\n", opt.run_dir, opt.reference.file_stem(),
                             r.healthy() ? "healthy" : "NOT healthy");
  });
}

}  // namespace mc
