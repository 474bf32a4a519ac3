// DNO: noise optimisation through a differentiable 10-step Euler chain of the flow
// prior, and the `generator: {type: dno}` component.
#include "samplers/dno.h"

#include <ATen/CPUGeneratorImpl.h>

#include <chrono>
#include <cmath>
#include <iostream>

#include "core/error.h"
#include "samplers/motion_generator.h"
#include "models/prior_source.h"
#include "samplers/task_observation.h"

namespace mc {

double dno_lr(const DnoConfig& c, int step) {
  if (step < c.warmup) return c.lr * (step + 1) / static_cast<double>(c.warmup);
  const int span = c.opt_steps - c.warmup;
  if (span <= 1) return c.lr;
  const double p = std::min(1.0, (step - c.warmup) / static_cast<double>(span - 1));
  const double floor = c.min_lr_ratio * c.lr;
  return floor + (c.lr - floor) * 0.5 * (1.0 + std::cos(M_PI * p));
}

torch::Tensor dno_chain(const FlowPrior& prior, const torch::Tensor& z, const torch::Tensor& text,
                        const torch::Tensor& mask, int steps, double cfg_scale) {
  const int64_t B = z.size(0);
  auto null = prior.null_texts(B);
  auto text2 = torch::cat({text, null});
  auto mask2 = torch::cat({mask, mask});
  auto x = z;
  for (int k = 0; k < steps; ++k) {
    const double t = static_cast<double>(k) / steps, dt = 1.0 / steps;
    auto tt = torch::full({2 * B}, t, torch::TensorOptions().device(z.device()));
    auto v2 = prior.raw_velocity(torch::cat({x, x}), tt, text2, mask2);
    auto vc = v2.narrow(0, 0, B), vu = v2.narrow(0, B, B);
    x = x + dt * (vu + cfg_scale * (vc - vu));  // eq. (1), explicit Euler with CFG
  }
  return x;
}

torch::Tensor decorrelation_penalty(const torch::Tensor& z, const std::vector<int>& lengths, int min_frames) {
  const int64_t B = z.size(0);
  std::vector<torch::Tensor> out;
  for (int64_t b = 0; b < B; ++b) {
    auto n = z[b].narrow(0, 0, lengths[b]).reshape({lengths[b], -1});  // [T, C]
    auto loss = torch::zeros({}, z.options());
    while (true) {
      // Correlated neighbouring frames are what lets the optimiser hide structure in
      // the noise; this keeps it close to white at every temporal scale.
      loss = loss + (n * torch::roll(n, 1, 0)).mean().pow(2);
      const int64_t T = n.size(0);
      if (T <= min_frames || T < 2) break;
      n = n.narrow(0, 0, T / 2 * 2).reshape({T / 2, 2, -1}).mean(1);
    }
    out.push_back(loss);
  }
  return torch::stack(out);
}

DnoResult dno_generate(const FlowPrior& prior, const std::vector<std::string>& captions,
                       const std::vector<int>& lengths, const std::vector<LinearObservation>& obs,
                       const DnoConfig& cfg, uint64_t seed) {
  const int64_t N = captions.size(), J = prior.num_joints();
  if (lengths.size() != captions.size() || obs.size() != captions.size())
    fail("DNO: {} captions, {} lengths and {} observations; give one of each per sample", captions.size(),
         lengths.size(), obs.size());
  int64_t T = 1;
  for (size_t i = 0; i < lengths.size(); ++i) {
    if (lengths[i] < 1 || lengths[i] > prior.t_max())
      fail("DNO: sample {} asks for {} frames; the prior '{}' was trained on clips of 1..{} frames", i, lengths[i],
           prior.run_dir(), prior.t_max());
    T = std::max<int64_t>(T, lengths[i]);
  }
  if (prior.net()->kinematic_noise)
    fail("DNO: the flow prior '{}' draws kinematic source noise (model.kinematic_head.noise), and DNO's noise "
         "regulariser assumes N(0, I); use a prior with absolute noise",
         prior.run_dir());
  const auto dev = prior.device();
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto noise = torch::randn({N, T, J, 3}, gen, torch::TensorOptions());

  DnoResult res;
  res.lengths = lengths;
  res.world = torch::zeros({N, T, J, 3});
  res.loss_history.assign(cfg.opt_steps, 0.0);
  res.initial_residual = torch::zeros({N});
  res.final_residual = torch::zeros({N});
  for (int64_t s = 0; s < N; s += cfg.batch_size) {
    const int64_t B = std::min<int64_t>(cfg.batch_size, N - s);
    std::vector<std::string> caps(captions.begin() + s, captions.begin() + s + B);
    std::vector<int> lens(lengths.begin() + s, lengths.begin() + s + B);
    std::vector<const LinearObservation*> ob;
    auto mask = torch::zeros({B, T}, torch::kBool);
    for (int64_t b = 0; b < B; ++b) {
      ob.push_back(&obs[s + b]);
      mask[b].narrow(0, 0, lens[b]).fill_(true);
    }
    mask = mask.to(dev);
    BatchedObservation A = batch_observations(ob, T, J, dev);
    auto text = prior.encode_texts(caps);

    auto z = noise.narrow(0, s, B).clone().to(dev).set_requires_grad(true);
    torch::optim::Adam opt({z}, torch::optim::AdamOptions(cfg.lr).betas({cfg.betas[0], cfg.betas[1]}));
    {
      torch::NoGradGuard ng;
      res.initial_residual.narrow(0, s, B).copy_(
          A.mean_abs_residual(dno_chain(prior, z, text, mask, cfg.ode_steps, cfg.cfg_scale)).cpu());
    }
    for (int k = 0; k < cfg.opt_steps; ++k) {
      auto x1 = dno_chain(prior, z, text, mask, cfg.ode_steps, cfg.cfg_scale);
      // Masked L1 over each sample's rows (metres); summing over samples keeps each
      // sample's gradient its own.
      auto task = A.mean_abs_residual(x1);
      auto loss = task.sum();
      if (cfg.decorrelation_weight > 0)
        loss = loss + cfg.decorrelation_weight * decorrelation_penalty(z, lens, cfg.decorrelation_min_frames).sum();
      const double lv = loss.item<double>();
      if (!std::isfinite(lv))
        fail("DNO: the loss became {} at optimisation step {} (samples {}..{}) with prior '{}'; lower lr or "
             "check the prior",
             lv, k, s, s + B - 1, prior.run_dir());
      res.loss_history[k] += task.sum().item<double>() / N;
      auto g = torch::autograd::grad({loss}, {z})[0];
      if (cfg.normalize_grad) {
        auto norm = g.reshape({B, -1}).norm(2, 1).clamp_min(1e-12).view({B, 1, 1, 1});
        g = g / norm;
      }
      z.mutable_grad() = g.detach();
      for (auto& pg : opt.param_groups()) static_cast<torch::optim::AdamOptions&>(pg.options()).lr(dno_lr(cfg, k));
      opt.step();
    }
    torch::NoGradGuard ng;
    auto x1 = dno_chain(prior, z, text, mask, cfg.ode_steps, cfg.cfg_scale);
    res.final_residual.narrow(0, s, B).copy_(A.mean_abs_residual(x1).cpu());
    auto world = prior.denormalize(x1).cpu() * mask.cpu().view({B, T, 1, 1}).to(torch::kFloat32);
    if (!torch::isfinite(world).all().item<bool>())
      fail("DNO: prior '{}' produced non-finite joints for samples {}..{}", prior.run_dir(), s, s + B - 1);
    res.world.narrow(0, s, B).copy_(world);
  }
  return res;
}

// ---------------------------------------------------------------- generator

namespace {

class DnoGenerator : public MotionGenerator {
 public:
  DnoGenerator(FlowPrior prior, DnoConfig cfg) : prior_(std::move(prior)), cfg_(std::move(cfg)) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    auto obs = model_observations(prior_, tasks);
    std::vector<std::string> caps;
    std::vector<int> lens;
    for (auto& t : tasks) {
      caps.push_back(t.caption);
      lens.push_back(t.length);
    }
    auto t0 = std::chrono::steady_clock::now();
    DnoResult r = dno_generate(prior_, caps, lens, obs, cfg_, seed);
    GeneratedMotions g;
    g.world = r.world;
    g.lengths = r.lengths;
    g.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!tasks.empty())
      g.notes.push_back(fmt::format("mean |A x - y| (m): {:.4f} from the initial noise, {:.4f} after {} steps",
                                    r.initial_residual.mean().item<double>(), r.final_residual.mean().item<double>(),
                                    cfg_.opt_steps));
    return g;
  }
  std::string describe() const override {
    return fmt::format("DNO on flow prior {} ({} opt steps, lr {}, {} ODE steps, cfg {}, decorrelation {})",
                       prior_.run_dir(), cfg_.opt_steps, cfg_.lr, cfg_.ode_steps, cfg_.cfg_scale,
                       cfg_.decorrelation_weight);
  }

 private:
  FlowPrior prior_;
  DnoConfig cfg_;
};

struct DnoGeneratorConfig : GeneratorConfig {
  PriorSourceConfig prior;
  DnoConfig dno;
  void visit(FieldVisitor& v) override {
    v("prior", prior, "the flow prior (run_dir, or a training config trained on demand)");
    dno.visit(v);  // the DNO hyperparameters sit next to `prior`
  }
  std::string validate() const override { return dno.validate(); }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    return std::make_unique<DnoGenerator>(load_flow_prior(prior, ctx.device), dno);
  }
};

}  // namespace

MC_REGISTER_GENERATOR("dno", DnoGeneratorConfig,
                      "DNO: initial-noise optimisation through a 10-step Euler chain of the flow prior");

}  // namespace mc
