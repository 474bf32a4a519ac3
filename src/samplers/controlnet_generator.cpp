// ACMDM+ControlNet as a motion generator: keyframe/trajectory items become the
// control signal; Euler sampling with separate text and control guidance.
#include "samplers/controlnet_generator.h"

#include <ATen/CPUGeneratorImpl.h>

#include <chrono>

#include "core/error.h"
#include "data/skeleton.h"
#include "samplers/motion_generator.h"
#include "samplers/task_observation.h"
#include "core/trained_runs.h"

namespace mc {

ControlTargets control_targets(const FlowPrior& base, const std::vector<ControlTask>& tasks, int64_t frames) {
  const int64_t N = tasks.size(), J = base.num_joints();
  for (const auto& t : tasks)
    for (size_t i = 0; i < t.spec.items.size(); ++i) {
      const std::string& ty = t.spec.items[i].type;
      // upper_body_edit fixes the lower body's joint positions: joint positions too.
      if (ty != "keyframe" && ty != "trajectory" && ty != "upper_body_edit")
        fail("task '{}': {} is a '{}' constraint; the ControlNet baseline only takes joint positions "
             "(keyframe, trajectory or upper_body_edit items selecting joint x/y/z), use ProjFlow or DNO for "
             "this task",
             t.id, t.spec.item_label(static_cast<int>(i)), ty);
    }
  auto obs = model_observations(base, tasks);
  ControlTargets out;
  out.target = torch::zeros({N, frames, J, 3});
  out.mask = torch::zeros({N, frames, J, 3});
  auto ta = out.target.accessor<float, 4>();
  auto ma = out.mask.accessor<float, 4>();
  for (int64_t n = 0; n < N; ++n) {
    const LinearObservation& o = obs[n];
    if (o.frames > frames) fail("task '{}' has {} frames; the batch holds {}", tasks[n].id, o.frames, frames);
    for (int r = 0; r < o.A.outerSize(); ++r) {
      int entries = 0;
      int64_t col = 0;
      double a = 0;
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(o.A, r); it; ++it) {
        ++entries;
        col = it.col();
        a = it.value();
      }
      // A keyframe/trajectory row selects one coordinate: a = the axis scale.
      if (entries != 1 || a == 0.0)
        fail("task '{}': {} does not select single joint coordinates; the ControlNet baseline only takes joint "
             "positions",
             tasks[n].id, o.item_labels[o.item_of_row[r]]);
      const int64_t f = col / (J * 3), j = (col / 3) % J, c = col % 3;
      ta[n][f][j][c] = static_cast<float>(o.y[r] / a);
      ma[n][f][j][c] = 1.0f;
    }
  }
  return out;
}

torch::Tensor sample_controlnet(const FlowControlNet& net, const std::vector<ControlTask>& tasks,
                                const ControlNetSampleConfig& cfg, uint64_t seed) {
  torch::NoGradGuard ng;
  const FlowPrior& base = net.base();
  const int64_t N = tasks.size(), J = base.num_joints();
  int64_t T = 1;
  for (const auto& t : tasks) {
    if (t.length < 1 || t.length > base.t_max())
      fail("task '{}' asks for {} frames; the prior '{}' was trained on clips of 1..{} frames", t.id, t.length,
           base.run_dir(), base.t_max());
    T = std::max<int64_t>(T, t.length);
  }
  ControlTargets ct = control_targets(base, tasks, T);
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  std::vector<int64_t> lengths;
  for (const auto& t : tasks) lengths.push_back(t.length);
  auto noise = base.draw_noise(lengths, T, gen);
  auto grid = torch::linspace(0.0, 1.0, cfg.steps + 1, torch::kFloat64);
  auto ga = grid.accessor<double, 1>();
  const auto dev = base.device();
  auto world_all = torch::zeros({N, T, J, 3});
  for (int64_t s = 0; s < N; s += cfg.batch_size) {
    const int64_t B = std::min<int64_t>(cfg.batch_size, N - s);
    std::vector<std::string> caps;
    auto mask = torch::zeros({B, T}, torch::kBool);
    for (int64_t b = 0; b < B; ++b) {
      caps.push_back(tasks[s + b].caption);
      mask[b].narrow(0, 0, tasks[s + b].length).fill_(true);
    }
    mask = mask.to(dev);
    auto signal = control_signal(ct.target.narrow(0, s, B), ct.mask.narrow(0, s, B)).to(dev);
    auto text = base.encode_texts(caps);
    auto x = noise.narrow(0, s, B).to(dev);
    for (int k = 0; k < cfg.steps; ++k) {
      auto t = torch::full({B}, ga[k], torch::TensorOptions().device(dev));
      x = x + (ga[k + 1] - ga[k]) * net.velocity(x, t, text, mask, signal, cfg.text_cfg, cfg.control_cfg);
    }
    auto world = base.denormalize(x).cpu() * mask.cpu().view({B, T, 1, 1}).to(torch::kFloat32);
    if (!torch::isfinite(world).all().item<bool>())
      fail("ControlNet sampling from '{}' produced non-finite joints (tasks {}..{})", net.run_dir(), s, s + B - 1);
    world_all.narrow(0, s, B).copy_(world);
  }
  return world_all;
}

