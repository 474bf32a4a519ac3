// The prior health check: the ground-truth self-check is exactly clean (ratios 1,
// FID 0 below its positive floor, healthy); a random-weight flow prior is judged
// unhealthy on bone lengths; reports are well-formed JSON/Markdown, deterministic
// per seed; token priors and the tokenizer run through the same check; bad input
// exits 2 naming the value.
#include <catch2/catch.hpp>

#include <fstream>

#include "core/error.h"
#include "eval/health.h"
#include "eval/health_test_util.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"
#include "train/train_job.h"

using namespace mc;
using namespace mc::test;

namespace {

// A fixture of `clips` clips (10% test, 10% val) and a tiny evaluator config on it.
struct HealthBed {
  TempDir dir{"health"};
  std::string fx, evaluator, runs;
  explicit HealthBed(int clips) {
    fx = (dir.path / "fx.h5").string();
    runs = (dir.path / "runs").string();
    auto r = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips={}", fx, clips));
    if (r.exit_code != 0) throw std::runtime_error(r.output);
    evaluator = (dir.path / "evaluator.yaml").string();
    write_tiny_evaluator_config(evaluator, fx, runs);
  }
  // Command-line options shared by every check of the bed.
  std::string common(int samples = 8) const {
    return fmt::format("--samples {} --data {} --evaluator {} protocol.repeats=3 threads=1", samples, fx, evaluator);
  }
};

bool python_json_ok(const fs::path& p) {
  return std::system(fmt::format("'{}' -c 'import json, sys; json.load(open(sys.argv[1]))' '{}'", MOTIONCTL_PYTHON,
                                 p.string())
                         .c_str()) == 0;
}

const HealthMetric& metric(const HealthReport& r, const std::string& key) {
  const HealthMetric* m = r.find(key);
  if (!m) throw std::runtime_error("no metric " + key);
  return *m;
}

}  // namespace

TEST_CASE("health report: JSON round trip, escaping, verdict, targets in --describe", "[health]") {
  HealthReport r;
  r.run_dir = "runs/prior/with \"quote\" and \\ backslash";
  r.model_type = "flow_prior";
  r.data = "fx.h5";
  r.reference = "test[0:8]";
  r.floor_reference = "val[0:8]";
  r.evaluator_run = "runs/evaluator/x";
  r.generator = "flow prior\nsecond line";
  r.options_hash = "abc";
  r.samples = 8;
  r.r_precision_pool = 8;
  r.repeats = 3;
  r.seed = 4;
  r.metrics.push_back({"fid", "FID (N = 8)", 3.5, 1.5, "<= 2x GT floor", false});
  r.metrics.push_back({"kid", "KID (N = 8)", -0.01, 0.002, "", std::nullopt});
  r.metrics.push_back({"foot_skating", "foot skating ratio", 0.2, 0.0, "<= 3x GT", false});
  r.metrics.push_back({"bone_length_std_mm", "bone-length std (mm)", 1.0, std::nullopt, "<= 5 mm", true});
  // Values that 10 significant digits would not carry: a report re-read from its cached
  // health.json must give the same ratios as the fresh one, to the last bit.
  r.metrics.push_back({"acceleration", "mean |acceleration| (m/s^2)", 1.0 / 3.0, 5.107186364123456, "<= 2x GT", true});
  r.validation["val_fm_t0.10"] = 0.25;
  REQUIRE_FALSE(r.healthy());
  REQUIRE(r.failed() == std::vector<std::string>{"FID (N = 8)", "foot skating ratio"});

  TempDir dir("health_json");
  const fs::path p = dir.path / "health.json";
  std::ofstream(p) << health_json(r);
  CHECK(python_json_ok(p));
  HealthReport back = read_health_json(p.string());
  CHECK(back.run_dir == r.run_dir);
  CHECK(back.generator == r.generator);
  CHECK(back.seed == 4);
  REQUIRE(back.metrics.size() == 5);
  CHECK(back.metrics[4].value == 1.0 / 3.0);
  CHECK(*back.metrics[4].ground_truth == 5.107186364123456);
  CHECK(back.metrics[0].value == 3.5);
  CHECK(*back.metrics[0].ground_truth == 1.5);
  CHECK(back.metrics[1].value == -0.01);
  CHECK_FALSE(back.metrics[1].pass.has_value());
  CHECK_FALSE(back.metrics[3].ground_truth.has_value());
  CHECK(back.validation.at("val_fm_t0.10") == 0.25);
  CHECK(back.failed() == r.failed());
  CHECK(health_json(back) == health_json(r));
  const std::string md = health_markdown(r);
  CHECK(md.find("NOT healthy") != std::string::npos);
  CHECK(md.find("| FID (N = 8) | 3.5 | 1.5 (floor) | 2.33x | <= 2x GT floor | **FAIL** |") != std::string::npos);
  // A '|' in a label is escaped, so every table row keeps its 6 cells.
  HealthReport piped = r;
  piped.metrics.push_back({"acceleration", "mean |acceleration| (m/s^2)", 4.0, 2.0, "<= 2x GT", true});
  CHECK(health_markdown(piped).find("| mean \\|acceleration\\| (m/s^2) | 4 | 2 | 2x | <= 2x GT | pass |") !=
        std::string::npos);
  CHECK(md.find("| foot skating ratio | 0.2 | 0 | – |") != std::string::npos);  // GT 0: no ratio
  CHECK(md.find("| val_fm_t0.10 | 0.25 |") != std::string::npos);
  std::ofstream(dir.path / "broken.json") << "{\"run_dir\": 1";
  REQUIRE_THROWS_AS(read_health_json((dir.path / "broken.json").string()), UserError);

  // The targets are declared once and printed with their defaults.
  auto d = run_motionctl("health --describe");
  INFO(d.output);
  REQUIRE(d.exit_code == 0);
  for (const char* key : {"targets.foot_skating_ratio", "targets.bone_length_std_mm", "targets.acceleration_ratio",
                          "targets.r_precision_top3_ratio", "targets.fid_floor_ratio"})
    CHECK(d.output.find(key) != std::string::npos);
  CHECK(run_motionctl("config --describe --job health --section targets").exit_code == 0);
}

