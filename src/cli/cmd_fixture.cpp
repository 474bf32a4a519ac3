// `motionctl fixture configs/data/<profile>.yaml [overrides] [--force]`.
#include <chrono>
#include <filesystem>
#include <iostream>

#include "cli/commands.h"
#include "data/fixture/fixture_build.h"
#include "cli/jobs.h"
#include "core/error.h"
#include "data/fixture/fixture.h"
#include "data/motion_set.h"
#include "data/normalizer.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"

namespace mc {
namespace fs = std::filesystem;

void add_fixture_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("fixture", "build the synthetic motion dataset (deterministic in config and seed)");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
    bool force = false;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "fixture config, e.g. configs/data/smoke.yaml")->required();
  cmd->add_option("overrides", a->overrides, "key.path=value overrides, e.g. fixture.num_clips=100 output=x.h5");
  cmd->add_flag("--force", a->force, "rebuild even when the file already holds this config");
  cmd->callback([a] {
    FixtureBuildResult r = build_fixture(a->file, a->overrides, a->force);
    if (r.up_to_date)
      std::cout << fmt::format("{}: up to date ({} clips)\n", r.output, r.clips);
    else
      std::cout << fmt::format("{}: {} clips in {:.2f} s\n", r.output, r.clips, r.seconds);
  });
}

}  // namespace mc
