// `motionctl train CONFIG [key=value ...]`, `motionctl sweep CONFIG key=a,b ...`
// and run_train (train/train_job.h), which other commands use to get trained parts.
#include <filesystem>
#include <iostream>

#include "cli/commands.h"
#include "data/fixture/fixture_build.h"
#include "cli/jobs.h"
#include "train/train_job.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "train/distributed.h"
#include "train/pretrained.h"
#include "train/trainer.h"

namespace mc {
namespace fs = std::filesystem;

static std::string stem_of(const std::string& file) { return fs::path(file).stem().string(); }

void add_train_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("train", "train a model from a YAML config (resumes; a finished run is a no-op)");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
    TrainLoopOptions loop;
    int nproc = 1;
    DistOptions dist;
    double bucket_mb = 25;
    std::string overlap = "on";
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "config file, e.g. configs/train/autoencoder_smoke.yaml")->required();
  cmd->add_option("overrides", a->overrides, "key.path=value overrides (run.force=true redoes a finished run)");
  cmd->add_option("--stop-after", a->loop.stop_after, "stop after N steps without finishing (resume later)");
  cmd->add_option("--snapshot-every", a->loop.snapshot_every,
                  "also save the final weights every N steps to checkpoints/snapshot_NNNNNN.pt (for "
                  "tools/health_curve.sh); does not change the run's name");
  cmd->add_option("--nproc", a->nproc,
                  "data-parallel training with N local processes (the global batch stays optim.batch_size; each "
                  "process computes batch_size / N clips with run.threads / N threads); under torchrun or a "
                  "scheduler, leave it out: RANK, WORLD_SIZE, MASTER_ADDR and MASTER_PORT say the job")
      ->check(CLI::Range(1, 1024));
  cmd->add_option("--dist-timeout", a->dist.timeout_seconds,
                  "data-parallel: seconds a process waits for the others (rendezvous, all-reduce) before it fails "
                  "naming the silent one")
      ->check(CLI::Range(1.0, 1e6));
  cmd->add_option("--bucket-mb", a->bucket_mb, "data-parallel: gradient all-reduce bucket size in MiB")
      ->check(CLI::Range(0.001, 1e5));
  cmd->add_option("--overlap", a->overlap,
                  "data-parallel: on = launch each bucket's all-reduce from the backward's gradient hooks, off = "
                  "after the backward")
      ->check(CLI::IsMember({"on", "off"}));
  cmd->callback([a] {
    const DistEnv env = dist_env_from_environment();
    if (a->nproc > 1) {
      if (env.distributed())
        fail("--nproc {} starts local processes itself, but this process is already rank {} of {} (RANK and "
             "WORLD_SIZE are set, e.g. by torchrun): leave --nproc out",
             a->nproc, env.rank, env.world);
      // The same command line for every rank, without --nproc.
      std::vector<std::string> args;
      const auto& argv = command_line();
      for (size_t i = 0; i < argv.size(); ++i) {
        if (argv[i] == "--nproc") {
          ++i;
          continue;
        }
        if (argv[i].rfind("--nproc=", 0) == 0) continue;
        args.push_back(argv[i]);
      }
      // A batch that does not divide is refused once, here, rather than by every rank.
      check_batch_divides(load_job<TrainJobConfig>(redirected_config(a->file), a->overrides), a->nproc);
      const int code = launch_local_ranks(a->nproc, args, a->dist.timeout_seconds + 10);
      if (code != 0) throw ExitStatus(code);
      return;
    }
    std::unique_ptr<DataParallel> dp;
    if (env.distributed()) {
      a->dist.bucket_bytes = static_cast<int64_t>(a->bucket_mb * (1 << 20));
      a->dist.overlap = a->overlap == "on";
      dp = DataParallel::join(env, a->dist);
      a->loop.data_parallel = dp.get();
    }
    TrainResult r = run_train(a->file, a->overrides, a->loop);
    if (dp && dp->rank() != 0) return;  // rank 0 reports the run
    std::cout << "run: " << r.run_dir.string() << (r.skipped ? " (already finished)" : "") << "\n";
    for (auto& [k, v] : r.summary) std::cout << fmt::format("  {} = {:.6g}\n", k, v);
  });
}