namespace {

struct ControlNetRunSource : Config, DeclaresDependencies {
  std::string run_dir;
  std::string config;
  std::vector<std::string> overrides;
  void visit(FieldVisitor& v) override {
    v("run_dir", run_dir, "finished flow_controlnet run directory (takes precedence over config)");
    v("config", config, "its training config (when run_dir is empty), trained on demand like `motionctl train`");
    v("overrides", overrides, "key=value overrides applied to `config`");
  }
  void dependencies(DependencyVisitor& d) override { d("controlnet", run_dir, config, overrides); }
  std::string validate() const override {
    if (run_dir.empty() && config.empty())
      return "set controlnet.run_dir (a finished flow_controlnet run) or controlnet.config, e.g. "
             "configs/prior/flow_controlnet_tiny.yaml";
    return "";
  }
};

class ControlNetGenerator : public MotionGenerator {
 public:
  ControlNetGenerator(FlowControlNet net, ControlNetSampleConfig cfg) : net_(std::move(net)), cfg_(std::move(cfg)) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    auto t0 = std::chrono::steady_clock::now();
    GeneratedMotions g;
    g.world = sample_controlnet(net_, tasks, cfg_, seed);
    for (auto& t : tasks) g.lengths.push_back(t.length);
    g.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    int64_t n = 0;
    for (auto& p : net_.branch()->parameters()) n += p.numel();
    g.notes.push_back(fmt::format("ControlNet branch parameters: {}", n));
    g.stats["params"] = static_cast<double>(n);
    return g;
  }
  std::string describe() const override {
    return fmt::format("ACMDM+ControlNet {} on base {} ({} steps, text cfg {}, control cfg {})", net_.run_dir(),
                       net_.base().run_dir(), cfg_.steps, cfg_.text_cfg, cfg_.control_cfg);
  }

 private:
  FlowControlNet net_;
  ControlNetSampleConfig cfg_;
};

struct ControlNetGeneratorConfig : GeneratorConfig {
  ControlNetRunSource controlnet;
  ControlNetSampleConfig sampler;
  void visit(FieldVisitor& v) override {
    v("controlnet", controlnet, "the trained ControlNet (run_dir, or its training config trained on demand)");
    sampler.visit(v);  // steps, text_cfg, control_cfg, batch_size next to `controlnet`
  }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    const std::string dir = trained_run("controlnet", controlnet.run_dir, controlnet.config, controlnet.overrides);
    return std::make_unique<ControlNetGenerator>(FlowControlNet::load(dir, ctx.device), sampler);
  }
};

}  // namespace

MC_REGISTER_GENERATOR("flow_controlnet", ControlNetGeneratorConfig,
                      "ACMDM+ControlNet: a trained ControlNet branch on the flow prior (joint-position controls only)");

}  // namespace mc
