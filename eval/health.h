// The prior health check (`motionctl health RUN_DIR`, issue 13): is a trained prior
// (flow, TMD, masked) or VQ tokenizer fit to test claims on? It generates N
// unconstrained motions for the first N test clips' captions and lengths (a
// tokenizer reconstructs those clips) through the generator registry, scores them
// beside the held-out ground truth with the text-to-motion evaluation code and the
// motion realism metrics, applies the health targets and writes RUN_DIR/health.md
// and health.json. Definitions: docs/metrics.md, "Prior health".
#pragma once
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "core/config.h"
#include "eval/evaluation.h"

namespace mc {

// The pass/fail thresholds, all in one place (printed by `motionctl health --describe`,
// overridable as targets.<name>=value).
struct HealthTargets : Config {
  double foot_skating_ratio = 3.0;      // foot skating <= this x ground truth
  double bone_length_std_mm = 5.0;      // bone-length std over time <= this (absolute, mm)
  double acceleration_ratio = 2.0;      // mean |acceleration| <= this x ground truth
  double r_precision_top3_ratio = 0.8;  // R-precision top-3 >= this x ground truth
  double fid_floor_ratio = 2.0;         // FID <= this x the ground-truth floor at the same N
  void visit(FieldVisitor& v) override {
    v("foot_skating_ratio", foot_skating_ratio, "pass when foot skating <= this x the ground truth's",
      positive<double>());
    v("bone_length_std_mm", bone_length_std_mm, "pass when the bone-length std over time <= this many mm",
      positive<double>());
    v("acceleration_ratio", acceleration_ratio, "pass when mean |acceleration| <= this x the ground truth's",
      positive<double>());
    v("r_precision_top3_ratio", r_precision_top3_ratio, "pass when R-precision top-3 >= this x the ground truth's",
      positive<double>());
    v("fid_floor_ratio", fid_floor_ratio, "pass when FID <= this x the ground-truth floor (GT vs GT at the same N)",
      positive<double>());
  }
};

// Which split the samples are compared with. `val` is for choosing a sampler setting
// (a CFG scale or interval) without looking at the test clips the tables report on;
// its files are health_val.md / health_val.json, so the test-split report a
// `reproduce` caches stays put. Its own section, absent from the dump at `test`, so
// cached reports keep their options hash.
struct HealthReferenceConfig : Config {
  std::string split = "test";
  void visit(FieldVisitor& v) override {
    v("split", split,
      "the reference clips: the first N of this split; the floor: the first N of the other one (test or val)",
      one_of({"test", "val"}));
  }
  bool omitted_from_dump() const override { return split == "test"; }
  // "health" or "health_val": the report's file name without extension.
  std::string file_stem() const { return split == "test" ? "health" : "health_" + split; }
};

struct HealthOptions : Config {
  std::string run_dir;
  int samples = 32;
  int64_t seed = 0;
  std::string evaluator;
  std::vector<std::string> evaluator_overrides;
  std::string data;
  HealthReferenceConfig reference;
  bool ground_truth = false;
  std::string generator;
  std::vector<std::string> generator_overrides;
  std::vector<std::string> substitutions;
  int threads = 0;
  std::string device = "cpu";
  EvalProtocol protocol;
  HealthTargets targets;
  void visit(FieldVisitor& v) override;
};

struct HealthMetric {
  std::string key;    // e.g. "fid", "foot_skating"
  std::string label;  // e.g. "FID"
  double value = 0.0;                 // the prior's (or tokenizer's) figure
  std::optional<double> ground_truth;  // held-out ground truth's figure (FID/KID: the floor)
  std::string target;                 // e.g. "<= 3x GT"; "" = reported, no target
  std::optional<bool> pass;           // set when there is a target
};

struct HealthReport {
  std::string run_dir, model_type, data, evaluator_run, generator;
  std::string reference;        // which clips are the reference, e.g. "test[0:32]"
  std::string floor_reference;  // the held-out clips of the floor, e.g. "val[0:32]"
  std::string options_hash;     // config_hash of the options (reproduce reuses a matching report)
  // SHA-1 of the checked run's and the evaluator's checkpoints/final.pt when the check ran
  // ("" when there is none): a report is reused only while both weights are the same
  // (the options name the evaluator's config, not its weights, which a retraining changes).
  std::string run_sha1, evaluator_sha1;
  bool ground_truth = false;    // the ground_truth self-check, not the run's samples
  int samples = 0, r_precision_pool = 0, repeats = 0;
  int64_t seed = 0;
  std::vector<HealthMetric> metrics;
  std::map<std::string, double> validation;  // the run's summary.csv val_* entries (per-t losses)

  bool healthy() const;                       // every target met
  std::vector<std::string> failed() const;    // labels of the targets missed
  const HealthMetric* find(const std::string& key) const;  // null when absent
};

// Model types the check knows (model.type in RUN_DIR/config.yaml).
const std::vector<std::string>& health_model_types();

// The evaluator training config (configs/eval/evaluator_*.yaml) whose data.path is
// `data_path`; UserError naming the data when none is.
std::string default_evaluator_config(const std::string& data_path);

// Runs the check and writes RUN_DIR/health.md and health.json (health_val.* with
// reference.split = val) atomically. UserError
// (naming the value) for a missing run directory, an unknown model type, samples < 3
// or more than the reference split, too few held-out clips for the floor.
HealthReport check_health(const HealthOptions& options);

std::string health_markdown(const HealthReport& r);
std::string health_json(const HealthReport& r);
// `s` as a JSON string literal (quoted, escaped): for files that embed reports.
std::string json_quote(const std::string& s);
// Reads health.json back (what health_json wrote); UserError naming the file.
HealthReport read_health_json(const std::string& path);

}  // namespace mc
