// DNO baseline: batched A x through index tensors, the learning-rate schedule, the
// decorrelation penalty, loss decrease and residual reduction on a random-weight
// prior, determinism, and the `generator: {type: dno}` component.
#include <catch2/catch.hpp>

#include <random>

#include "control/control_task.h"
#include "core/error.h"
#include "samplers/dno.h"
#include "models/flow_prior_test_util.h"
#include "samplers/motion_generator.h"
#include "samplers/task_observation.h"
#include "test_util.h"
#include "samplers/generator_test_util.h"

using namespace mc;
using namespace mc::test;


TEST_CASE("A x through index tensors equals the Eigen sparse product, per sample", "[dno]") {
  std::vector<ControlTask> tasks = {
      make_task("a", 20,
                "- {type: keyframe, joints: [0, 20], frames: [1, 7], from_source: true}\n"
                "- {type: camera_2d, joints: [15], camera: {scale: 1.1, pitch_deg: 20, yaw_deg: 30}, "
                "from_source: true, variance: 0.1}\n",
                1),
      make_task("b", 30,
                "- {type: trajectory, joints: [pelvis], axes: xz, frames: {start: 0, stop: 30, step: 3}, "
                "from_source: true}\n"
                "- {type: relative, joints: [20, 21], frames: [4, 5], from_source: true}\n",
                2),
      make_task("c", 25, "", 3),
  };
  std::array<double, 3> scale{0.5, 0.4, 0.8}, offset{0.0, 0.9, 0.1};
  auto obs = model_observations(tasks, humanml3d_skeleton(), scale, offset);
  REQUIRE(obs.size() == 3);
  CHECK(obs[2].rows() == 0);
  const int64_t T = 32, J = 22;
  std::vector<const LinearObservation*> ptrs{&obs[0], &obs[1], &obs[2]};
  BatchedObservation bo = batch_observations(ptrs, T, J);
  REQUIRE(bo.rows() == obs[0].rows() + obs[1].rows());
  torch::manual_seed(3);
  auto x = torch::randn({3, T, J, 3});
  auto ax = bo.apply(x);
  auto res = bo.residual(x);
  int64_t r0 = 0;
  for (int b = 0; b < 3; ++b) {
    Eigen::VectorXd xb(obs[b].dim());
    auto xa = x.accessor<float, 4>();
    for (int f = 0; f < obs[b].frames; ++f)
      for (int j = 0; j < J; ++j)
        for (int c = 0; c < 3; ++c) xb[LinearObservation::index(f, j, c, J)] = xa[b][f][j][c];
    Eigen::VectorXd ref = obs[b].A * xb;
    for (int r = 0; r < obs[b].rows(); ++r) {
      CHECK(ax[r0 + r].item<double>() == Approx(ref[r]).margin(1e-4));
      CHECK(res[r0 + r].item<double>() == Approx(ref[r] - obs[b].y[r]).margin(1e-4));
      CHECK(bo.sample[r0 + r].item<int64_t>() == b);
    }
    r0 += obs[b].rows();
  }
  // The model-space observation means the same thing as the world one.
  auto world = x * torch::tensor({0.5f, 0.4f, 0.8f}) + torch::tensor({0.0f, 0.9f, 0.1f});
  auto wobs = compile(tasks[1].spec, 30, humanml3d_skeleton(), tasks[1].source.data());
  Eigen::VectorXd xw(wobs.dim());
  auto wa = world.accessor<float, 4>();
  for (int f = 0; f < 30; ++f)
    for (int j = 0; j < J; ++j)
      for (int c = 0; c < 3; ++c) xw[LinearObservation::index(f, j, c, J)] = wa[1][f][j][c];
  Eigen::VectorXd wres = wobs.A * xw - wobs.y;
  for (int r = 0; r < wobs.rows(); ++r)
    CHECK(res[obs[0].rows() + r].item<double>() == Approx(wres[r]).margin(1e-4));
  // Per-sample mean |residual|; a sample without rows scores 0.
  auto per = bo.mean_abs_residual(x);
  CHECK(per[0].item<double>() == Approx(res.narrow(0, 0, obs[0].rows()).abs().mean().item<double>()).epsilon(1e-5));
  CHECK(per[2].item<double>() == 0.0);
  // Gradients flow through the index form.
  auto xg = x.clone().set_requires_grad(true);
  bo.mean_abs_residual(xg).sum().backward();
  CHECK(xg.grad()[2].abs().sum().item<double>() == 0.0);
  CHECK(xg.grad()[0].abs().sum().item<double>() > 0.0);
}

