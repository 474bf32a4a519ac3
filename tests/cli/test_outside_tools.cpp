// Results open to outside tools (issue 14): `generate` stores each sample's
// constraint spec and `score` reproduces its printed control errors from the file
// alone (protocol tasks and the user's own constraints); `eval` writes the
// evaluator embeddings (FID recomputes from them) and keys its cache by content,
// so a file regenerated at the same path is evaluated anew.
#include <catch2/catch.hpp>

#include <random>
#include <regex>

#include "control/sample_constraints.h"
#include "data/motion_set.h"
#include "eval/eval_outputs.h"
#include "eval/metrics.h"
#include "eval/t2m_evaluator.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

// The numbers of generate's "control: traj_err A  loc_err B  avg_err C m" line.
std::array<double, 3> printed_control(const std::string& out) {
  std::smatch m;
  REQUIRE(std::regex_search(out, m, std::regex("control: traj_err ([0-9.e+-]+)  loc_err ([0-9.e+-]+)  avg_err ([0-9.e+-]+)")));
  return {std::stod(m[1]), std::stod(m[2]), std::stod(m[3])};
}

// metric -> value of `score --csv` (or of a metrics.csv's mean column).
std::map<std::string, double> csv_values(const std::string& text) {
  std::map<std::string, double> out;
  std::regex row(R"(^([A-Za-z_@.0-9|/=]+),([-0-9.e+naif]+))");
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    std::smatch m;
    if (std::regex_search(line, m, row) && m[1] != "metric") out[m[1]] = std::stod(m[2]);
  }
  return out;
}

}  // namespace

TEST_CASE("score on a generate output reproduces the generator's printed control errors", "[cli][outside]") {
  TempDir dir("outside_gen");
  const std::string fx = (dir.path / "fx.h5").string(), prior = (dir.path / "prior").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=30", fx)).exit_code == 0);
  write_random_prior_run(prior, 196);

  SECTION("protocol tasks: 2D lifting under guidance (non-zero errors, cameras stored)") {
    const std::string out = (dir.path / "lift.h5").string();
    auto g = run_motionctl(fmt::format(
        "generate configs/control/lifting_smoke.yaml generator=guidance_tiny generator.prior.run_dir={} "
        "generator.sampler.steps=3 generator.guidance.scale=0.01 data.path={} data.num_samples=3 output={} "
        "run.threads=1",
        prior, fx, out));
    INFO(g.output);
    REQUIRE(g.exit_code == 0);
    auto printed = printed_control(g.output);
    CHECK(printed[2] > 1e-3);  // an untrained prior under weak guidance (scale 0.01) misses its targets
    SampleConstraints sc = read_sample_constraints(out);
    REQUIRE(sc.specs.size() == 3);
    bool camera = false;
    for (auto& spec : sc.specs)
      for (auto& it : spec.items) {
        CHECK_FALSE(it.from_source);  // targets written out: no ground truth needed
        camera = camera || (it.type == "camera_2d" && it.has_camera);
      }
    CHECK(camera);
    auto s = run_motionctl(fmt::format("score {} --csv", out));  // no --constraints, no --source
    INFO(s.output);
    REQUIRE(s.exit_code == 0);
    auto v = csv_values(s.output);
    REQUIRE(v.count("avg_err"));
    CHECK(v["traj_err@0.5"] == Approx(printed[0]).margin(6e-5));
    CHECK(v["loc_err@0.5"] == Approx(printed[1]).margin(6e-5));
    CHECK(v["avg_err"] == Approx(printed[2]).margin(6e-7));
    // A different spec gives different errors: score really reads the stored one.
    std::ofstream(dir.path / "other.yaml") << "- {type: keyframe, joints: [pelvis], frames: [0], values: [[[5, 5, 5]]]}\n";
    auto o = run_motionctl(fmt::format("score {} --csv --constraints {}", out, (dir.path / "other.yaml").string()));
    REQUIRE(o.exit_code == 0);
    CHECK(std::abs(csv_values(o.output)["avg_err"] - printed[2]) > 0.1);
  }

  SECTION("the user's own constraints, caption and length") {
    // A soft pelvis path the user drew (30 frames), and a hard start position.
    std::string yaml = "constraints:\n  - {type: keyframe, name: start, joints: [pelvis], frames: [0], values: [[[0.0, 0.9, 0.0]]]}\n"
                       "  - type: trajectory\n    name: my path\n    joints: [pelvis]\n    axes: xz\n    variance: 0.05\n"
                       "    frames: {start: 1, stop: 30}\n    values: [";
    for (int t = 1; t < 30; ++t) yaml += fmt::format("{}[{:.3f}, {:.3f}]", t > 1 ? ", " : "", 0.05 * t, 0.02 * t);
    yaml += "]\n";
    std::ofstream(dir.path / "mine.yaml") << yaml;
    const std::string out = (dir.path / "mine.h5").string();
    auto g = run_motionctl(fmt::format(
        "generate configs/control/trajectory_smoke.yaml generator.prior.run_dir={} generator.sampler.steps=3 "
        "data.path={} data.num_samples=2 output={} run.threads=1 custom.constraints={} custom.length=30 "
        "\"custom.caption=a person walks in a curve\"",
        prior, fx, out, (dir.path / "mine.yaml").string()));
    INFO(g.output);
    REQUIRE(g.exit_code == 0);
    auto printed = printed_control(g.output);
    CHECK(printed[2] > 1e-4);  // soft rows are not met exactly
    MotionSet m = read_motion_file(out);
    REQUIRE(m.size() == 2);
    CHECK(m.lengths[0] == 30);
    CHECK(m.captions[1][0] == "a person walks in a curve");
    CHECK(m.at(0, 0, 0)[0] == Approx(0.0).margin(1e-4));  // the hard start holds
    auto s = run_motionctl(fmt::format("score {} --csv", out));
    REQUIRE(s.exit_code == 0);
    auto v = csv_values(s.output);
    CHECK(v["avg_err"] == Approx(printed[2]).margin(6e-7));
    CHECK(v["traj_err@0.5"] == Approx(printed[0]).margin(6e-5));

    // Per-task specs from an HDF5 file with /control (here: the output just written).
    auto again = run_motionctl(fmt::format(
        "generate configs/control/trajectory_smoke.yaml generator.prior.run_dir={} generator.sampler.steps=3 "
        "data.path={} data.num_samples=2 output={}/again.h5 run.threads=1 custom.constraints={}",
        prior, fx, dir.path.string(), out));
    INFO(again.output);
    REQUIRE(again.exit_code == 0);
    CHECK(read_motion_file((dir.path / "again.h5").string()).lengths[1] == 30);  // /control/frames
    auto bad = run_motionctl(fmt::format(
        "generate configs/control/trajectory_smoke.yaml generator.prior.run_dir={} data.path={} data.num_samples=3 "
        "output={}/bad.h5 custom.constraints={}",
        prior, fx, dir.path.string(), out));
    CHECK(bad.exit_code == 2);
    CHECK(bad.output.find("data.num_samples=2") != std::string::npos);
  }
}

