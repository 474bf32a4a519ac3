// `motionctl fixture configs/data/<profile>.yaml [overrides] [--force]`.
#include <chrono>
#include <filesystem>
#include <iostream>

#include "cli/commands.h"
#include "cli/fixture_job.h"
#include "cli/jobs.h"
#include "core/error.h"
#include "data/fixture/fixture.h"
#include "data/motion_set.h"
#include "data/normalizer.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"

namespace mc {
namespace fs = std::filesystem;

FixtureBuildResult build_fixture(const std::string& config_file, const std::vector<std::string>& overrides,
                                 bool force) {
  auto t0 = std::chrono::steady_clock::now();
  auto job = load_job<FixtureJobConfig>(config_file, overrides);
  std::string resolved = dump_config(job);
  FixtureBuildResult r;
  r.output = job.output;
  if (!force && fs::exists(job.output)) {
    try {
      MotionSet old = read_motion_file(job.output);
      if (old.provenance.generator == "motionctl fixture" && old.provenance.config == resolved) {
        r.up_to_date = true;
        r.clips = old.size();
        return r;
      }
    } catch (const UserError&) {
      // unreadable or foreign file: rebuild it
    }
  }
  Skeleton skel = load_skeleton(job.skeleton);
  MotionSet m = generate_fixture(job.fixture, skel);
  // No timestamp: the same config and seed must give a byte-identical file.
  m.provenance = Provenance{"motionctl fixture", MOTIONCTL_VERSION, job.fixture.seed, resolved, "deterministic"};
  m.stats = compute_norm_stats(m);
  m.vocab = TextVocab::build(m).words();
  m.clear_padding();
  write_motion_file(job.output, m);
  r.clips = m.size();
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

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