TEST_CASE("DNO learning rate: linear warm-up then cosine decay", "[dno]") {
  DnoConfig c;
  c.opt_steps = 300;
  c.warmup = 50;
  c.lr = 5e-2;
  CHECK(dno_lr(c, 0) == Approx(5e-2 / 50));
  CHECK(dno_lr(c, 24) == Approx(5e-2 * 25 / 50));
  CHECK(dno_lr(c, 49) == Approx(5e-2));
  CHECK(dno_lr(c, 50) == Approx(5e-2));
  CHECK(dno_lr(c, 50 + 249 / 2) == Approx(5e-2 * 0.5 * (1 + std::cos(M_PI * (249 / 2) / 249.0))));
  CHECK(dno_lr(c, 299) == Approx(0.0).margin(1e-12));
  c.min_lr_ratio = 0.1;
  CHECK(dno_lr(c, 299) == Approx(5e-3));
  for (int k = 51; k < 300; ++k) CHECK(dno_lr(c, k) <= dno_lr(c, k - 1) + 1e-15);
}

TEST_CASE("DNO decorrelation penalty: near zero for white noise, large for smooth noise", "[dno]") {
  torch::manual_seed(1);
  auto white = torch::randn({1, 128, 22, 3});
  // Every frame repeated: neighbouring frames perfectly correlated.
  auto smooth = torch::randn({1, 64, 22, 3}).repeat_interleave(2, 1);
  double pw = decorrelation_penalty(white, {128}, 2).item<double>();
  double ps = decorrelation_penalty(smooth, {128}, 2).item<double>();
  INFO("white " << pw << " smooth " << ps);
  CHECK(pw < 0.01);
  CHECK(ps > 0.2);  // lag-1 correlation 1/2 at the finest scale: (1/2)^2
  // Only valid frames count: garbage past the length changes nothing.
  auto padded = torch::cat({white, torch::ones({1, 20, 22, 3}) * 5}, 1);
  CHECK(decorrelation_penalty(padded, {128}, 2).item<double>() == Approx(pw));
}

TEST_CASE("DNO reduces the constraint residual on a random-weight prior, deterministic in the seed", "[dno]") {
  TempDir dir("dno");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers);
  FlowPrior prior = FlowPrior::load(dir.path.string());
  std::vector<ControlTask> tasks = {
      make_task("k", 30, "- {type: keyframe, joints: [0], frames: [3, 15, 27], from_source: true}\n", 11,
                "a person walks"),
      make_task("t", 24, "- {type: trajectory, joints: [l_wrist], axes: xz, from_source: true}\n", 12,
                "a person jumps forward"),
      make_task("m", 36,
                "- {type: keyframe, joints: [10, 11, 15], frames: [0, 35], from_source: true}\n"
                "- {type: trajectory, joints: [pelvis], axes: y, frames: {start: 0, stop: 36, step: 4}, "
                "from_source: true}\n",
                13, "a person jumps"),
  };
  auto obs = model_observations(prior, tasks);
  std::vector<std::string> caps;
  std::vector<int> lens;
  for (auto& t : tasks) {
    caps.push_back(t.caption);
    lens.push_back(t.length);
  }
  DnoConfig c;
  c.opt_steps = 40;
  c.warmup = 8;
  c.batch_size = 3;
  DnoResult r = dno_generate(prior, caps, lens, obs, c, 7);
  REQUIRE(r.loss_history.size() == 40);
  REQUIRE(r.world.sizes() == torch::IntArrayRef({3, 36, 22, 3}));
  double first = r.loss_history.front(), last = r.loss_history.back();
  INFO("loss " << first << " -> " << last << "; residual " << r.initial_residual << " -> " << r.final_residual);
  CHECK(first == Approx(r.initial_residual.mean().item<double>()).epsilon(1e-4));
  CHECK(last < 0.5 * first);
  for (int b = 0; b < 3; ++b) CHECK(r.final_residual[b].item<double>() < 0.3 * r.initial_residual[b].item<double>());
  // The residual reported is the world one of the returned motions.
  for (int b = 0; b < 3; ++b) {
    auto wobs = compile(tasks[b].spec, lens[b], prior.skeleton(), tasks[b].source.data());
    Eigen::VectorXd xw(wobs.dim());
    auto wa = r.world.accessor<float, 4>();
    for (int f = 0; f < lens[b]; ++f)
      for (int j = 0; j < 22; ++j)
        for (int k = 0; k < 3; ++k) xw[LinearObservation::index(f, j, k, 22)] = wa[b][f][j][k];
    CHECK((wobs.A * xw - wobs.y).cwiseAbs().mean() == Approx(r.final_residual[b].item<double>()).epsilon(1e-3));
    // zero past the length
    if (lens[b] < 36) CHECK(r.world[b].narrow(0, lens[b], 36 - lens[b]).abs().sum().item<double>() == 0.0);
  }

  {  // same seed, same motions; batch size does not matter; another seed differs
    c.opt_steps = 8;
    DnoResult a = dno_generate(prior, caps, lens, obs, c, 21);
    DnoResult b = dno_generate(prior, caps, lens, obs, c, 21);
    CHECK(torch::equal(a.world, b.world));
    c.batch_size = 1;
    DnoResult one = dno_generate(prior, caps, lens, obs, c, 21);
    CHECK(torch::allclose(a.world, one.world, 1e-4, 1e-4));
    DnoResult other = dno_generate(prior, caps, lens, obs, c, 22);
    CHECK_FALSE(torch::allclose(a.world, other.world, 1e-3, 1e-3));
  }
  {  // the decorrelation penalty changes the optimum but the residual still falls
    c.opt_steps = 16;
    c.warmup = 4;
    c.decorrelation_weight = 0.0;
    DnoResult plain = dno_generate(prior, caps, lens, obs, c, 5);
    c.decorrelation_weight = 50.0;
    DnoResult decor = dno_generate(prior, caps, lens, obs, c, 5);
    CHECK_FALSE(torch::equal(plain.world, decor.world));
    CHECK(decor.final_residual.mean().item<double>() < decor.initial_residual.mean().item<double>());
  }
}