void add_ship_command(CLI::App& app) {
  auto* cmd = app.add_subcommand(
      "ship", "copy the finished run of a training config into pretrained/ and record it in its manifest");
  struct Args {
    std::string file;
    std::vector<std::string> overrides;
    std::string root;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "training config whose finished run to ship, e.g. configs/prior/flow_standard.yaml")
      ->required();
  cmd->add_option("overrides", a->overrides, "the key=value overrides it was trained with");
  cmd->add_option("--to", a->root, "shipped folder (default: pretrained/ in the source tree)");
  cmd->callback([a] {
    fs::path run = run_dir_of(a->file, a->overrides);
    // A named run (runs/evaluator/standard) may predate edits of its config file.
    if (fs::exists(run / "config.yaml") &&
        run_config_hash((run / "config.yaml").string(), {}) != run_config_hash(a->file, a->overrides))
      fail("ship {}: the run '{}' was trained from another version of this config; retrain it with `motionctl "
           "train {} run.force=true` first",
           a->file, run.string(), a->file);
    std::string retrain = "motionctl train " + a->file;
    for (auto& o : a->overrides) retrain += " " + o;
    retrain += " run.force=true";
    PretrainedEntry e = ship_run(run, a->root.empty() ? pretrained_root() : fs::path(a->root), a->file,
                                 a->overrides, run_config_hash(a->file, a->overrides), retrain);
    std::cout << fmt::format("shipped {} as {} (final.pt sha1 {})\n", run.string(), e.dir.string(), e.sha1);
  });
}

void add_sweep_command(CLI::App& app) {
  auto* cmd = app.add_subcommand("sweep", "train the grid of all value combinations, one run per combination");
  struct Args {
    std::string file;
    std::vector<std::string> grid;
    std::string summary;
  };
  auto a = std::make_shared<Args>();
  cmd->add_option("config", a->file, "training config file")->required();
  cmd->add_option("grid", a->grid, "key=v1,v2,... (a single value is a plain override)");
  cmd->add_option("--summary", a->summary, "summary CSV path (default runs/<experiment>/sweep-<config>.csv)");
  cmd->callback([a] {
    // Expand the grid: every key=v1,v2 becomes one axis.
    std::vector<std::pair<std::string, std::vector<std::string>>> axes;
    for (auto& g : a->grid) {
      auto eq = g.find('=');
      if (eq == std::string::npos || eq == 0) fail("sweep argument '{}' must look like key=v1,v2", g);
      std::string key = g.substr(0, eq), vals = g.substr(eq + 1);
      std::vector<std::string> values;
      if (!vals.empty() && vals[0] == '[') {
        values.push_back(vals);  // a list literal is one value
      } else {
        std::stringstream ss(vals);
        for (std::string v; std::getline(ss, v, ',');) values.push_back(v);
      }
      if (values.empty()) fail("sweep argument '{}' has no values", g);
      axes.emplace_back(key, values);
    }
    std::vector<std::vector<std::string>> combos{{}};
    for (auto& [key, values] : axes) {
      std::vector<std::vector<std::string>> next;
      for (auto& c : combos)
        for (auto& v : values) {
          auto n = c;
          n.push_back(key + "=" + v);
          next.push_back(n);
        }
      combos = next;
    }
    // The settings every run shares (single-valued arguments, run.root among
    // them) decide where the summary goes.
    std::vector<std::string> shared;
    for (size_t k = 0; k < axes.size(); ++k)
      if (axes[k].second.size() == 1) shared.push_back(axes[k].first + "=" + axes[k].second.front());
    auto base = load_job<TrainJobConfig>(a->file, shared);
    std::vector<std::map<std::string, double>> rows;
    std::set<std::string> metric_names;
    for (size_t i = 0; i < combos.size(); ++i) {
      auto overrides = combos[i];
      std::string tag;
      for (size_t k = 0; k < overrides.size(); ++k)
        if (axes[k].second.size() > 1) tag += (tag.empty() ? "" : ",") + overrides[k];
      std::string run_name = fmt::format("{}-{}", stem_of(a->file), tag.empty() ? "base" : tag);
      overrides.push_back("run.name=" + sanitize_name(run_name));
      std::cout << fmt::format("[{}/{}] {}\n", i + 1, combos.size(), fmt::join(combos[i], " ")) << std::flush;
      TrainResult r = run_train(a->file, overrides);
      std::cout << "  run: " << r.run_dir.string() << (r.skipped ? " (already finished)" : "") << "\n";
      rows.push_back(r.summary);
      for (auto& [k, _] : r.summary) metric_names.insert(k);
    }
    std::string csv = "run";
    for (auto& [key, _] : axes) csv += "," + key;
    for (auto& m : metric_names) csv += "," + m;
    csv += "\n";
    for (size_t i = 0; i < combos.size(); ++i) {
      std::string line = fmt::format("{}", i);
      for (auto& kv : combos[i]) line += "," + kv.substr(kv.find('=') + 1);
      for (auto& m : metric_names) {
        auto it = rows[i].find(m);
        line += it == rows[i].end() ? "," : fmt::format(",{:.8g}", it->second);
      }
      csv += line + "\n";
    }
    fs::path out = a->summary.empty()
                       ? fs::path(base.run.root) / sanitize_name(base.run.experiment) / ("sweep-" + stem_of(a->file) + ".csv")
                       : fs::path(a->summary);
    write_file_atomic(out, csv);
    std::cout << "summary: " << out.string() << "\n";
  });
}

}  // namespace mc
