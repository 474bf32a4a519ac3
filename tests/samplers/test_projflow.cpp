// ProjFlow sampler: pseudo-observation construction (eqs. (13)-(18)), exactness of
// hard constraints of every type through the whole sampler, soft rows as Sigma -> 0,
// the ablation switches, reconstruction guidance, and the spatial protocols.
#include <catch2/catch.hpp>

#include <random>

#include "control/control_task.h"
#include "control/linear_observation.h"
#include "control/projection_solver.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "models/flow_prior_test_util.h"
#include "samplers/motion_generator.h"
#include "samplers/projflow.h"
#include "samplers/task_observation.h"
#include "control/control_test_util.h"
#include "data/data_test_util.h"
#include "test_util.h"
#include "samplers/generator_test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

std::unique_ptr<MotionGenerator> make_generator(const std::string& yaml) { return build_generator(yaml); }

// Largest |A x - y| over the hard rows of `spec` compiled for `motion` (world units).
double hard_residual(const ConstraintSpec& spec, int T, const std::vector<float>& source, const float* motion) {
  const Skeleton& sk = humanml3d_skeleton();
  LinearObservation obs = compile(spec, T, sk, source.data());
  Eigen::VectorXd x(obs.dim());
  for (int i = 0; i < obs.dim(); ++i) x[i] = motion[i];
  Eigen::VectorXd r = obs.A * x - obs.y;
  double worst = 0;
  for (int i = 0; i < obs.rows(); ++i)
    if (obs.is_hard(i)) worst = std::max(worst, std::abs(r[i]));
  return worst;
}

std::vector<float> sample_of(const GeneratedMotions& g, int i, int T) {
  auto w = g.world[i].narrow(0, 0, T).contiguous();
  return std::vector<float>(w.data_ptr<float>(), w.data_ptr<float>() + w.numel());
}

// One hard point observation per (frame, value) of joint `j`, axis `c`, with
// coefficient `a` (so the stored target is a * value).
LinearObservation point_rows(int T, int J, int j, int c, const std::vector<std::pair<int, double>>& fv, double a) {
  LinearObservation o;
  o.frames = T;
  o.joints = J;
  std::vector<Eigen::Triplet<double>> trip;
  o.y.resize(fv.size());
  o.variance = Eigen::VectorXd::Zero(fv.size());
  for (size_t r = 0; r < fv.size(); ++r) {
    trip.emplace_back(r, LinearObservation::index(fv[r].first, j, c, J), a);
    o.y[r] = a * fv[r].second;
    o.item_of_row.push_back(0);
  }
  o.item_labels = {"points"};
  o.A.resize(fv.size(), 3 * J * T);
  o.A.setFromTriplets(trip.begin(), trip.end());
  return o;
}

}  // namespace

TEST_CASE("pseudo-observation candidates interpolate each observed joint axis linearly", "[projflow]") {
  auto o = point_rows(10, 22, 0, 0, {{2, 1.0}, {6, 3.0}}, 2.0);
  PseudoCandidates c = pseudo_candidates(o);
  REQUIRE(c.entries.size() == 8);  // 10 frames - 2 observed
  std::map<int, std::pair<double, int>> by_frame;
  for (auto& e : c.entries) {
    CHECK(e.joint == 0);
    CHECK(e.axis == 0);
    by_frame[e.frame] = {e.target, e.distance};
  }
  CHECK(by_frame.count(2) == 0);
  CHECK(by_frame.count(6) == 0);
  CHECK(by_frame[0] == std::pair<double, int>{1.0, 2});  // one side only: copied
  CHECK(by_frame[1] == std::pair<double, int>{1.0, 1});
  CHECK(by_frame[3].first == Approx(1.5));
  CHECK(by_frame[4].first == Approx(2.0));
  CHECK(by_frame[4].second == 2);
  CHECK(by_frame[5].first == Approx(2.5));
  CHECK(by_frame[9] == std::pair<double, int>{3.0, 3});

  // rows touching more than one coordinate (relative, camera) give no candidates
  LinearObservation rel = o;
  std::vector<Eigen::Triplet<double>> trip = {{0, 0, 1.0}, {0, 3, -1.0}};
  rel.A.resize(1, o.dim());
  rel.A.setFromTriplets(trip.begin(), trip.end());
  rel.y = Eigen::VectorXd::Zero(1);
  rel.variance = Eigen::VectorXd::Zero(1);
  CHECK(pseudo_candidates(rel).entries.empty());
}

