// Reconstruction guidance (`flow_guidance`) as a fair baseline (issue 14): with the
// tables' own settings (experiments/generators/guidance.yaml) on the shipped smoke
// prior it beats the unconstrained prior's control error at every OmniControl density,
// pelvis and all joints, paired (same tasks, same seeds); and the residual clip keeps a
// step size far too large for a single keyframe from throwing the sample away.
#include <catch2/catch.hpp>

#include <limits>
#include <map>
#include <random>

#include "control/control_task.h"
#include "control/linear_observation.h"
#include "data/fixture/fixture.h"
#include "data/skeleton.h"
#include "models/flow_prior_test_util.h"
#include "samplers/motion_generator.h"
#include "train/pretrained.h"
#include "control/control_test_util.h"
#include "data/data_test_util.h"
#include "test_util.h"
#include "samplers/generator_test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

std::unique_ptr<MotionGenerator> generator_of(const ConfigSource& src) { return build_generator(src); }

struct ProtocolFile : Config {
  Component protocol{"protocol"};
  void visit(FieldVisitor& v) override { v("protocol", protocol, "protocol"); }
};

// Mean over the task's controlled joint-frames of the Euclidean error (metres), the
// OmniControl Avg. err of one sample: rows come in (x, y, z) triples per joint-frame.
double avg_err(const ControlTask& t, const GeneratedMotions& g, size_t i) {
  LinearObservation o = compile(t.spec, t.length, humanml3d_skeleton(), t.source.data());
  auto w = g.world[static_cast<int64_t>(i)].narrow(0, 0, t.length).contiguous();
  Eigen::VectorXd x(o.dim());
  for (int k = 0; k < o.dim(); ++k) x[k] = w.data_ptr<float>()[k];
  Eigen::VectorXd r = o.A * x - o.y;
  double sum = 0;
  for (int k = 0; k + 2 < r.size(); k += 3) sum += r.segment<3>(k).norm();
  return sum / static_cast<double>(r.size() / 3);
}

// Per-density mean Avg. err of a generator on `tasks` (group "joint=.../density=D").
std::map<std::string, double> per_density(MotionGenerator& gen, const std::vector<ControlTask>& tasks,
                                          uint64_t seed) {
  auto g = gen.generate(tasks, seed);
  std::map<std::string, double> sum;
  std::map<std::string, int> n;
  for (size_t i = 0; i < tasks.size(); ++i) {
    const std::string d = tasks[i].group.substr(tasks[i].group.find("density=") + 8);
    sum[d] += avg_err(tasks[i], g, i);
    ++n[d];
  }
  for (auto& [d, s] : sum) s /= n[d];
  return sum;
}

}  // namespace

TEST_CASE("guidance beats the unconstrained prior's control error at every OmniControl density (paired)",
          "[samplers][slow]") {
  const std::string src = MOTIONCTL_SOURCE_DIR;
  std::string prior_dir;
  for (const auto& e : read_pretrained_manifest(fs::path(src) / "pretrained"))
    if (e.config == "configs/prior/flow_tiny.yaml") prior_dir = e.dir.string();
  REQUIRE(!prior_dir.empty());  // the smoke prior is shipped

  FixtureJobConfig job;
  parse_config(compose_config(src + "/configs/data/smoke.yaml"), job);
  const MotionSet data = generate_fixture(job.fixture, load_skeleton(src + "/" + job.skeleton));
  const std::vector<size_t> test = data.indices_of_split("test");
  REQUIRE(test.size() >= 30);

  // The tables' guidance settings (the tuned step), on the smoke prior at the smoke profile's 10 steps.
  const std::vector<std::string> on_smoke = {"generator.prior.run_dir=" + prior_dir,
                                             "generator.sampler.steps=10"};
  auto guided = generator_of(compose_config(src + "/experiments/generators/guidance.yaml", on_smoke));
  auto free = generator_of(compose_config(src + "/experiments/generators/flow.yaml", on_smoke));

  for (const std::string& joints : {std::string("[0]"), std::string("[0, 10, 11, 15, 20, 21]")}) {
    ProtocolFile p;
    // Pelvis: 4 clips x 5 densities; all joints: 30 clips, each (joint, density) once.
    const bool pelvis = joints == "[0]";
    parse_config(config_from_string(fmt::format("protocol: {{type: omnicontrol, joints: {}, assignment: {}}}", joints,
                                                pelvis ? "all" : "cycle")),
                 p);
    const std::vector<size_t> clips(test.begin(), test.begin() + (pelvis ? 4 : 30));
    const auto tasks = as_protocol(p.protocol).make_tasks(data, clips, 3);
    const auto e_free = per_density(*free, tasks, 11), e_guided = per_density(*guided, tasks, 11);
    REQUIRE(e_free.size() == 5);
    for (const auto& [d, err] : e_free) {
      INFO("joints " << joints << " density " << d << ": prior " << err << " m, guidance " << e_guided.at(d) << " m");
      CHECK(e_guided.at(d) < err);
    }
  }
}

TEST_CASE("guidance: the residual clip keeps an oversized step from overshooting a single keyframe", "[samplers]") {
  TempDir dir("guidance_clip");
  write_random_prior_run(dir.path / "prior");
  const Skeleton& sk = humanml3d_skeleton();
  std::mt19937_64 rng(21);
  std::vector<ControlTask> tasks;
  for (int i = 0; i < 4; ++i) {
    ControlTask t;
    t.id = "c" + std::to_string(i);
    t.caption = "a person walks";
    t.length = 16;
    t.source = random_motion(rng, t.length, sk);
    ConstraintItem it;
    it.type = "keyframe";
    it.joints = {JointRef{i % 2 == 0 ? 0 : 20, ""}};
    it.frames.kind = FrameSelection::Kind::list;
    it.frames.list = {3 + i};
    it.from_source = true;
    t.spec.items = {it};
    tasks.push_back(t);
  }
  const std::string base = fmt::format(
      "generator:\n  type: flow_guidance\n  prior: {{run_dir: {}}}\n  sampler: {{steps: 10}}\n", (dir.path / "prior").string());
  auto err_of = [&](const std::string& guidance) {
    auto g = generator_of(config_from_string(base + guidance))->generate(tasks, 5);
    double e = 0;
    for (size_t i = 0; i < tasks.size(); ++i) e += avg_err(tasks[i], g, i);
    return e / tasks.size();
  };
  const double free = err_of("  guidance: {iterations: 0, final_steps: 0}\n");
  // A step 1e4 times what a single keyframe's mean loss needs: clipped, it lands near the target.
  const double clipped = err_of("  guidance: {scale: 1.0e4, final_steps: 2, final_iterations: 10}\n");
  INFO("free " << free << " clipped " << clipped);
  CHECK(clipped < 0.5 * free);
  // Clipped steps cannot move a coordinate further than the residual, so the result stays finite
  // and the error stays below the prior's; unclipped, the same step overshoots by metres or diverges.
  double unclipped = 0;
  try {
    unclipped = err_of("  guidance: {scale: 1.0e4, clip_to_residual: false, final_steps: 2, final_iterations: 10}\n");
  } catch (const UserError&) {
    unclipped = std::numeric_limits<double>::infinity();  // the sampler refuses non-finite motions
  }
  INFO("unclipped " << unclipped);
  CHECK(unclipped > free);
}
