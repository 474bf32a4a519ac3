// `motionctl bench projflow`: what ProjFlow's projection costs on top of plain
// sampling at 196 frames, structured vs dense solves, and (when available) DNO.
#include <chrono>
#include <iostream>
#include <random>

#include "bench/bench.h"
#include "control/control_task.h"
#include "control/projection_solver.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "samplers/dno.h"
#include "samplers/projflow.h"
#include "samplers/task_observation.h"

namespace mc {

namespace {
using Clock = std::chrono::steady_clock;
double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// A plausible-looking [T, J, 3] motion: rest pose on a straight walk, small sway.
std::vector<float> walk_motion(const Skeleton& sk, int T, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n(0.0, 0.02);
  auto rest = sk.rest_pose();
  const int J = sk.num_joints();
  std::vector<float> m(static_cast<size_t>(T) * J * 3);
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < J; ++j)
      for (int c = 0; c < 3; ++c) {
        double root = c == 1 ? 0.9 : c == 2 ? 0.05 * t : 0.05 * std::sin(0.3 * t);
        m[(static_cast<size_t>(t) * J + j) * 3 + c] = static_cast<float>(root + rest[j][c] + n(rng));
      }
  return m;
}

// The fixture's floor convention: the lowest joint of the clip at y = 0, so a floor
// under the toes never contradicts keyframes taken from the clip.
void lift_to_floor(std::vector<float>& m) {
  float lowest = INFINITY;
  for (size_t i = 1; i < m.size(); i += 3) lowest = std::min(lowest, m[i]);
  for (size_t i = 1; i < m.size(); i += 3) m[i] -= lowest;
}

ControlTask keyframe_task(const Skeleton& sk, int T, int every, uint64_t seed) {
  ControlTask t;
  t.id = fmt::format("bench{}", seed);
  t.caption = "a person walks forward";
  t.length = T;
  t.source = walk_motion(sk, T, seed);
  ConstraintItem it;
  it.type = "keyframe";
  it.name = "all joints";
  for (int j = 0; j < sk.num_joints(); ++j) it.joints.push_back(JointRef{j, ""});
  it.frames.kind = FrameSelection::Kind::range;
  it.frames.start = 0;
  it.frames.stop = T;
  it.frames.step = every;
  it.from_source = true;
  t.spec.items = {it};
  t.spec.source = "bench";
  return t;
}
}  // namespace