TEST_CASE("pseudo-observations: halo shrinks from l_max to l_min, variances follow eqs. (15)-(18)", "[projflow]") {
  const int T = 30, J = 22;
  auto o = point_rows(T, J, 20, 1, {{15, 0.5}}, 1.0);
  PseudoCandidates c = pseudo_candidates(o);
  PseudoObservationConfig cfg;
  KinematicMetric metric = KinematicMetric::kinematic(humanml3d_skeleton());
  Eigen::MatrixXd still = Eigen::MatrixXd::Zero(T, 3 * J);  // zero curvature everywhere
  const int steps = 10;
  PseudoStep first = pseudo_step(c, cfg, metric, still, 0, steps, 0.0);
  PseudoStep last = pseudo_step(c, cfg, metric, still, steps - 1, steps, 0.9);
  CHECK(first.active.size() == 18);  // distance 1..9 on both sides (< l_max = 10)
  CHECK(last.active.size() == 4);    // distance 1..2 (< l_min = 3)
  // t = 0: tau = 1, pi = clip(c0) = pi_max = 1 -> the variance floor
  for (int i = 0; i < first.variance.size(); ++i) CHECK(first.variance[i] == Approx(cfg.min_variance));
  // t = 0.9: tau = 0.1 + 0.9 * 0.1 = 0.19; pi = 0.57; sigma^2 = r (1 - pi) / pi
  const double pi = 0.19 * 3.0;
  const double r = metric.inverse_diagonal()[20];
  for (int i = 0; i < last.variance.size(); ++i) CHECK(last.variance[i] == Approx(r * (1 - pi) / pi));

  // Two halo joints at a frame share the frame trust in proportion to q_j.
  auto two = point_rows(T, J, 0, 0, {{10, 0.0}}, 1.0);
  auto other = point_rows(T, J, 15, 0, {{10, 0.0}}, 1.0);
  LinearObservation both = two;
  std::vector<Eigen::Triplet<double>> trip = {{0, LinearObservation::index(10, 0, 0, J), 1.0},
                                              {1, LinearObservation::index(10, 15, 0, J), 1.0}};
  both.A.resize(2, two.dim());
  both.A.setFromTriplets(trip.begin(), trip.end());
  both.y = Eigen::VectorXd::Zero(2);
  both.variance = Eigen::VectorXd::Zero(2);
  PseudoCandidates cb = pseudo_candidates(both);
  PseudoStep sb = pseudo_step(cb, cfg, metric, still, steps - 1, steps, 0.9);
  REQUIRE(sb.active.size() == 8);
  const auto& col = metric.inverse_column_norms();
  const double q0 = 1 / (col[0] * col[0]), q15 = 1 / (col[15] * col[15]);
  for (size_t i = 0; i < sb.active.size(); ++i) {
    const auto& e = cb.entries[sb.active[i]];
    const double pij = std::clamp(pi * (e.joint == 0 ? q0 : q15) / (q0 + q15), cfg.pi_min, cfg.pi_max);
    CHECK(sb.variance[i] == Approx(metric.inverse_diagonal()[e.joint] * (1 - pij) / pij));
  }
  (void)other;
}

