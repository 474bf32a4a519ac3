// The flow prior's reference output on a fixed input (samplers/flow_probe.h): the
// velocities through FlowPrior's own calls and the step through the sampler's
// EulerStepper, so the probe is what sample_flow computes at that step.
#include "samplers/flow_probe.h"

#include <ATen/CPUGeneratorImpl.h>

#include "core/error.h"
#include "data/text_vocab.h"

namespace mc {

FlowWeightsGroup flow_probe(const FlowPrior& prior, const FlowProbeOptions& opt) {
  torch::NoGradGuard ng;
  const int64_t B = opt.captions.size(), J = prior.num_joints();
  if (B < 1) fail("the probe needs at least one caption");
  if (opt.steps < 1 || opt.step < 0 || opt.step >= opt.steps)
    fail("probe step {} is outside the grid of {} steps (0..{})", opt.step, opt.steps, opt.steps - 1);
  const int64_t T = std::max(1, std::min(opt.frames, prior.t_max()));
  // Clip b is T - b * T/(2B) frames long: the first fills the batch, the others end
  // early so the key padding mask matters.
  std::vector<int32_t> lengths(B);
  auto mask = torch::zeros({B, T}, torch::kBool);
  for (int64_t b = 0; b < B; ++b) {
    lengths[b] = static_cast<int32_t>(std::max<int64_t>(1, T - b * T / (2 * B)));
    mask[b].narrow(0, 0, lengths[b]).fill_(true);
  }
  auto gen = at::make_generator<at::CPUGeneratorImpl>(opt.seed);
  auto x = torch::randn({B, T, J, 3}, gen, torch::TensorOptions());
  // The sampler's grid (samplers/flow_sampler.cpp): float64 linspace, t as float32 [B].
  auto grid = torch::linspace(0.0, 1.0, opt.steps + 1, torch::kFloat64);
  const double t = grid[opt.step].item<double>(), t_next = grid[opt.step + 1].item<double>();
  const auto dev = prior.device();
  auto tt = torch::full({B}, t, torch::TensorOptions().device(dev));
  auto xd = x.to(dev), md = mask.to(dev);

  auto enc = encode_captions(prior.vocab(), opt.captions, prior.config().max_words);
  auto text = prior.encode_texts(opt.captions);
  auto null_text = prior.null_texts(B);
  auto v_cond = prior.raw_velocity(xd, tt, text, md);
  auto v_uncond = prior.raw_velocity(xd, tt, null_text, md);
  auto v_cfg = prior.velocity(xd, tt, text, md, opt.cfg_scale);
  FlowStep st;
  st.cfg_scale = opt.cfg_scale;
  st.index = opt.step;
  st.steps = opt.steps;
  st.t = t;
  st.t_next = t_next;
  st.x = xd;
  st.v = v_cfg;
  st.mask = md;
  auto x_next = EulerStepper().step(st);

  FlowWeightsGroup g;
  g.name = "probe";
  g.strings = {{"captions", opt.captions}};
  g.arrays = {{"text_ids", enc.ids},
              {"text_lengths", enc.lengths},
              {"x", x},
              {"t", tt},
              {"mask", mask},
              {"lengths", torch::tensor(lengths, torch::kInt32)},
              {"text", text},
              {"null_text", null_text},
              {"v_cond", v_cond},
              {"v_uncond", v_uncond},
              {"v_cfg", v_cfg},
              {"x_next", x_next}};
  g.numbers = {{"t", t},
               {"t_next", t_next},
               {"cfg_scale", opt.cfg_scale},
               {"step", opt.step},
               {"steps", opt.steps},
               {"seed", static_cast<double>(opt.seed)}};
  g.texts = {{"about", "flow prior output on a fixed input: x [B, T, J, 3] in normalised units at flow time t, "
                       "v_cond/v_uncond = network velocity with the captions' text / the null text, v_cfg = v_uncond "
                       "+ cfg_scale (v_cond - v_uncond), x_next = x + (t_next - t) v_cfg (one Euler step)"}};
  return g;
}

}  // namespace mc
