// `motionctl eval CONFIG [overrides]` (evaluator metrics with replications; run
// directories keyed by the SHA-1 of every input's bytes, embeddings and per-sample
// metrics in metrics.h5) and `motionctl score FILE.h5 [--constraints SPEC]`
// (evaluator-free metrics; without --constraints, the specs the file carries).
#include <c10/util/hash.h>

#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <random>
#include <cmath>
#include <iostream>

#include "cli/commands.h"
#include "cli/eval_job.h"
#include "cli/jobs.h"
#include "control/sample_constraints.h"
#include "train/train_job.h"
#include "core/error.h"
#include "core/job_memory.h"
#include "core/resources.h"
#include "core/run_dir.h"
#include "data/skeleton.h"
#include "eval/eval_outputs.h"
#include "eval/evaluation.h"
#include "train/pretrained.h"

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
  // protocol.repeats is the one size of an evaluation not bounded by its files: each
  // bootstrap resample keeps at least matching, diversity and foot_skating until the
  // summary (core/job_memory.h). Checked before the evaluator is trained or loaded.
  require_memory(replicated_values_bytes(job.protocol.repeats, 3), fmt::format("{}: this evaluation", stem),
                 fmt::format("protocol.repeats={} resamples x at least 3 metrics kept as doubles",
                             job.protocol.repeats),
                 "lower protocol.repeats (the papers use 20)");
  // Everything the result depends on, by content: the run is keyed by the SHA-1 of the
  // inputs' bytes, so a file regenerated at the same path is a new evaluation, never a
  // stale cached one. The evaluator is trained (or found) first for its checkpoint.
  RunsRootScope components_root(job.run.root);  // the evaluator it trains lives under run.root too
  TrainResult ev_run = run_train(resolve_data_path(job.eval.evaluator), job.eval.evaluator_overrides);
  std::string ref_path = resolve_data_path(job.eval.reference);
  std::string motions_path = job.eval.motions.empty() ? ref_path : resolve_data_path(job.eval.motions);
  std::string src_path = job.eval.source.empty() ? "" : resolve_data_path(job.eval.source);
  std::string constraints_path = job.eval.constraints.empty() ? "" : resolve_data_path(job.eval.constraints);
  std::vector<std::pair<std::string, std::string>> inputs = {
      {"evaluator_checkpoint", (ev_run.run_dir / "checkpoints" / "final.pt").string()},
      {"reference", ref_path},
      {"motions", motions_path}};
  if (!constraints_path.empty()) inputs.emplace_back("constraints", constraints_path);
  if (!src_path.empty()) inputs.emplace_back("source", src_path);
  std::map<std::string, std::string> attrs = {{"split", job.eval.split}, {"evaluator_run", ev_run.run_dir.string()}};
  std::string identity = identity_yaml(job) + "# inputs by content (SHA-1 of the bytes), part of this run's identity:\n";
  for (auto& [role, path] : inputs) {
    if (!fs::exists(path))
      fail("{}: eval.{} '{}' does not exist", stem, role == "evaluator_checkpoint" ? "evaluator" : role, path);
    const std::string sha = file_sha1(path);
    identity += fmt::format("#   {}: {} {}\n", role, sha, path);
    attrs[role] = path;
    attrs[role + "_sha1"] = sha;
  }
  RunDir run = RunDir::open(job.run, identity, overrides,
                            fmt::format("{}-{}-{}", stem, identity_hash(job), c10::sha1(identity).str().substr(0, 8)));
  res.run_dir = run.path().string();
  if (run.finished()) {  // a finished evaluation of the same bytes is a no-op: report what it found
    for (auto& [k, v] : run.summary()) {
      Replicated r;
      r.mean = v;
      res.summaries[k] = r;
    }
    // The spread the run wrote (metrics.csv: metric,mean,std,ci95,n); means from DONE.
    std::ifstream csv(run.path() / "metrics.csv");
    std::string line;
    std::getline(csv, line);
    while (std::getline(csv, line)) {
      std::vector<std::string> f;
      std::stringstream ss(line);
      for (std::string x; std::getline(ss, x, ',');) f.push_back(x);
      if (f.size() != 5 || !res.summaries.count(f[0])) continue;
      char* end = nullptr;
      const double sd = std::strtod(f[2].c_str(), &end), ci = std::strtod(f[3].c_str(), nullptr);
      const long nn = std::strtol(f[4].c_str(), nullptr, 10);
      if (end == f[2].c_str() || !std::isfinite(sd) || !std::isfinite(ci) || nn < 0) continue;
      res.summaries[f[0]].std = sd, res.summaries[f[0]].ci95 = ci, res.summaries[f[0]].n = static_cast<int>(nn);
    }
    run.log().info(fmt::format("{} is finished; showing its means (run.force=true redoes it)", res.run_dir));
    return res;
  }
  T2MEvaluator ev = T2MEvaluator::load(ev_run.run_dir.string());
  MotionSet reference = split_of(read_motion_file(ref_path), job.eval.split, ref_path);
  MotionSet motions = job.eval.motions.empty() ? reference : read_motion_file(motions_path);
  if (!(motions.skeleton == reference.skeleton))
    fail("{}: skeleton '{}' differs from the reference's '{}'", motions_path, motions.skeleton.name,
         reference.skeleton.name);
  run.log().info(fmt::format("evaluating {} ({} motions) against {} split '{}' ({} clips) with evaluator {}",
                             motions_path, motions.size(), ref_path, job.eval.split, reference.size(),
                             ev_run.run_dir.string()));
  EvalEmbeddings emb = embed_for_eval(ev, reference, ref_path, motions, motions_path);
  std::optional<MotionSet> source;
  if (!src_path.empty()) source = read_motion_file(src_path);
  // Control errors: from eval.constraints, else from the specs a generated file carries.
  std::vector<ConstraintSpec> stored;
  if (constraints_path.empty() && !job.eval.motions.empty()) {
    stored = read_sample_constraints(motions_path).specs;
    if (!any_constraints(stored)) stored.clear();
    if (!stored.empty() && stored.size() != motions.size())
      fail("{}: /control holds {} sample specs for {} motions", motions_path, stored.size(), motions.size());
  }
  auto free = stored.empty() ? evaluator_free_metrics(motions, motions_path, job.protocol, constraints_path,
                                                      source ? &*source : nullptr)
                             : evaluator_free_metrics(motions, motions_path, job.protocol, stored);
  std::vector<std::vector<double>> errors;  // per sample, the error of every constrained entry
  if (!stored.empty()) errors = control_entry_errors(motions, motions_path, stored);
  else if (!constraints_path.empty())
    errors = control_entry_errors(motions, motions_path, constraints_path, source ? &*source : nullptr);

  // The motions are fixed (nothing is regenerated here), so replicate r is a bootstrap
  // resample of the samples (seed + r): repeating the same set would print ± 0 for
  // FID, matching and one-pool R-precision. The reported value stays the full set's.
  const size_t n = motions.size();
  std::vector<JointsView> clips;
  for (size_t i = 0; i < n; ++i) clips.push_back(joints_view(motions, i));
  std::map<std::string, double> point = t2m_metrics(emb, job.protocol, static_cast<uint64_t>(job.run.seed));
  for (auto& [k, v] : free) point[k] = v;
  for (int r = 0; r < job.protocol.repeats; ++r) {
    std::mt19937_64 rng(static_cast<uint64_t>(job.run.seed) + static_cast<uint64_t>(r));
    std::uniform_int_distribution<size_t> pick(0, n - 1);
    std::vector<size_t> idx(n);
    for (auto& i : idx) i = pick(rng);
    auto m = t2m_metrics(select_rows(emb, idx), job.protocol, static_cast<uint64_t>(job.run.seed) + r);
    for (auto& [k, v] : free_metrics_of_selection(clips, errors.empty() ? nullptr : &errors, idx, motions.skeleton,
                                                  motions.fps, job.protocol))
      m[k] = v;
    // A metric a resample cannot form (no caption drawn twice: no multimodality; no
    // constrained sample drawn) leaves that resample out of its spread.
    for (auto& [k, v] : m)
      if (point.count(k) && std::isfinite(v)) res.values[k].push_back(v);
  }
  std::map<std::string, Replicated> summaries;
  for (auto& [k, v] : point) {
    res.values[k];  // a metric no resample could form still reports its full-set value
    summaries[k] = bootstrap_summary(v, res.values[k]);
  }
  res.summaries = summaries;

  // Per sample, for outside tools: matching distance, foot skating, control errors.
  EvalSampleRecord rec;
  rec.embeddings = &emb;
  rec.ids = motions.ids;
  rec.lengths = motions.lengths;
  rec.reference_ids = reference.ids;
  rec.attrs = attrs;
  auto& matching = rec.metrics["matching"];
  for (size_t i = 0; i < n; ++i) matching.push_back((emb.text.row(i) - emb.motion.row(i)).norm());
  FootSkatingOptions fo;
  fo.fps = motions.fps;
  fo.padded_196 = job.protocol.foot_skating_padded_196;
  auto& skating = rec.metrics["foot_skating"];
  for (size_t i = 0; i < n; ++i) skating.push_back(foot_skating_ratio({clips[i]}, motions.skeleton, fo));
  if (!errors.empty()) {
    auto& avg = rec.metrics["avg_err"];
    auto& mx = rec.metrics["max_err"];
    for (auto& e : errors) {
      double sum = 0, m = 0;
      for (double x : e) sum += x, m = std::max(m, x);
      avg.push_back(e.empty() ? std::nan("") : sum / e.size());
      mx.push_back(e.empty() ? std::nan("") : m);
    }
  }
  write_eval_results(run.path().string(), res.values, summaries, rec);
  std::map<std::string, double> summary;
  for (auto& [k, r] : summaries) summary[k] = r.mean;
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
      std::cout << format_metric_table(r.summaries) << "results: " << r.run_dir << "/metrics.csv, metrics.h5\n";
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
    cmd->add_option("--constraints", a->constraints, "constraint spec (YAML or HDF5) the motions were generated under (default: the per-sample specs "
                   "`motionctl generate` stored in the file, if any)");
    cmd->add_option("--source", a->source, "motion file whose clip i gives sample i's from_source targets");
    cmd->add_flag("--csv", a->csv, "print metric,value CSV");
    cmd->add_flag("--padded-196", a->padded, "foot skating over the padded 196 frames");
    cmd->callback([a] {
      MotionSet m = read_motion_file(a->file);
      std::optional<MotionSet> src;
      if (!a->source.empty()) src = read_motion_file(a->source);
      EvalProtocol p;
      p.foot_skating_padded_196 = a->padded;
      std::map<std::string, double> metrics;
      std::vector<ConstraintSpec> stored;
      if (a->constraints.empty()) stored = read_sample_constraints(a->file).specs;
      if (any_constraints(stored)) {
        if (stored.size() != m.size())
          fail("{}: /control holds {} sample specs for {} motions; the group must hold one per motion", a->file,
               stored.size(), m.size());
        if (!a->source.empty())
          fail("{}: --source gives from_source targets for --constraints, but the file's own specs (/control) "
               "already hold their targets; drop --source or pass --constraints",
               a->file);
        std::cerr << fmt::format("control errors from the {} constraint specs stored in {} (/control)\n",
                                 stored.size(), a->file);
        metrics = evaluator_free_metrics(m, a->file, p, stored);
      } else {
        metrics = evaluator_free_metrics(m, a->file, p, a->constraints, src ? &*src : nullptr);
      }
      if (a->csv) std::cout << "metric,value\n";
      for (auto& [k, v] : metrics)
        std::cout << (a->csv ? fmt::format("{},{:.8g}\n", k, v) : fmt::format("{:<16} {:.6f}\n", k, v));
    });
  }
}

}  // namespace mc