TEST_CASE("pseudo-observation trust falls where the clean estimate curves", "[projflow]") {
  const int T = 20, J = 22;
  auto o = point_rows(T, J, 0, 0, {{0, 0.0}, {19, 0.0}}, 1.0);
  PseudoCandidates c = pseudo_candidates(o);
  PseudoObservationConfig cfg;
  KinematicMetric metric = KinematicMetric::kinematic(humanml3d_skeleton());
  Eigen::MatrixXd x = Eigen::MatrixXd::Zero(T, 3 * J);
  for (int t = 0; t < T; ++t) x(t, 0) = 0.01 * t;  // straight line: no curvature
  x(5, 0) += 1.0;                                    // a kink at frame 5
  PseudoStep s = pseudo_step(c, cfg, metric, x, 0, 50, 0.5);
  double var_kink = 0, var_flat = 0;
  for (size_t i = 0; i < s.active.size(); ++i) {
    if (c.entries[s.active[i]].frame == 5) var_kink = s.variance[i];
    if (c.entries[s.active[i]].frame == 9) var_flat = s.variance[i];
  }
  CHECK(var_kink > 10 * var_flat);
}

TEST_CASE("ProjFlow: hard constraints of every type hold exactly through the sampler", "[projflow]") {
  TempDir dir("projflow");
  write_random_prior_run(dir.path / "prior");
  const Skeleton& sk = humanml3d_skeleton();
  const int T = 24;
  std::mt19937_64 rng(11);
  const std::vector<std::string> types = {"keyframe", "trajectory", "planar_root", "camera_2d",
                                          "relative", "loop", "upper_body_edit"};
  std::vector<ControlTask> tasks;
  for (size_t i = 0; i < types.size() + 3; ++i) {
    ControlTask t;
    t.id = "task" + std::to_string(i);
    t.caption = "a person walks forward";
    t.length = T - static_cast<int>(i % 3);  // ragged lengths in one batch
    t.source = random_motion(rng, t.length, sk);
    // one type per task, then three tasks mixing several types
    std::vector<std::string> ts = i < types.size() ? std::vector<std::string>{types[i]}
                                                   : std::vector<std::string>{"keyframe", "camera_2d", "relative"};
    random_observation(ts, rng, t.length, sk, t.source, false, &t.spec);
    tasks.push_back(t);
  }
  const std::string base = fmt::format("generator:\n  type: projflow\n  prior: {{run_dir: {}}}\n"
                                       "  sampler: {{steps: 12, batch_size: 4}}\n",
                                       (dir.path / "prior").string());
  for (std::string variant : {"", "  projflow: {metric: {type: euclidean}}\n", "  projflow: {noise: 'off'}\n",
                              "  projflow: {pseudo_observations: {enabled: false}}\n",
                              "  projflow: {metric: {type: euclidean}, noise: 'off', pseudo_observations: {enabled: false}}\n"}) {
    INFO("variant: " << variant);
    auto gen = make_generator(base + variant);
    GeneratedMotions g = gen->generate(tasks, 3);
    REQUIRE(g.world.size(0) == static_cast<int64_t>(tasks.size()));
    for (size_t i = 0; i < tasks.size(); ++i) {
      INFO("task " << i << " " << tasks[i].spec.items.front().type);
      auto m = sample_of(g, static_cast<int>(i), tasks[i].length);
      CHECK(hard_residual(tasks[i].spec, tasks[i].length, tasks[i].source, m.data()) <= 1e-4);
    }
  }
}

