// `motionctl config [FILE] [overrides] [--describe [SECTION]] [--job KIND]`:
// prints the resolved config, or the reference of every field.
#include <iostream>

#include "cli/commands.h"
#include "cli/jobs.h"
#include "core/error.h"

namespace mc {

void add_config_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("config", "print the fully resolved config, or describe the fields of a section");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
    bool describe = false;
    std::string section;
    std::string job;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "config file (optional with --describe)");
  cmd->add_option("overrides", a->overrides, "key.path=value overrides");
  cmd->add_flag("--describe", a->describe, "print the field reference instead of the resolved config");
  cmd->add_option("--section", a->section, "with --describe: only this top-level section (e.g. model, optim)");
  cmd->add_option("--job", a->job, "job kind when no file is given: train, fixture");
  cmd->callback([a] {
    std::unique_ptr<Config> cfg;
    if (!a->file.empty()) {
      ConfigSource src = compose_config(a->file, a->overrides);
      const JobKind& kind = a->job.empty() ? detect_job_kind(src) : job_kind(a->job);
      cfg = kind.make();
      parse_config(src, *cfg);
    } else {
      if (!a->describe) fail("give a config file, or --describe [--job KIND] [--section NAME] for the reference");
      cfg = job_kind(a->job.empty() ? "train" : a->job).make();
    }
    std::cout << (a->describe ? describe_config(*cfg, a->section) : dump_config(*cfg));
  });
}

}  // namespace mc
