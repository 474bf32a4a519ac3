// The Euler sampler loop over a loaded flow prior.
#include "samplers/flow_sampler.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <fstream>

#include "core/error.h"

namespace mc {

// ---------------------------------------------------------------- sampling

std::string FlowSamplerConfig::describe_cfg() const {
  if (cfg_interval.omitted_from_dump()) return fmt::format("cfg {}", cfg_scale);
  return fmt::format("cfg {} on t in [{}, {})", cfg_scale, cfg_interval.start, cfg_interval.end);
}

torch::Tensor FlowStep::fresh_noise() const {
  if (prior) return prior->net()->draw_noise(mask, x.size(2), *generator);
  return torch::randn(x.sizes(), *generator, torch::TensorOptions());
}

FlowSampleResult sample_flow(const FlowPrior& prior, const std::vector<std::string>& captions,
                             const std::vector<int>& lengths, const FlowSamplerConfig& cfg, uint64_t seed,
                             FlowStepper* stepper) {
  torch::NoGradGuard ng;
  const int64_t N = captions.size(), J = prior.num_joints();
  if (lengths.size() != captions.size())
    fail("{} captions but {} lengths; give one length per caption", captions.size(), lengths.size());
  int64_t T = 1;
  for (size_t i = 0; i < lengths.size(); ++i) {
    if (lengths[i] < 1 || lengths[i] > prior.t_max())
      fail("sample {} asks for {} frames; the prior '{}' was trained on clips of 1..{} frames", i, lengths[i],
           prior.run_dir(), prior.t_max());
    T = std::max<int64_t>(T, lengths[i]);
  }
  EulerStepper euler;
  FlowStepper& step_rule = stepper ? *stepper : euler;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto noise = prior.draw_noise(std::vector<int64_t>(lengths.begin(), lengths.end()), T, gen);
  auto grid = torch::linspace(0.0, 1.0, cfg.steps + 1, torch::kFloat64);
  auto ga = grid.accessor<double, 1>();
  const auto dev = prior.device();

  FlowSampleResult out;
  out.world = torch::zeros({N, T, J, 3});
  out.lengths = lengths;
  for (int64_t s = 0; s < N; s += cfg.batch_size) {
    const int64_t B = std::min<int64_t>(cfg.batch_size, N - s);
    std::vector<std::string> caps(captions.begin() + s, captions.begin() + s + B);
    std::vector<int64_t> ids(B);
    auto mask = torch::zeros({B, T}, torch::kBool);
    for (int64_t b = 0; b < B; ++b) {
      ids[b] = s + b;
      mask[b].narrow(0, 0, lengths[s + b]).fill_(true);
    }
    mask = mask.to(dev);
    auto text = prior.encode_texts(caps);
    auto x = step_rule.begin(noise.narrow(0, s, B).to(dev), mask, ids);
    for (int k = 0; k < cfg.steps; ++k) {
      FlowStep st;
      st.index = k;
      st.steps = cfg.steps;
      st.t = ga[k];
      st.t_next = ga[k + 1];
      st.x = x;
      st.mask = mask;
      st.sample_ids = ids;
      st.generator = &gen;
      st.prior = &prior;
      st.cfg_scale = cfg.scale_at(st.t);
      st.v = prior.velocity(x, torch::full({B}, st.t, torch::TensorOptions().device(dev)), text, mask, st.cfg_scale);
      x = step_rule.step(st);
    }
    auto world = prior.denormalize(x).to(torch::kCPU) * mask.to(torch::kCPU).view({B, T, 1, 1}).to(torch::kFloat32);
    if (!torch::isfinite(world).all().item<bool>())
      fail("sampling from '{}' produced non-finite joints (samples {}..{}); nothing was written", prior.run_dir(), s,
           s + B - 1);
    out.world.narrow(0, s, B).copy_(world);
  }
  return out;
}

MotionSet to_motion_set(const FlowPrior& prior, const FlowSampleResult& r, const std::vector<std::string>& captions,
                        const std::vector<std::string>& ids) {
  MotionSet m;
  m.skeleton = prior.skeleton();
  m.fps = prior.fps();
  m.t_max = prior.t_max();
  const int64_t N = r.lengths.size(), J = prior.num_joints(), T = r.world.size(1);
  auto full = torch::zeros({N, m.t_max, J, 3});
  full.narrow(1, 0, T).copy_(r.world);
  full = full.contiguous();
  m.joints.assign(full.data_ptr<float>(), full.data_ptr<float>() + full.numel());
  m.lengths = r.lengths;
  m.ids = ids;
  m.splits.assign(N, "sample");
  for (auto& c : captions) m.captions.push_back({c});
  NormStats st;
  auto mean = prior.net()->joint_mean.to(torch::kCPU).contiguous();
  auto sd = prior.net()->joint_std.to(torch::kCPU).contiguous();
  st.joint_mean.assign(mean.data_ptr<float>(), mean.data_ptr<float>() + 3);
  st.joint_std.assign(sd.data_ptr<float>(), sd.data_ptr<float>() + 3);
  m.stats = st;
  m.clear_padding();
  return m;
}

}  // namespace mc
