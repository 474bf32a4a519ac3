// The `motionctl eval` job: which evaluator, reference split and motion file,
// under which protocol. The table replay reuses run_eval_job.
#pragma once
#include <map>
#include <string>
#include <vector>

#include "core/config.h"
#include "core/run_dir.h"
#include "eval/evaluation.h"

namespace mc {

struct EvalInputs : Config {
  std::string evaluator = "configs/eval/evaluator_smoke.yaml";
  std::vector<std::string> evaluator_overrides;  // e.g. your own dataset: [data.path=data/mine.h5, run.name=mine]
  std::string reference = "data/fixture_smoke.h5";
  std::string split = "test";
  std::string motions;
  std::string constraints;
  std::string source;
  void visit(FieldVisitor& v) override {
    v("evaluator", evaluator, "training config of the evaluator (trained on first use, then reused)");
    v("evaluator_overrides", evaluator_overrides,
      "key=value overrides applied to `evaluator`, e.g. [data.path=data/mine.h5, run.name=mine] to train it on "
      "your own dataset");
    v("reference", reference, "ground-truth motion file");
    v("split", split, "reference split", one_of({"train", "val", "test"}));
    v("motions", motions, "motion file to evaluate ('' = the reference split itself: the ground-truth row)");
    v("constraints", constraints, "constraint spec the motions were generated under ('' = the per-sample specs a `generate` output "
                   "carries, else no control metrics)");
    v("source", source, "motion file giving from_source constraint targets, clip i for motion i");
  }
};

struct EvalJobConfig : Config {
  RunConfig run;
  EvalInputs eval;
  EvalProtocol protocol;
  EvalJobConfig() { run.experiment = "eval"; }
  void visit(FieldVisitor& v) override {
    v("run", run, "run directory and seed (replicate r uses seed + r)");
    v("eval", eval, "what to evaluate");
    v("protocol", protocol, "metric protocol (papers' values by default)");
  }
};

struct EvalJobResult {
  std::string run_dir;
  std::map<std::string, std::vector<double>> values;  // metric -> one value per bootstrap resample
  std::map<std::string, Replicated> summaries;        // full-set value, bootstrap spread (bootstrap_summary)
};

EvalJobResult run_eval_job(EvalJobConfig& job, const std::vector<std::string>& overrides, const std::string& stem);

}  // namespace mc