// ProjFlow's projection time per step with inequality rows beside the same
// equality rows, on one sampling run each (same prior, tasks and seed).
void bench_inequalities(const ProjflowBenchOptions& o, FlowPrior& prior, std::ostream& out) {
  const Skeleton& sk = prior.skeleton();
  const int T = o.frames;
  FlowSamplerConfig sc;
  sc.steps = o.steps;
  sc.batch_size = o.samples;
  std::vector<ControlTask> tasks;
  for (int i = 0; i < o.samples; ++i) {
    ControlTask t = keyframe_task(sk, T, o.keyframe_every, 300 + i);
    lift_to_floor(t.source);
    tasks.push_back(std::move(t));
  }
  std::vector<std::string> captions(o.samples, tasks[0].caption);
  std::vector<int> lengths(o.samples, T);
  ConstraintItem floor;
  floor.type = "floor";
  floor.name = "toes above the floor";
  ConstraintItem speed;
  speed.type = "speed_limit";
  speed.name = "pelvis speed";
  speed.joints = {JointRef{0, ""}};
  speed.axes = {0, 2};
  speed.upper = {0.2};
  struct Case {
    std::string label;
    std::vector<ConstraintItem> extra;
  };
  const std::vector<Case> cases = {{"toes y >= 0 at every frame", {floor}},
                                   {"+ pelvis |dx|, |dz| <= 0.2 m/frame", {floor, speed}}};
  out << fmt::format("projection with inequality rows (ProjFlow, pseudo-observations on, {} samples x {} steps, "
                     "keyframes of all joints every {} frames):\n",
                     o.samples, o.steps, o.keyframe_every);
  ProjFlowConfig cfg;
  const KinematicMetric metric = KinematicMetric::from_config(cfg.metric, sk);
  auto run = [&](const std::vector<ControlTask>& ts, bool warm, int64_t* qps, int64_t* iters, double* worst) {
    auto obs = model_observations(prior, ts);
    ProjFlowStepper stepper(cfg, metric, obs);
    stepper.set_warm_start(warm);
    auto r = sample_flow(prior, captions, lengths, sc, 1, &stepper);
    if (qps) *qps = stepper.qp_solves();
    if (iters) *iters = stepper.qp_iterations();
    if (worst) {  // worst hard inequality violation of the output, world metres
      *worst = 0;
      for (int i = 0; i < o.samples; ++i) {
        LinearObservation w = compile(ts[i].spec, T, sk, ts[i].source.data());
        if (w.inequalities() == 0) continue;
        auto m = r.world[i].contiguous();
        Eigen::VectorXd x(w.dim());
        for (int k = 0; k < w.dim(); ++k) x[k] = m.data_ptr<float>()[k];
        *worst = std::max(*worst, (w.G * x - w.h).maxCoeff());
      }
    }
    return stepper.projection_seconds() / (static_cast<double>(o.steps) * o.samples);
  };
  const double base = run(tasks, true, nullptr, nullptr, nullptr);
  out << fmt::format("  equality rows only:                   {:8.3f} ms per projection\n", 1e3 * base);
  for (const auto& c : cases) {
    std::vector<ControlTask> ts = tasks;
    for (auto& t : ts) t.spec.items.insert(t.spec.items.end(), c.extra.begin(), c.extra.end());
    int64_t qps = 0, iters = 0;
    double worst = 0;
    const double warm = run(ts, true, &qps, &iters, &worst);
    const double cold = run(ts, false, nullptr, nullptr, nullptr);
    out << fmt::format("  {:<38} {:8.3f} ms = {:.2f}x equality-only (warm start; cold {:.2f}x); {:.1f} QPs and {:.1f} "
                       "active-set changes per projection; worst violation {:.1e} m\n",
                       c.label, 1e3 * warm, warm / base, cold / base,
                       static_cast<double>(qps) / (o.steps * o.samples),
                       static_cast<double>(iters) / (o.steps * o.samples), std::max(0.0, worst));
  }
}

