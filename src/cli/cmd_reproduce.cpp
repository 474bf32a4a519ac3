// `motionctl reproduce --profile smoke|standard|paper [--tables IDS] [--set k=v]`.
#include <iostream>

#include "cli/commands.h"
#include "experiments/reproduce.h"

namespace mc {

void add_reproduce_command(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "reproduce", "replay the papers' tables on the fixture: train what is missing, run every row, render results/");
  auto opt = std::make_shared<ReproduceOptions>();
  cmd->add_option("--profile", opt->profile, "smoke | standard | paper, or a profile file")->capture_default_str();
  cmd->add_option("--tables", opt->tables, "table ids or prefixes (e.g. projflow anchorroute/table4); default: all")
      ->delimiter(',');
  cmd->add_option("--set", opt->profile_overrides, "profile overrides, e.g. profile.num_samples=8");
  cmd->add_option("--specs", opt->specs_root, "folder of the experiment specs")->capture_default_str();
  cmd->add_flag("!--no-figures", opt->figures, "skip the matplotlib figures");
  cmd->callback([opt] {
    if (const char* py = std::getenv("PYTHON")) opt->python = py;
    ReproduceResult r = reproduce(*opt);
    std::cout << fmt::format("\ntables ({}):\n", r.table_files.size());
    for (auto& f : r.table_files) std::cout << "  " << f << "\n";
    std::cout << fmt::format("summary: {}/summary.md  (claims: {} hold, {} contradicted, {} undecided, {} not run)\n",
                             r.results_dir, r.claims_hold, r.claims_contradicted, r.claims_undecided,
                             r.claims_not_run);
    std::cout << fmt::format("raw metrics: {}/results.h5\n", r.results_dir);
    if (r.priors_checked > 0)
      std::cout << fmt::format("prior health: {} ({} of {} healthy)\n", r.health_file, r.priors_healthy,
                               r.priors_checked);
    if (!r.failures.empty()) {
      std::cout << fmt::format("{} failures:\n", r.failures.size());
      for (auto& f : r.failures) std::cout << "  " << f << "\n";
      throw CLI::RuntimeError(1);
    }
  });
}

}  // namespace mc