TEST_CASE("ProjFlow: soft keyframes approach their targets as the variance shrinks, seeds", "[projflow]") {
  TempDir dir("projflow_soft");
  write_random_prior_run(dir.path / "prior");
  const Skeleton& sk = humanml3d_skeleton();
  std::mt19937_64 rng(5);
  ControlTask t;
  t.id = "soft";
  t.caption = "a person jumps";
  t.length = 20;
  t.source = random_motion(rng, t.length, sk);
  ConstraintItem it;
  it.type = "keyframe";
  it.joints = {JointRef{20, ""}, JointRef{0, ""}};
  it.frames.kind = FrameSelection::Kind::list;
  it.frames.list = {3, 11, 17};
  it.from_source = true;
  auto gen = make_generator(fmt::format("generator:\n  type: projflow\n  prior: {{run_dir: {}}}\n"
                                        "  sampler: {{steps: 10}}\n  projflow: {{pseudo_observations: {{enabled: false}}}}\n",
                                        (dir.path / "prior").string()));
  double previous = 1e9;
  for (double var : {1e-1, 1e-3, 1e-5, 1e-7}) {
    it.variance = var;
    t.spec.items = {it};
    auto g = gen->generate({t}, 7);
    auto m = sample_of(g, 0, t.length);
    ConstraintSpec hard = t.spec;
    hard.items[0].variance = 0;
    double err = hard_residual(hard, t.length, t.source, m.data());
    INFO("variance " << var << " residual " << err);
    CHECK(err < previous);
    previous = err;
  }
  CHECK(previous < 1e-3);

  it.variance = 0;
  t.spec.items = {it};
  auto a = gen->generate({t}, 9), b = gen->generate({t}, 9), c = gen->generate({t}, 10);
  CHECK(torch::equal(a.world, b.world));
  CHECK(!torch::equal(a.world, c.world));
}

TEST_CASE("reconstruction guidance pulls samples toward the constraints, imputation is exact", "[projflow]") {
  TempDir dir("guidance");
  write_random_prior_run(dir.path / "prior");
  const Skeleton& sk = humanml3d_skeleton();
  std::mt19937_64 rng(8);
  std::vector<ControlTask> tasks;
  for (int i = 0; i < 3; ++i) {
    ControlTask t;
    t.id = "g" + std::to_string(i);
    t.caption = "a person walks";
    t.length = 16;
    t.source = random_motion(rng, t.length, sk);
    random_observation({"keyframe"}, rng, t.length, sk, t.source, false, &t.spec);
    tasks.push_back(t);
  }
  const std::string prior = (dir.path / "prior").string();
  auto free = make_generator(fmt::format("generator:\n  type: flow\n  prior: {{run_dir: {}}}\n  sampler: {{steps: 10}}\n", prior));
  auto guided = make_generator(fmt::format(
      "generator:\n  type: flow_guidance\n  prior: {{run_dir: {}}}\n  sampler: {{steps: 10}}\n"
      "  guidance: {{scale: 10.0, iterations: 2, final_steps: 2}}\n", prior));
  auto gf = free->generate(tasks, 4), gg = guided->generate(tasks, 4);
  double err_free = 0, err_guided = 0;
  for (size_t i = 0; i < tasks.size(); ++i) {
    auto mf = sample_of(gf, static_cast<int>(i), 16), mg = sample_of(gg, static_cast<int>(i), 16);
    auto of = compile(tasks[i].spec, 16, sk, tasks[i].source.data());
    err_free += (of.A * to_vector(mf) - of.y).norm();
    err_guided += (of.A * to_vector(mg) - of.y).norm();
  }
  INFO("free " << err_free << " guided " << err_guided);
  CHECK(err_guided < 0.5 * err_free);
}

