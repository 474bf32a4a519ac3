// The table replay: profiles (smoke/standard/paper), table specs (rows of
// generator configs on a protocol, metric columns), and the row runner that
// generates, evaluates with replications and caches each row by config hash.
#pragma once
#include <map>
#include <string>
#include <vector>

#include "core/config.h"
#include "control/control_task.h"
#include "core/run_dir.h"
#include "eval/evaluation.h"
#include "experiments/paired.h"

namespace mc {

// `profile:` section of configs/profile/<name>.yaml: how big everything is.
struct ProfileConfig : Config {
  std::string name = "smoke";
  std::string data = "data/fixture_smoke.h5";          // ground-truth motion file (tasks and FID reference)
  std::string data_fixture = "configs/data/smoke.yaml";  // builds `data` when it is missing
  std::string evaluator = "configs/eval/evaluator_smoke.yaml";
  std::string split = "test";
  int num_samples = 32;   // tasks per row: the first N clips of the split (0 = all)
  int repeats = 3;        // replications, each with fresh generation (papers: 20)
  int64_t seed = 1;
  int threads = 0;
  std::string device = "cpu";
  std::vector<std::string> substitutions;  // path=value applied to generator/protocol files where path exists
  std::vector<std::string> trained_configs;  // from=to: training configs swapped for this profile
  // table_id=N: tasks per row of one table in this profile (cheap tables with small
  // effects get more tasks; the smoke and CI profiles keep theirs).
  std::vector<std::string> table_num_samples;
  bool lengthen_training = true;  // rows may train a component longer than its training config
  std::string runs_root = "runs/experiments";
  std::string results_root = "results";
  bool health = true;  // prior health of every trained prior the rows use
  int health_samples = 0;  // N of those checks (0 = num_samples); issue 13's targets ask for N >= 256
  void visit(FieldVisitor& v) override {
    v("name", name, "profile name (results/<name>/)");
    v("data", data, "ground-truth motion file: tasks come from its split, FID references it");
    v("data_fixture", data_fixture, "fixture config that builds `data` when it is missing ('' = must exist)");
    v("evaluator", evaluator, "training config of the evaluator (trained on first use)");
    v("split", split, "split the tasks and the FID reference come from", one_of({"train", "val", "test"}));
    v("num_samples", num_samples, "tasks per row: the first N clips of the split (0 = all)", at_least(0));
    v("repeats", repeats, "replications with fresh generation (mean +- 1.96 std / sqrt(n))", at_least(1));
    v("seed", seed, "base seed; replicate r of a row uses seed + 1000 r");
    v("threads", threads, "torch CPU threads (0 = all cores)", at_least(0));
    v("device", device, "torch device: cpu, cuda, cuda:N");
    v("substitutions", substitutions,
      "path=value overrides applied to every generator and protocol file that has `path` (model sizes, steps)");
    v("trained_configs", trained_configs,
      "from=to training-config swaps for every trained component, also inside other training configs "
      "(e.g. configs/prior/flow_tiny.yaml=configs/prior/flow_standard.yaml)");
    v("table_num_samples", table_num_samples,
      "table_id=N entries: tasks per row for that table in this profile (over the table's own num_samples and "
      "profile.num_samples), e.g. anchorroute/table4=256");
    v("lengthen_training", lengthen_training,
      "whether rows may train a component longer than its training config says (optim.steps overrides such as "
      "Table IV's 4,500-step adapter); false caps them at the config's own steps (smoke and CI profiles), and "
      "the capped run carries optim.steps=N");
    v("runs_root", runs_root, "where row runs and trained components live");
    v("results_root", results_root, "results/<profile>/ goes here");
    v("health", health,
      "check every trained prior and tokenizer the rows use (motionctl health): verdicts at the top of each table "
      "and in results/<profile>/health.md");
    v("health_samples", health_samples,
      "samples of each health check (0 = num_samples); capped so that N test clips and N floor clips exist",
      at_least(0));
  }
  std::string validate() const override;
};

struct ProfileFile : Config {
  ProfileConfig profile;
  EvalProtocol protocol;
  void visit(FieldVisitor& v) override {
    v("profile", profile, "sizes, data, evaluator, substitutions");
    v("protocol", protocol, "metric protocol (protocol.repeats is ignored: profile.repeats counts replications)");
  }
};
ProfileFile load_profile(const std::string& name_or_file);  // "smoke" -> configs/profile/smoke.yaml

// `table:` section of an experiment spec (experiments/<paper>/tableN.yaml).
struct TableConfig : Config {
  std::string id;             // e.g. projflow/table1
  std::string title;
  std::string paper_numbers;  // experiments/paper_numbers/<paper>/tableN.yaml ('' = none)
  std::string protocol;       // file with a `protocol:` section
  std::vector<std::string> protocol_overrides;
  std::vector<std::string> columns;  // metric keys; key@group-filter restricts to tasks whose group contains it
  int num_samples = 0;        // 0 = the profile's
  int multimodality_texts = 0;        // > 0: T2M's separate multimodality pass over this many texts
  int multimodality_generations = 10;  // generations per text in that pass
  std::string foot_skating = "padded_196";  // which convention the foot_skating column shows
  std::vector<std::string> differences;     // remaining differences from the paper's protocol (caption)
  std::vector<std::string> derived;         // column=metric/row: computed from another metric, not measured
  void visit(FieldVisitor& v) override {
    v("id", id, "table id, e.g. projflow/table1");
    v("title", title, "caption");
    v("paper_numbers", paper_numbers, "the paper's numbers for this table ('' = none)");
    v("protocol", protocol, "file with a `protocol:` section: the control tasks of every row");
    v("protocol_overrides", protocol_overrides, "path=value overrides of the protocol file");
    v("columns", columns, "metric keys shown (metric@filter: over tasks whose group contains filter)");
    v("num_samples", num_samples, "tasks per row (0 = the profile's)", at_least(0));
    v("multimodality_texts", multimodality_texts,
      "texts of the separate multimodality pass (T2M: 100 texts x 30 generations; 0 = no pass)", at_least(0));
    v("multimodality_generations", multimodality_generations, "generations per text in the multimodality pass",
      at_least(2));
    v("foot_skating", foot_skating,
      "frames of the foot_skating column: padded_196 (the published OmniControl/GMD script: all 196 stored frames, "
      "/ 195) or valid_frames (the clip's own frames); the other one is shown as a labelled extra column",
      one_of({"padded_196", "valid_frames"}));
    v("differences", differences, "differences from the paper's protocol that remain (listed in the caption)");
    v("derived", derived,
      "derived columns, each column=metric/row: every replicate's metric divided by the mean of that metric in row "
      "`row` (Table VII: relative_cost=time_per_sample/rs0); the column must be listed in columns");
  }
  std::string validate() const override;
};

// One `table.derived` entry, column=metric/row.
struct DerivedColumn {
  std::string column, metric, base_row;
};
// UserError naming `what` and the entry when it is not column=metric/row.
DerivedColumn parse_derived_column(const std::string& entry, const std::string& what);

// One entry of `rows:`.
struct RowConfig : Config {
  std::string id;         // our row id; matched against the paper numbers' ours_id
  std::string label;      // shown in the table ('' = id)
  std::string generator;  // file with a `generator:` section
  std::vector<std::string> overrides;  // path=value on the generator file
  std::string protocol;   // '' = the table's
  std::vector<std::string> protocol_overrides;
  std::string paper_id;   // ours_id in the paper numbers ('' = id)
  std::string paper_section;  // section of the paper row ('' = the first row with that ours_id)
  int repeats = 0;        // 0 = the profile's; fewer for a row too slow for the profile's budget (DNO)
  void visit(FieldVisitor& v) override {
    v("id", id, "row id, e.g. projflow/euclidean");
    v("label", label, "row label ('' = id)");
    v("generator", generator, "file with a `generator:` section");
    v("overrides", overrides, "path=value overrides of the generator file");
    v("protocol", protocol, "protocol file ('' = the table's)");
    v("protocol_overrides", protocol_overrides, "path=value overrides of the protocol (after the table's)");
    v("paper_id", paper_id, "ours_id of the matching paper row ('' = id)");
    v("paper_section", paper_section, "section of the matching paper row ('' = first row with that ours_id)");
    v("repeats", repeats,
      "replications of this row (0 = the profile's; fewer for a row that cannot fit the profile's budget otherwise)",
      at_least(0));
  }
  std::string validate() const override {
    if (id.empty()) return "row id is empty";
    if (generator.empty()) return "row '" + id + "' names no generator file";
    return "";
  }
};

struct TableSpec {
  std::string file;
  TableConfig table;
  std::vector<RowConfig> rows;
};
TableSpec load_table_spec(const std::string& file);  // UserError naming file, row and key

// Tasks per row of `table` under `profile`: profile.table_num_samples, else the table's
// num_samples, else profile.num_samples.
int table_tasks(const ProfileConfig& profile, const TableConfig& table);

// Everything a finished row produced.
struct RowResult {
  std::string row_id, label, run_dir, generator_description;
  std::map<std::string, std::vector<double>> values;  // metric -> one value per replicate
  std::vector<std::string> notes;                     // e.g. trainable parameter counts
  std::vector<std::string> components;  // run directories of the trained components the generator used
  RowSamples samples;                   // per task and replicate (samples.h5): what paired tests resample
  bool cached = false;
};

inline constexpr size_t kExamplesPerRow = 4;  // samples per row kept for figures (examples.h5)
inline constexpr unsigned long long kExamplesInResults = 2;  // of those, copied into results.h5

class RowEvaluator;  // evaluator + reference embeddings, shared across rows

// The row's generator and protocol as resolved (substitutions and overrides applied).
struct ResolvedRow {
  Component generator{"generator"};
  Component protocol{"protocol"};
  std::string generator_yaml, protocol_yaml;  // dumps (part of the cache key)
};
ResolvedRow resolve_row(const ProfileConfig& profile, const TableSpec& table, const RowConfig& row);

// Per-sample metrics of one replicate (what samples.h5 keeps): control errors, both
// foot-skating conventions, lifting errors over every camera item (MPJPE on the first,
// the keypose), per-sample matching and R-precision hits in the pools of `seed`.
std::map<std::string, std::vector<double>> row_sample_metrics(const MotionSet& generated, const EvalEmbeddings& emb,
                                                             const std::vector<ControlTask>& tasks,
                                                             const EvalProtocol& proto, uint64_t seed);

// Generates `repeats` replicate sample sets for the row's tasks, evaluates each
// and writes runs/experiments/<profile>/rows/<row>-<hash>/ (config, samples_r*.h5,
// metrics.csv/h5, DONE). A finished run with the same key is read back instead.
RowResult run_row(const ProfileFile& profile, const TableSpec& table, const RowConfig& row, RowEvaluator& ev);

// A row's examples.h5 (row_runner.cpp): the first `k` generated samples with their
// targets, hard point constraints and cameras, for figures; sealed (core/h5_seal.h).
void write_examples(const std::string& path, const MotionSet& gen, const std::vector<ControlTask>& tasks, size_t k);

}  // namespace mc