TEST_CASE("default evaluator: the evaluator config trained on the same data, else a clear error", "[health]") {
  CHECK(fs::path(default_evaluator_config("data/fixture_smoke.h5")).filename() == "evaluator_smoke.yaml");
  CHECK(fs::path(default_evaluator_config("data/fixture_standard.h5")).filename() == "evaluator_standard.yaml");
  try {
    default_evaluator_config("/tmp/elsewhere.h5");
    FAIL("no error");
  } catch (const UserError& e) {
    CHECK(std::string(e.what()).find("/tmp/elsewhere.h5") != std::string::npos);
    CHECK(std::string(e.what()).find("--evaluator") != std::string::npos);
  }
}

TEST_CASE("motionctl health: ground-truth self-check is clean, a random flow prior is not, bad input exits 2",
          "[health][cli]") {
  HealthBed bed(120);  // 12 test, 12 val clips
  const fs::path prior = bed.dir.path / "prior";
  write_random_prior_run(prior, 196);
  // The run's own validation figures are reported (val_* only).
  std::ofstream(prior / "summary.csv") << "key,value\nsteps,10\nval_fm,0.4\nval_fm_t0.10,0.9\nval_fm_t0.90,0.1\n";

  {  // bad input first (exit 2 naming the value, nothing written)
    auto missing = run_motionctl(fmt::format("health {}/nope {}", bed.dir.path.string(), bed.common()));
    CHECK(missing.exit_code == 2);
    CHECK(missing.output.find("nope' does not exist") != std::string::npos);
    auto big = run_motionctl(fmt::format("health {} {}", prior.string(), bed.common(13)));
    CHECK(big.exit_code == 2);
    CHECK(big.output.find("samples = 13 is larger than the test split") != std::string::npos);
    auto small = run_motionctl(fmt::format("health {} {}", prior.string(), bed.common(1)));
    CHECK(small.exit_code == 2);
    CHECK(small.output.find("samples = 1") != std::string::npos);
    const fs::path other = bed.dir.path / "evaluator_run";
    fs::create_directories(other);
    std::ofstream(other / "config.yaml") << "model:\n  type: t2m_evaluator\n";
    auto type = run_motionctl(fmt::format("health {} {}", other.string(), bed.common()));
    CHECK(type.exit_code == 2);
    CHECK(type.output.find("'t2m_evaluator'") != std::string::npos);
    auto no_ev = run_motionctl(fmt::format("health {} --samples 8 --data {}", prior.string(), bed.fx));
    CHECK(no_ev.exit_code == 2);
    CHECK(no_ev.output.find("no evaluator config") != std::string::npos);
    auto typo = run_motionctl(fmt::format("health {} {} targets.foot_skating_ratoi=2", prior.string(), bed.common()));
    CHECK(typo.exit_code == 2);
    CHECK(typo.output.find("did you mean") != std::string::npos);
    // Too few held-out clips for the floor: 6 test and 3 val clips cannot give 4 + 4.
    const std::string fx2 = (bed.dir.path / "fx2.h5").string();
    REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60 "
                                      "fixture.train_fraction=0.85 fixture.val_fraction=0.05",
                                      fx2)).exit_code == 0);
    auto floor = run_motionctl(fmt::format("health {} --samples 4 --data {} --evaluator {}", prior.string(), fx2,
                                           bed.evaluator));
    INFO(floor.output);
    CHECK(floor.exit_code == 2);
    CHECK(floor.output.find("the val split of") != std::string::npos);
    CHECK_FALSE(fs::exists(prior / "health.json"));
    CHECK_FALSE(fs::exists(other / "health.json"));
  }
  {  // ground truth scored as samples: every ratio 1, FID 0 under a positive floor, healthy
    auto r = run_motionctl(fmt::format("health {} --ground-truth {}", prior.string(), bed.common()));
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    REQUIRE(python_json_ok(prior / "health.json"));
    HealthReport h = read_health_json((prior / "health.json").string());
    CHECK(h.ground_truth);
    CHECK(h.samples == 8);
    CHECK(h.reference == "test[0:8]");
    CHECK(h.floor_reference == "val[0:8]");
    CHECK(h.r_precision_pool == 8);  // pools capped at N
    for (const char* key : {"foot_skating", "acceleration", "bone_length_std_mm", "r_precision_top1",
                            "r_precision_top3", "matching", "diversity", "toe_penetration_m"}) {
      INFO(key);
      CHECK(metric(h, key).value == *metric(h, key).ground_truth);
    }
    CHECK(metric(h, "acceleration").value > 0.1);  // the fixture moves
    CHECK(std::abs(metric(h, "fid").value) < 1e-6);
    CHECK(*metric(h, "fid").ground_truth > 1e-3);  // held-out clips are not the reference
    CHECK(metric(h, "bone_length_std_mm").value < 1.0);  // the fixture's skeleton is rigid
    CHECK(h.healthy());
    CHECK(h.validation.size() == 3);
    CHECK(h.validation.at("val_fm_t0.10") == 0.9);
    CHECK(h.validation.count("steps") == 0);
    const std::string md = slurp(prior / "health.md");
    CHECK(md.find("**Verdict: healthy** (5 of 5 targets met)") != std::string::npos);
    CHECK(md.find("| metric | GT as samples | ground truth | ratio | target | pass |") != std::string::npos);
    CHECK(md.find("| val_fm_t0.90 | 0.1 |") != std::string::npos);
  }
  {  // a random-weight prior fails the bone-length target; same seed, same report
    const std::string cmd = fmt::format("health {} {} 'generator_overrides=[generator.sampler.steps=3]'",
                                        prior.string(), bed.common());
    auto r = run_motionctl(cmd + " --seed 5");
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    CHECK(r.output.find("NOT healthy") != std::string::npos);
    const std::string first = slurp(prior / "health.json");
    HealthReport h = read_health_json((prior / "health.json").string());
    CHECK_FALSE(h.ground_truth);
    CHECK(h.model_type == "flow_prior");
    CHECK(h.generator.find("flow prior") != std::string::npos);
    CHECK(h.generator.find("3 steps") != std::string::npos);
    CHECK(metric(h, "bone_length_std_mm").value > 5.0);
    CHECK(metric(h, "bone_length_std_mm").pass == false);
    CHECK_FALSE(h.healthy());
    auto again = run_motionctl(cmd + " --seed 5");
    REQUIRE(again.exit_code == 0);
    CHECK(slurp(prior / "health.json") == first);
    auto other = run_motionctl(cmd + " --seed 6");
    REQUIRE(other.exit_code == 0);
    CHECK(slurp(prior / "health.json") != first);
  }
  {  // --split val: the val clips are the reference, test the floor, in files of their own
    const std::string test_report = slurp(prior / "health.json");
    auto r = run_motionctl(fmt::format("health {} --ground-truth --split val {}", prior.string(), bed.common()));
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    CHECK(r.output.find("health_val.json") != std::string::npos);
    REQUIRE(python_json_ok(prior / "health_val.json"));
    HealthReport h = read_health_json((prior / "health_val.json").string());
    CHECK(h.reference == "val[0:8]");
    CHECK(h.floor_reference == "test[0:8]");
    CHECK(std::abs(metric(h, "fid").value) < 1e-6);
    CHECK(h.healthy());
    CHECK(slurp(prior / "health_val.md").find("val[0:8]") != std::string::npos);
    CHECK(slurp(prior / "health.json") == test_report);  // the test-split report stays put
    auto bad = run_motionctl(fmt::format("health {} --split train {}", prior.string(), bed.common()));
    CHECK(bad.exit_code == 2);
    CHECK(bad.output.find("reference.split") != std::string::npos);
  }
}