void bench_projflow(const ProjflowBenchOptions& o, std::ostream& out) {
  const Skeleton& sk = humanml3d_skeleton();
  FlowPriorConfig pc;
  pc.depth = o.depth;
  pc.width = 0;  // family rule: 64 L
  pc.heads = 0;
  FlowPrior prior = FlowPrior::untrained(pc, sk, o.frames, 1);
  const int T = o.frames;
  FlowSamplerConfig sc;
  sc.steps = o.steps;
  sc.batch_size = o.samples;
  out << fmt::format("ProjFlow bench: untrained ACMDM prior depth {} (width {}), {} samples x {} frames, {} steps, "
                     "{} torch thread(s)\n",
                     o.depth, 64 * o.depth, o.samples, T, o.steps, torch::get_num_threads());
  if (o.inequalities_only) return bench_inequalities(o, prior, out);

  std::vector<ControlTask> tasks;
  for (int i = 0; i < o.samples; ++i) tasks.push_back(keyframe_task(sk, T, o.keyframe_every, 100 + i));
  std::vector<std::string> captions(o.samples, tasks[0].caption);
  std::vector<int> lengths(o.samples, T);
  auto obs = model_observations(prior, tasks);
  out << fmt::format("constraints: all {} joints x 3 axes, hard, every {} frame(s) ({} rows per sample)\n",
                     sk.num_joints(), o.keyframe_every, obs[0].rows());

  auto t0 = Clock::now();
  sample_flow(prior, captions, lengths, sc, 1);
  const double plain = seconds_since(t0);
  out << fmt::format("  unconstrained Euler:                {:8.2f} s  ({:.3f} s/sample)\n", plain, plain / o.samples);

  for (bool pseudo : {false, true}) {
    ProjFlowConfig cfg;
    cfg.pseudo_observations.enabled = pseudo;
    ProjFlowStepper stepper(cfg, KinematicMetric::from_config(cfg.metric, sk), obs);
    t0 = Clock::now();
    auto r = sample_flow(prior, captions, lengths, sc, 1, &stepper);
    const double s = seconds_since(t0);
    // exactness in world units, as a sanity check of what was timed
    double worst = 0;
    for (int i = 0; i < o.samples; ++i) {
      LinearObservation w = compile(tasks[i].spec, T, sk, tasks[i].source.data());
      auto m = r.world[i].contiguous();
      Eigen::VectorXd x(w.dim());
      for (int k = 0; k < w.dim(); ++k) x[k] = m.data_ptr<float>()[k];
      worst = std::max(worst, (w.A * x - w.y).cwiseAbs().maxCoeff());
    }
    out << fmt::format("  ProjFlow{}: {:8.2f} s  ({:.3f} s/sample) = {:.3f}x unconstrained; projections {:.2f} s; "
                       "max hard residual {:.1e} m\n",
                       pseudo ? " + pseudo-observations" : "                     ", s, s / o.samples, s / plain,
                       stepper.projection_seconds(), worst);
  }

  // DNO on the same prior and tasks: a few optimisation steps, extrapolated to the paper's count.
  if (o.dno_steps > 0) {
    DnoConfig dc;
    dc.opt_steps = o.dno_steps;
    dc.warmup = std::min(dc.warmup, std::max(1, o.dno_steps / 2));
    dc.batch_size = o.samples;
    t0 = Clock::now();
    DnoResult r = dno_generate(prior, captions, lengths, obs, dc, 1);
    const double s = seconds_since(t0);
    const double per_step = s / o.samples / o.dno_steps;
    out << fmt::format("  DNO ({} ODE steps, {} optimisation steps): {:8.2f} s  ({:.3f} s/sample/step; {:.1f} s/sample "
                       "at 500 steps); mean residual {:.3f} -> {:.3f} m\n",
                       dc.ode_steps, o.dno_steps, s, per_step, per_step * 500, r.initial_residual.mean().item<double>(),
                       r.final_residual.mean().item<double>());
  }

  // Structured vs dense solve of a full observation (every joint, axis and frame).
  out << "projection solver, full hard observation (all joints x axes x frames), one sample:\n";
  KinematicMetric metric = KinematicMetric::kinematic(sk);
  for (int frames : o.dense_frames) {
    ControlTask t = keyframe_task(sk, frames, 1, 7);
    LinearObservation full = compile(t.spec, frames, sk, t.source.data());
    Eigen::MatrixXd x = Eigen::MatrixXd::Random(full.dim(), 1);
    t0 = Clock::now();
    ProjectionSolver solver(metric);
    solver.set_observation(full);
    Eigen::MatrixXd a = solver.project(x);
    const double structured = seconds_since(t0);
    t0 = Clock::now();
    Eigen::MatrixXd b = dense_reference_projection(metric, full, x);
    const double dense = seconds_since(t0);
    out << fmt::format("  T = {:3d} (d = {:5d}): structured {:9.4f} s, dense {:9.3f} s ({:.0f}x), max difference {:.1e}\n",
                       frames, full.dim(), structured, dense, dense / std::max(structured, 1e-9),
                       (a - b).cwiseAbs().maxCoeff());
  }
  {
    ControlTask t = keyframe_task(sk, 196, 1, 7);
    LinearObservation full = compile(t.spec, 196, sk, t.source.data());
    Eigen::MatrixXd x = Eigen::MatrixXd::Random(full.dim(), 1);
    t0 = Clock::now();
    ProjectionSolver solver(metric);
    solver.set_observation(full);
    solver.project(x);
    const double first = seconds_since(t0);
    t0 = Clock::now();
    for (int r = 0; r < 10; ++r) solver.project(x);
    out << fmt::format("  T = 196 (d = {}): structured set-up + solve {:.4f} s, cached solve {:.5f} s "
                       "(the dense solve is O(d^3); time it with --dense-frames 196)\n",
                       full.dim(), first, seconds_since(t0) / 10);
  }
  if (o.inequalities) bench_inequalities(o, prior, out);
}

}  // namespace mc