TEST_CASE("spatial protocols: OmniControl densities, lifting cameras, applications", "[projflow][protocol]") {
  MotionSet data = random_motion_set({40, 60, 33, 50}, {"test"});
  std::vector<size_t> clips = {0, 1, 2, 3};
  auto protocol_of = [](const std::string& yaml) {
    struct File : Config {
      Component protocol{"protocol"};
      void visit(FieldVisitor& v) override { v("protocol", protocol, "protocol"); }
    } f;
    parse_config(config_from_string(yaml), f);
    return f;
  };
  {
    auto f = protocol_of("protocol: {type: omnicontrol, assignment: all}");
    auto tasks = as_protocol(f.protocol).make_tasks(data, clips, 1);
    REQUIRE(tasks.size() == 4 * 6 * 5);
    std::map<std::string, int> frames_of_density;
    for (auto& t : tasks) {
      REQUIRE(t.spec.items.size() == 1);
      const auto& it = t.spec.items[0];
      CHECK(it.joints.size() == 1);
      const int n = static_cast<int>(it.frames.list.size());
      const std::string d = t.group.substr(t.group.find("density=") + 8);
      if (d == "100%") CHECK(n == t.length);
      else if (d == "25%") {
        // Floored as OmniControl's int(T * 0.25): 12 frames of the 50-frame clip, not 13.
        CHECK(n == t.length / 4);
        if (t.length == 50) CHECK(n == 12);
      }
      else CHECK(n == std::stoi(d));
      CHECK(std::is_sorted(it.frames.list.begin(), it.frames.list.end()));
      compile(t.spec, t.length, data.skeleton, t.source.data());  // compiles
    }
    auto again = as_protocol(f.protocol).make_tasks(data, clips, 1);
    for (size_t i = 0; i < tasks.size(); ++i) CHECK(again[i].spec.items[0] == tasks[i].spec.items[0]);
    auto cycle = as_protocol(protocol_of("protocol: {type: omnicontrol, mode: cross}").protocol).make_tasks(data, clips, 2);
    CHECK(cycle.size() == 4);
  }
  {
    auto f = protocol_of("protocol: {type: lifting, mode: cross}");
    auto tasks = as_protocol(f.protocol).make_tasks(data, clips, 3);
    REQUIRE(tasks.size() == 4);
    for (auto& t : tasks) {
      REQUIRE(!t.spec.items.empty());
      CHECK(t.spec.items[0].type == "camera_2d");
      CHECK(t.spec.items[0].frames.list == std::vector<int>{0});
      CHECK(t.spec.items[0].camera.pitch_deg >= 0);
      CHECK(t.spec.items[0].camera.pitch_deg <= 30);
      auto obs = compile(t.spec, t.length, data.skeleton, t.source.data());
      CHECK(obs.rows() >= 22 * 2);
      check_hard_rows(obs);
    }
  }
  for (std::string app : {"upper_body_edit", "relative", "loop"}) {
    auto f = protocol_of("protocol: {type: application, application: " + app + "}");
    auto tasks = as_protocol(f.protocol).make_tasks(data, clips, 1);
    REQUIRE(tasks.size() == 4);
    for (auto& t : tasks) CHECK(compile(t.spec, t.length, data.skeleton, t.source.data()).rows() > 0);
  }
  CHECK_THROWS_AS(as_protocol(protocol_of("protocol: {type: omnicontrol, joints: [0, 40]}").protocol)
                      .make_tasks(data, clips, 1),
                  UserError);
}