TEST_CASE("health of the token priors (decoded samples) and the VQ tokenizer (reconstructions)", "[health]") {
  HealthBed bed(60);  // 6 test, 6 val clips
  const std::vector<std::string> common = {"data.path=" + bed.fx, "run.root=" + bed.runs, "run.threads=1",
                                           "optim.steps=12", "optim.warmup=2", "optim.batch_size=8",
                                           "run.log_every=4", "run.checkpoint_every=12"};
  auto tok_ov = common;
  for (const char* o : {"model.width=32", "model.code_dim=32", "model.codebook_size=32"}) tok_ov.push_back(o);
  const std::string tok = run_train("configs/tokenizer/vq_tiny.yaml", tok_ov).run_dir.string();
  auto prior_ov = common;
  for (const std::string& o : std::vector<std::string>{"model.width=32", "model.heads=2", "model.text_width=32",
                                                       "model.text_ff=32", "model.eval_t=[0.5]",
                                                       "model.tokenizer_run=" + tok})
    prior_ov.push_back(o);
  const std::string tmd = run_train("configs/tmd/tmd_tiny.yaml", prior_ov).run_dir.string();
  const std::string masked = run_train("configs/masked/masked_tiny.yaml", prior_ov).run_dir.string();

  auto options = [&](const std::string& run) {
    HealthOptions o;
    o.run_dir = run;
    o.samples = 4;
    o.data = bed.fx;
    o.evaluator = bed.evaluator;
    o.threads = 1;
    o.protocol.repeats = 2;
    return o;
  };
  HealthOptions t = options(tmd);
  t.generator_overrides = {"generator.sampler.steps=4"};
  HealthReport h = check_health(t);
  CHECK(h.model_type == "tmd_prior");
  CHECK(h.generator.find("TMD prior") != std::string::npos);
  CHECK(h.generator.find("4 steps") != std::string::npos);
  CHECK(h.validation.count("val_ce_t0.50") == 1);
  CHECK(h.r_precision_pool == 4);
  CHECK(h.metrics.size() == 12);
  for (const auto& m : h.metrics) CHECK(std::isfinite(m.value));
  const std::string json = slurp(fs::path(tmd) / "health.json");
  CHECK(python_json_ok(fs::path(tmd) / "health.json"));
  CHECK(slurp(fs::path(tmd) / "health.md").find("# Prior health") == 0);
  check_health(t);  // deterministic: the same report again
  CHECK(slurp(fs::path(tmd) / "health.json") == json);

  HealthOptions m = options(masked);
  m.generator_overrides = {"generator.sampler.steps=3"};
  HealthReport hm = check_health(m);
  CHECK(hm.model_type == "masked_prior");
  CHECK(hm.generator.find("masked prior") != std::string::npos);

  HealthReport hv = check_health(options(tok));
  CHECK(hv.model_type == "vq_tokenizer");
  CHECK(hv.generator.find("reconstructions") != std::string::npos);
  REQUIRE(hv.find("reconstruction_mpjpe_m"));
  const double mpjpe = hv.find("reconstruction_mpjpe_m")->value;
  CHECK(mpjpe > 0.0);
  // The same pipeline on the ground truth reconstructs nothing: MPJPE 0, ratios 1.
  HealthOptions g = options(tok);
  g.ground_truth = true;
  HealthReport hg = check_health(g);
  CHECK(hg.find("reconstruction_mpjpe_m")->value == 0.0);
  CHECK(hg.find("acceleration")->value == *hg.find("acceleration")->ground_truth);
  CHECK(hg.healthy());
}
