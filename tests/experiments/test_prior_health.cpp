// Prior health in the table replay: a table whose rows used an unhealthy prior says
// so at its top (with a link to health.md), components the check does not cover are
// left out, results/<profile>/health.{md,json} gather the reports, and a later replay
// reuses RUN_DIR/health.json when the options match.
#include <catch2/catch.hpp>

#include <fstream>

#include "core/atomic_file.h"
#include "eval/health_test_util.h"
#include "experiments/prior_health.h"
#include "experiments/report.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("reproduce's prior health: table tops name the verdict, health.md/json gather the reports", "[health]") {
  TempDir dir("prior_health");
  const std::string fx = (dir.path / "fx.h5").string(), runs = (dir.path / "runs").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=100", fx)).exit_code ==
          0);
  const std::string evaluator = (dir.path / "evaluator.yaml").string();
  write_tiny_evaluator_config(evaluator, fx, runs);
  const fs::path prior = dir.path / "prior", adapter = dir.path / "adapter";
  write_random_prior_run(prior, 196);  // random weights: bones are not kept
  fs::create_directories(adapter);
  std::ofstream(adapter / "config.yaml") << "model:\n  type: anchorkv_adapter\n";  // not covered: left out
  // Control components: no sampling check, their signal uptake from summary.csv instead.
  const fs::path kv = dir.path / "kv", cn = dir.path / "cn";
  fs::create_directories(kv);
  fs::create_directories(cn);
  std::ofstream(kv / "config.yaml") << "model:\n  type: anchor_adapter\n  adapter: anchorkv\n  dual_context: false\n";
  std::ofstream(kv / "summary.csv") << "key,value\nval_soft_control_error_t01,0.4\nval_soft_control_error_t01_zeroed,0.5\n";
  std::ofstream(cn / "config.yaml") << "model:\n  type: flow_controlnet\n";
  std::ofstream(cn / "summary.csv") << "key,value\nval_ctrl_t0.10,0.05\n";  // trained before val_ctrl_off

  ProfileFile pf;
  pf.profile.name = "ci";
  pf.profile.data = fx;
  pf.profile.evaluator = evaluator;
  pf.profile.num_samples = 50;  // more than the 10 test clips: capped to 10 (val has 10 for the floor)
  pf.profile.repeats = 2;
  pf.profile.threads = 1;
  pf.profile.substitutions = {"generator.sampler.steps=3", "generator.opt_steps=2"};
  const MotionSet data = read_motion_file(fx);
  ProfileHealth health(pf, data);
  CHECK(health.samples() == 10);
  {
    // health_samples sets N apart from the rows' count (and is capped the same way).
    ProfileFile own = pf;
    own.profile.health_samples = 4;
    CHECK(ProfileHealth(own, data).samples() == 4);
    own.profile.num_samples = 3;
    CHECK(ProfileHealth(own, data).samples() == 4);
    own.profile.health_samples = 0;
    CHECK(ProfileHealth(own, data).samples() == 3);
    own.profile.health_samples = 256;
    CHECK(ProfileHealth(own, data).samples() == 10);
  }

  TableResult t;
  t.spec.table.id = "projflow/table9";
  t.spec.table.title = "a table";
  t.spec.table.columns = {"fid"};
  RowConfig rc;
  rc.id = "row";
  rc.generator = "experiments/generators/flow.yaml";
  t.spec.rows = {rc, rc};
  RowResult a, b;
  a.row_id = b.row_id = "row";
  a.label = b.label = "Row";
  a.values["fid"] = b.values["fid"] = {1.0, 2.0};
  a.components = {prior.string(), adapter.string(), kv.string(), cn.string()};
  b.components = {prior.string()};  // the same prior twice: checked once
  t.rows = {a, b};
  t.health = health.table_line(t);
  INFO(t.health);
  CHECK(t.health.find("**Prior health: NOT healthy** ([health.md](../health.md), N = 10)") == 0);
  CHECK(t.health.find("(flow_prior) **NOT healthy** (misses ") != std::string::npos);
  CHECK(t.health.find("bone-length std (mm)") != std::string::npos);
  CHECK(t.health.find("adapter") == std::string::npos);
  REQUIRE(health.components().size() == 1);
  const std::string md = render_table(t).markdown;
  CHECK(md.find("### projflow/table9 — a table\n\n**Prior health: NOT healthy**") == 0);
  // The flow generator got the profile's sampling budget (substitution where the path exists).
  REQUIRE(health.components()[0].report);
  CHECK(health.components()[0].report->generator.find("3 steps") != std::string::npos);

  // A table without trained priors gets no line.
  TableResult gt = t;
  for (auto& r : gt.rows) r.components.clear();
  CHECK(health.table_line(gt).empty());

  const fs::path out = dir.path / "results";
  fs::create_directories(out);
  health.write(out);
  const std::string hmd = slurp(out / "health.md");
  CHECK(hmd.find("0 of 1 healthy") != std::string::npos);
  CHECK(hmd.find(fmt::format("| `{}` | flow_prior | **NOT healthy** |", prior.string())) != std::string::npos);
  CHECK(hmd.find("| metric | flow_prior | ground truth | ratio | target | pass |") != std::string::npos);
  CHECK(hmd.find("## Control components: do they read their signal?") != std::string::npos);
  CHECK(hmd.find(fmt::format("| `{}` | anchor_adapter (anchorkv, no dual context) |", kv.string())) != std::string::npos);
  CHECK(hmd.find("| 0.4 | 0.5 | -20.0 % |") != std::string::npos);
  CHECK(hmd.find("not logged: the run has no val_ctrl_off_t0.10") != std::string::npos);
  CHECK(hmd.find("anchorkv_adapter") == std::string::npos);  // unknown types are left out
  CHECK_FALSE(control_uptake(prior.string(), "flow_prior"));
  // Feedback channels and rollout states are named (the run names are hashes).
  const fs::path ro = dir.path / "ro";
  fs::create_directories(ro);
  std::ofstream(ro / "config.yaml")
      << "model:\n  type: anchor_adapter\n  adapter: anchorkv\n  dual_context: false\n  features:\n    feedback:\n"
         "      enabled: true\n  training:\n    rollout:\n      prob: 0.3\n      loss:\n        ce_weight: 0.2\n"
         "        anchor_weight: 1\n";
  auto u = control_uptake(ro.string(), "anchor_adapter");
  REQUIRE(u);
  CHECK(u->model_type ==
        "anchor_adapter (anchorkv, no dual context, feedback channels, rollout states in 0.3 of batches (CE 0.2, "
        "anchor loss 1))");
  CHECK(std::system(fmt::format("'{}' -c 'import json, sys; d = json.load(open(sys.argv[1])); "
                                "assert d[\"healthy\"] is False and len(d[\"components\"]) == 1; "
                                "c = d[\"control_components\"]; assert len(c) == 2 and c[0][\"with_signal\"] == 0.4 "
                                "and c[1][\"without_signal\"] is None' '{}'",
                                MOTIONCTL_PYTHON, (out / "health.json").string())
                        .c_str()) == 0);

  // A second replay with the same options reuses RUN_DIR/health.json (no new check);
  // other options check again.
  const auto stamp = fs::last_write_time(prior / "health.json");
  ProfileHealth again(pf, data);
  CHECK(again.table_line(t) == t.health);
  CHECK(fs::last_write_time(prior / "health.json") == stamp);
  // A report scored with other evaluator weights (a retrained evaluator at the same path)
  // is checked again; so is one written before the fingerprints.
  {
    std::string js = slurp(prior / "health.json");
    const std::string key = "\"evaluator_sha1\": \"";
    const size_t at = js.find(key);
    REQUIRE(at != std::string::npos);
    REQUIRE(js.compare(at + key.size(), 1, "\"") != 0);  // a fingerprint was recorded
    js.replace(at + key.size(), 4, "0000");
    write_file_atomic(prior / "health.json", js);
    const auto edited = fs::last_write_time(prior / "health.json");
    ProfileHealth other_evaluator(pf, data);
    CHECK(other_evaluator.table_line(t) == t.health);
    CHECK(fs::last_write_time(prior / "health.json") != edited);
    CHECK(slurp(prior / "health.json").find(key + "0000") == std::string::npos);
  }
  const auto rechecked = fs::last_write_time(prior / "health.json");
  ProfileHealth reused(pf, data);
  reused.table_line(t);
  CHECK(fs::last_write_time(prior / "health.json") == rechecked);
  pf.profile.seed = 2;
  ProfileHealth reseeded(pf, data);
  reseeded.table_line(t);
  CHECK(fs::last_write_time(prior / "health.json") != stamp);

  // Too little data for N >= 3 with a floor (2 test, 2 val clips): the line says the
  // check failed, nothing throws.
  std::vector<size_t> keep = data.indices_of_split("train");
  for (const char* split : {"test", "val"})
    for (size_t k = 0; k < 2; ++k) keep.push_back(data.indices_of_split(split)[k]);
  ProfileHealth none(pf, data.subset(keep));
  const std::string failed = none.table_line(t);
  CHECK(failed.find("health check failed: ") != std::string::npos);
  CHECK(failed.find("fewer than 3 samples") != std::string::npos);
}
