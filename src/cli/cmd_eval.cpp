// `motionctl eval CONFIG [overrides]` (evaluator metrics with replications) and
// `motionctl score FILE.h5 [--constraints SPEC]` (evaluator-free metrics).
#include <filesystem>
#include <optional>
#include <iostream>

#include "cli/commands.h"
#include "cli/eval_job.h"
#include "cli/jobs.h"
#include "train/train_job.h"
#include "core/error.h"
#include "core/run_dir.h"
#include "data/skeleton.h"
#include "eval/evaluation.h"

namespace mc {
namespace fs = std::filesystem;

namespace {

MotionSet split_of(const MotionSet& m, const std::string& split, const std::string& source) {
  auto idx = m.indices_of_split(split);
  if (idx.empty()) fail("{}: split '{}' is empty", source, split);
  return m.subset(idx);
}

}  // namespace

EvalJobResult run_eval_job(EvalJobConfig& job, const std::vector<std::string>& overrides, const std::string& stem) {
  EvalJobResult res;
  RunDir run = RunDir::open(job.run, dump_config(job), overrides, fmt::format("{}-{}", stem, config_hash(job)));
  res.run_dir = run.path().string();
  if (run.finished()) {  // a finished evaluation is a no-op: report what it found
    for (auto& [k, v] : run.summary()) res.values[k] = {v};
    run.log().info(fmt::format("{} is finished; showing its means (run.force=true redoes it)", res.run_dir));
    return res;
  }
  TrainResult ev_run = run_train(resolve_data_path(job.eval.evaluator), {});
  T2MEvaluator ev = T2MEvaluator::load(ev_run.run_dir.string());
  std::string ref_path = resolve_data_path(job.eval.reference);
  MotionSet reference = split_of(read_motion_file(ref_path), job.eval.split, ref_path);
  std::string motions_path = job.eval.motions.empty() ? ref_path : resolve_data_path(job.eval.motions);
  MotionSet motions = job.eval.motions.empty() ? reference : read_motion_file(motions_path);
  if (!(motions.skeleton == reference.skeleton))
    fail("{}: skeleton '{}' differs from the reference's '{}'", motions_path, motions.skeleton.name,
         reference.skeleton.name);
  run.log().info(fmt::format("evaluating {} ({} motions) against {} split '{}' ({} clips) with evaluator {}",
                             motions_path, motions.size(), ref_path, job.eval.split, reference.size(),
                             ev_run.run_dir.string()));
  EvalEmbeddings emb = embed_for_eval(ev, reference, ref_path, motions, motions_path);
  std::string src_path = job.eval.source.empty() ? "" : resolve_data_path(job.eval.source);
  std::optional<MotionSet> source;
  if (!src_path.empty()) source = read_motion_file(src_path);
  auto free = evaluator_free_metrics(motions, motions_path, job.protocol, job.eval.constraints,
                                     source ? &*source : nullptr);
  for (int r = 0; r < job.protocol.repeats; ++r) {
    for (auto& [k, v] : t2m_metrics(emb, job.protocol, static_cast<uint64_t>(job.run.seed) + r)) res.values[k].push_back(v);
    for (auto& [k, v] : free) res.values[k].push_back(v);  // fixed motions: these do not vary
  }
  write_metric_results(run.path().string(), res.values);
  std::map<std::string, double> summary;
  for (auto& [k, v] : res.values) summary[k] = summarize(v).mean;
  run.mark_finished(summary);
  return res;
}

void add_eval_commands(CLI::App& app) {
  {
    auto* cmd = app.add_subcommand("eval", "evaluate a motion file against the test split (evaluator metrics with CIs)");
    struct Args {
      std::string file;
      std::vector<std::string> overrides;
    };
    auto a = std::make_shared<Args>();
    cmd->add_option("config", a->file, "eval config, e.g. configs/eval/t2m_smoke.yaml")->required();
    cmd->add_option("overrides", a->overrides, "key.path=value overrides, e.g. eval.motions=samples.h5");
    cmd->callback([a] {
      auto job = load_job<EvalJobConfig>(a->file, a->overrides);
      EvalJobResult r = run_eval_job(job, a->overrides, fs::path(a->file).stem().string());
      std::cout << format_metric_table(r.values) << "results: " << r.run_dir << "/metrics.csv, metrics.h5\n";
    });
  }
  {
    auto* cmd = app.add_subcommand("score", "evaluator-free metrics of any motion file (foot skating, control errors)");
    struct Args {
      std::string file, constraints, source;
      bool csv = false, padded = false;
    };
    auto a = std::make_shared<Args>();
    cmd->add_option("motions", a->file, "motion HDF5 file")->required();
    cmd->add_option("--constraints", a->constraints, "constraint spec (YAML or HDF5) the motions were generated under");
    cmd->add_option("--source", a->source, "motion file whose clip i gives sample i's from_source targets");
    cmd->add_flag("--csv", a->csv, "print metric,value CSV");
    cmd->add_flag("--padded-196", a->padded, "foot skating over the padded 196 frames");
    cmd->callback([a] {
      MotionSet m = read_motion_file(a->file);
      std::optional<MotionSet> src;
      if (!a->source.empty()) src = read_motion_file(a->source);
      EvalProtocol p;
      p.foot_skating_padded_196 = a->padded;
      auto metrics = evaluator_free_metrics(m, a->file, p, a->constraints, src ? &*src : nullptr);
      if (a->csv) std::cout << "metric,value\n";
      for (auto& [k, v] : metrics)
        std::cout << (a->csv ? fmt::format("{},{:.8g}\n", k, v) : fmt::format("{:<16} {:.6f}\n", k, v));
    });
  }
}

}  // namespace mc