TEST_CASE("eval: embeddings round-trip and FID recomputes from them, a file regenerated in place is re-evaluated",
          "[eval][outside]") {
  TempDir t("outside_eval");
  const std::string fx = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=120", fx)).exit_code == 0);
  // A barely trained evaluator: the round trip needs its numbers, not its quality.
  auto tr = run_motionctl(fmt::format(
      "train configs/eval/evaluator_smoke.yaml data.path={} run.root={} run.name=ev optim.steps=4 optim.warmup=1 "
      "run.threads=1",
      fx, t.path.string()));
  INFO(tr.output);
  REQUIRE(tr.exit_code == 0);
  const std::string ev_run = (t.path / "evaluator" / "ev").string();
  std::ofstream(t.path / "ev.yaml") << slurp(fs::path(ev_run) / "config.yaml");
  MotionSet all = read_motion_file(fx);
  MotionSet test = all.subset(all.indices_of_split("test"));
  REQUIRE(test.size() >= 4);
  auto noisy = [&](double sigma) {
    MotionSet m = test;
    std::mt19937_64 rng(3);
    std::normal_distribution<double> n(0.0, sigma);
    for (size_t i = 0; i < m.size(); ++i)
      for (int f = 0; f < m.lengths[i]; ++f)
        for (int j = 0; j < m.num_joints(); ++j)
          for (int c = 0; c < 3; ++c) m.at(i, f, j)[c] += static_cast<float>(n(rng));
    for (auto& s : m.splits) s = "sample";
    return m;
  };
  const std::string motions = (t.path / "samples.h5").string();
  const std::string base = fmt::format(
      "eval configs/eval/t2m_smoke.yaml eval.evaluator={} eval.reference={} eval.motions={} run.root={} "
      "protocol.repeats=2 run.threads=1",
      (t.path / "ev.yaml").string(), fx, motions, t.path.string());
  T2MEvaluator ev = T2MEvaluator::load(ev_run);
  Embeddings gt = ev.embed_motions(test, "test");
  auto run_dir_of = [](const std::string& out) {
    std::smatch m;
    REQUIRE(std::regex_search(out, m, std::regex("results: (\\S+)/metrics.csv")));
    return std::string(m[1]);
  };

  double first_fid = 0;
  std::string first_dir;
  for (double sigma : {0.02, 0.2}) {
    MotionSet m = noisy(sigma);
    write_motion_file(motions, m);  // the same path both times
    auto r = run_motionctl(base);
    INFO("sigma " << sigma << ": " << r.output);
    REQUIRE(r.exit_code == 0);
    const std::string run = run_dir_of(r.output);
    const double printed = csv_values(slurp(fs::path(run) / "metrics.csv")).at("fid");
    // Round trip: the stored embeddings are what the evaluator computes for these files.
    EvalEmbeddings e = read_eval_embeddings(run);
    Embeddings mine = ev.embed_motions(m, "m");
    REQUIRE(e.motion.rows() == static_cast<Eigen::Index>(m.size()));
    REQUIRE(e.gt_motion.rows() == gt.rows());
    CHECK((e.motion - mine).cwiseAbs().maxCoeff() <= 1e-5 * (1 + mine.cwiseAbs().maxCoeff()));
    CHECK((e.gt_motion - gt).cwiseAbs().maxCoeff() <= 1e-5 * (1 + gt.cwiseAbs().maxCoeff()));
    CHECK(e.text.rows() == e.motion.rows());
    // FID recomputed from the stored embeddings equals the one eval reported.
    CHECK(fid(e.motion, e.gt_motion) == Approx(printed).epsilon(1e-6));
    // The true FID of the file now at that path, not a cached one.
    CHECK(printed == Approx(fid(mine, gt)).epsilon(1e-4));
    if (first_dir.empty()) {
      first_fid = printed, first_dir = run;
    } else {
      CHECK(run != first_dir);
      CHECK(printed > first_fid * 1.5);  // more noise: a clearly different FID
    }
  }
  // Same bytes again: the finished run is reused (a cache hit, by content).
  auto again = run_motionctl(base);
  REQUIRE(again.exit_code == 0);
  CHECK(again.output.find("is finished") != std::string::npos);
}