TEST_CASE("generator dno: built from config, one world motion per task, clear task errors", "[dno]") {
  TempDir dir("dno_gen");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers);
  GeneratorFile job;
  parse_config(config_from_string(fmt::format("generator:\n  type: dno\n  prior:\n    run_dir: {}\n"
                                              "  opt_steps: 6\n  ode_steps: 4\n  warmup: 2\n",
                                              dir.path.string())),
               job);
  auto gen = build_generator(job.generator);
  CHECK(gen->describe().find("DNO") != std::string::npos);
  std::vector<ControlTask> tasks = {
      make_task("p", 20, "- {type: keyframe, joints: [0], frames: [2, 9], from_source: true}\n", 4),
      make_task("q", 12, "- {type: planar_root, from_source: true}\n", 5),
  };
  GeneratedMotions g = gen->generate(tasks, 3);
  CHECK(g.world.sizes() == torch::IntArrayRef({2, 20, 22, 3}));
  CHECK(g.lengths == std::vector<int>{20, 12});
  CHECK(torch::isfinite(g.world).all().item<bool>());
  REQUIRE_FALSE(g.notes.empty());
  GeneratedMotions again = gen->generate(tasks, 3);
  CHECK(torch::equal(g.world, again.world));

  tasks[1].source.resize(10);
  std::string e = user_error_of([&] { gen->generate(tasks, 3); });
  CHECK(e.find("task 'q'") != std::string::npos);
  CHECK(e.find("source clip") != std::string::npos);

  GeneratorFile bad;
  std::string pe = user_error_of([&] { parse_config(config_from_string("generator:\n  type: dno\n  opt_steps: 3\n"), bad); });
  CHECK(pe.find("prior.run_dir") != std::string::npos);
}

TEST_CASE("DNO refuses a prior whose source noise is not N(0, I)", "[dno][kinematic]") {
  TempDir dir("dno_kin");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers,
                         "  prediction: clean\n  kinematic_head:\n    enabled: true\n    noise:\n      enabled: true\n");
  FlowPrior prior = FlowPrior::load(dir.path.string());
  std::vector<ControlTask> tasks = {
      make_task("k", 20, "- {type: keyframe, joints: [0], frames: [3, 15], from_source: true}\n", 11, "a person walks")};
  auto obs = model_observations(prior, tasks);
  DnoConfig c;
  c.opt_steps = 2;
  auto msg = user_error_of([&] { dno_generate(prior, {"a person walks"}, {20}, obs, c, 7); });
  CHECK(msg.find("kinematic") != std::string::npos);
}