TEST_CASE("ProjFlow with inequality and direction items: rows hold through the sampler, warm = cold start",
          "[projflow][inequality]") {
  TempDir dir("projflow_ineq");
  write_random_prior_run(dir.path / "prior");
  const Skeleton& sk = humanml3d_skeleton();
  const int T = 24;
  std::mt19937_64 rng(12);
  const std::vector<std::string> specs = {
      "- {type: floor}\n- {type: keyframe, joints: [pelvis], frames: [0, 20], from_source: true}",
      "- {type: speed_limit, joints: [pelvis], axes: xz, max: 0.02}\n- {type: box, joints: [l_wrist], min: [-0.3, 0.5, -0.3], max: [0.3, 1.2, 0.3]}",
      "- {type: half_space, joints: [l_wrist, r_wrist], normal: [0, 1, 0], offset: 0.0, relative_to: head}",
      "- {type: tangent, joints: [pelvis], frames: [5, 15], values: [1, 0]}\n- {type: facing, frames: [10], values: [0, -1]}\n"
      "- {type: floor, variance: 0.0001}"};
  std::vector<ControlTask> tasks;
  for (size_t i = 0; i < specs.size(); ++i) {
    ControlTask t;
    t.id = "task" + std::to_string(i);
    t.caption = "a person walks forward";
    t.length = T - static_cast<int>(i % 2);
    t.source = random_motion(rng, t.length, sk);
    float lowest = INFINITY;  // the floor convention of the data: nothing below y = 0
    for (size_t k = 1; k < t.source.size(); k += 3) lowest = std::min(lowest, t.source[k]);
    for (size_t k = 1; k < t.source.size(); k += 3) t.source[k] -= lowest;
    t.spec = parse_constraint_spec_yaml(specs[i], "task" + std::to_string(i));
    tasks.push_back(t);
  }
  auto gen = make_generator(fmt::format("generator:\n  type: projflow\n  prior: {{run_dir: {}}}\n"
                                        "  sampler: {{steps: 10, batch_size: 4}}\n",
                                        (dir.path / "prior").string()));
  GeneratedMotions g = gen->generate(tasks, 3);
  for (size_t i = 0; i < tasks.size(); ++i) {
    INFO(specs[i]);
    auto m = sample_of(g, static_cast<int>(i), tasks[i].length);
    LinearObservation obs = compile(tasks[i].spec, tasks[i].length, sk, tasks[i].source.data());
    CHECK(hard_residual(tasks[i].spec, tasks[i].length, tasks[i].source, m.data()) <= 1e-4);
    Eigen::VectorXd x(obs.dim());
    for (int k = 0; k < obs.dim(); ++k) x[k] = m[k];
    Eigen::VectorXd v = obs.G * x - obs.h;
    for (int r = 0; r < obs.inequalities(); ++r)
      if (obs.is_hard_inequality(r)) CHECK(v[r] <= 1e-5);
  }
  // The same run without the warm start: the same samples (the QP's answer does not depend on it).
  FlowPrior prior = FlowPrior::load((dir.path / "prior").string());
  std::vector<std::string> captions;
  std::vector<int> lengths;
  for (auto& t : tasks) captions.push_back(t.caption), lengths.push_back(t.length);
  FlowSamplerConfig sc;
  sc.steps = 10;
  sc.batch_size = 4;
  auto obs = model_observations(prior, tasks);
  ProjFlowConfig cfg;
  ProjFlowStepper warm(cfg, KinematicMetric::from_config(cfg.metric, sk), obs), cold(cfg, KinematicMetric::from_config(cfg.metric, sk), obs);
  cold.set_warm_start(false);
  auto a = sample_flow(prior, captions, lengths, sc, 5, &warm);
  auto b = sample_flow(prior, captions, lengths, sc, 5, &cold);
  CHECK((a.world - b.world).abs().max().item<double>() < 1e-4);
  CHECK(warm.qp_solves() > 0);
  CHECK(warm.qp_iterations() <= cold.qp_iterations());
}

TEST_CASE("ProjFlow on a prior with the kinematic head and its source noise: hard constraints still hold exactly",
          "[projflow][kinematic]") {
  TempDir dir("projflow_kin");
  write_random_prior_run(dir.path / "prior", 40, "flow_prior", kPriorWords,
                         "  prediction: clean\n  kinematic_head:\n    enabled: true\n    noise:\n      enabled: true\n");
  const Skeleton& sk = humanml3d_skeleton();
  std::mt19937_64 rng(13);
  std::vector<ControlTask> tasks;
  for (int i = 0; i < 4; ++i) {
    ControlTask t;
    t.id = "kin" + std::to_string(i);
    t.caption = "a person walks forward";
    t.length = 20 - i;
    t.source = random_motion(rng, t.length, sk);
    random_observation({i % 2 ? "trajectory" : "keyframe"}, rng, t.length, sk, t.source, false, &t.spec);
    tasks.push_back(t);
  }
  auto gen = make_generator(fmt::format("generator:\n  type: projflow\n  prior: {{run_dir: {}}}\n"
                                        "  sampler: {{steps: 8, batch_size: 4}}\n",
                                        (dir.path / "prior").string()));
  GeneratedMotions a = gen->generate(tasks, 5), b = gen->generate(tasks, 5);
  CHECK(torch::equal(a.world, b.world));  // the structured noise is drawn from the seeded generator
  for (size_t i = 0; i < tasks.size(); ++i) {
    auto m = sample_of(a, static_cast<int>(i), tasks[i].length);
    CHECK(hard_residual(tasks[i].spec, tasks[i].length, tasks[i].source, m.data()) <= 1e-4);
  }
}
