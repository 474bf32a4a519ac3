// `motionctl generate` with every application config (configs/control/*.yaml) on a
// randomly initialised prior: runs end to end, hard constraints hold, bad input exits 2.
#include <catch2/catch.hpp>

#include <fstream>
#include <regex>

#include "data/motion_set.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("motionctl generate: every application config runs and satisfies its hard constraints", "[projflow][cli]") {
  TempDir dir("generate");
  const std::string fx = (dir.path / "fx.h5").string(), prior = (dir.path / "prior").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=30", fx)).exit_code == 0);
  write_random_prior_run(prior, 196);
  for (std::string app : {"keyframes", "trajectory", "lifting", "relative", "loop", "upper_body_edit"}) {
    const std::string out = (dir.path / (app + ".h5")).string();
    auto r = run_motionctl(fmt::format(
        "generate configs/control/{}_smoke.yaml generator.prior.run_dir={} generator.sampler.steps=4 "
        "data.path={} data.num_samples=3 output={} run.threads=1",
        app, prior, fx, out));
    INFO(app << ": " << r.output);
    REQUIRE(r.exit_code == 0);
    MotionSet m = read_motion_file(out);
    CHECK(m.size() == 3);
    std::smatch match;
    REQUIRE(std::regex_search(r.output, match, std::regex("max hard residual ([0-9.e+-]+)")));
    CHECK(std::stod(match[1]) <= 1e-4);
  }
  // the imputation baseline through the group swap
  auto imp = run_motionctl(fmt::format(
      "generate configs/control/keyframes_smoke.yaml generator=imputation_tiny generator.prior.run_dir={} "
      "generator.sampler.steps=3 data.path={} data.num_samples=2 output={}/imp.h5 run.threads=1",
      prior, fx, dir.path.string()));
  INFO(imp.output);
  CHECK(imp.exit_code == 0);
  CHECK(imp.output.find("metric euclidean") != std::string::npos);

  // bad input: unknown protocol key, a joint outside the skeleton -> exit 2, no output file
  auto bad = run_motionctl(fmt::format("generate configs/control/keyframes_smoke.yaml protocol.jionts=[0] "
                                       "generator.prior.run_dir={} data.path={} output={}/bad.h5",
                                       prior, fx, dir.path.string()));
  CHECK(bad.exit_code == 2);
  CHECK(bad.output.find("did you mean") != std::string::npos);
  auto joint = run_motionctl(fmt::format("generate configs/control/keyframes_smoke.yaml protocol.joints=[0,99] "
                                         "generator.prior.run_dir={} data.path={} output={}/bad.h5 run.threads=1",
                                         prior, fx, dir.path.string()));
  CHECK(joint.exit_code == 2);
  CHECK(joint.output.find("99") != std::string::npos);
  CHECK(!fs::exists(dir.path / "bad.h5"));
}

TEST_CASE("motionctl generate: the floor application and every inequality / direction example spec", "[projflow][cli][inequality]") {
  TempDir dir("generate_ineq");
  const std::string fx = (dir.path / "fx.h5").string(), prior = (dir.path / "prior").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=30", fx)).exit_code == 0);
  write_random_prior_run(prior, 196);
  auto value = [](const std::string& out, const std::string& pattern) {
    std::smatch match;
    REQUIRE(std::regex_search(out, match, std::regex(pattern + " ([0-9.e+-]+)")));
    return std::stod(match[1]);
  };
  {
    const std::string out = (dir.path / "floor.h5").string();
    auto r = run_motionctl(fmt::format(
        "generate configs/control/floor_smoke.yaml generator.prior.run_dir={} generator.sampler.steps=4 data.path={} "
        "data.num_samples=3 output={} run.threads=1",
        prior, fx, out));
    INFO(r.output);
    REQUIRE(r.exit_code == 0);
    CHECK(value(r.output, "max hard residual") <= 1e-4);
    CHECK(value(r.output, "max hard violation") <= 1e-5);
    // every stored sample keeps its floor item (score re-reads it from the file)
    MotionSet m = read_motion_file(out);
    for (size_t i = 0; i < m.size(); ++i)
      for (int t = 0; t < m.lengths[i]; ++t)
        for (int j : m.skeleton.role("toes")) CHECK(m.at(i, t, j)[1] >= -1e-5);
  }
  for (std::string spec : {"floor", "half_space", "box", "speed_limit", "tangent", "facing"}) {
    const std::string out = (dir.path / (spec + ".h5")).string();
    auto r = run_motionctl(fmt::format(
        "generate configs/control/keyframes_smoke.yaml custom.constraints=configs/control/specs/{}.yaml "
        "generator.prior.run_dir={} generator.sampler.steps=4 data.path={} data.num_samples=2 output={} run.threads=1",
        spec, prior, fx, out));
    INFO(spec << ": " << r.output);
    REQUIRE(r.exit_code == 0);
    CHECK(value(r.output, "max hard violation") <= 1e-5);
    if (spec == "tangent" || spec == "facing") CHECK(value(r.output, "mean angle error") <= 0.05);
  }
  // an infeasible spec is exit 2 naming its items, and writes nothing
  const std::string bad = (dir.path / "bad.yaml").string();
  {
    std::ofstream f(bad);
    f << "- {type: floor, name: ground}\n"
         "- {type: keyframe, name: sunk, joints: [l_foot], frames: [3], axes: y, values: [[[-0.2]]]}\n";
  }
  auto r = run_motionctl(fmt::format("generate configs/control/keyframes_smoke.yaml custom.constraints={} "
                                     "generator.prior.run_dir={} data.path={} data.num_samples=1 output={}/bad.h5",
                                     bad, prior, fx, dir.path.string()));
  CHECK(r.exit_code == 2);
  CHECK(r.output.find("infeasible") != std::string::npos);
  CHECK(r.output.find("'ground'") != std::string::npos);
  CHECK(r.output.find("'sunk'") != std::string::npos);
  CHECK(!fs::exists(dir.path / "bad.h5"));
}
