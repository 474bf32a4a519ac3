// The Euler ODE sampler of a flow prior (models/flow_prior.h) with a replaceable
// per-step update (ProjFlow's hook).
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"
#include "models/flow_prior.h"

namespace mc {

// Where on the time grid CFG extrapolates (ours, issue 13; Kynkaanniemi et al. 2024,
// "Applying guidance in a limited interval"). Outside [start, end) the step uses the
// conditional velocity alone (s = 1). Why: on our flow prior the extrapolation
// v_u + s (v_c - v_u) is what takes foot skating from 2.7x to 5.0x ground truth and
// bone-length std from 4.7 to 9.5 mm (docs/choices.md, "The CFG scale is the
// trade-off"), and the two come from different times: guidance after t ~ 0.7 drifts
// the bones, guidance before t ~ 0.3 raises skating but also buys most of the FID
// ("Guidance in a limited interval"). Its own section, absent from
// the dump at the default [0, 1) (guidance on every step, as ProjFlow), so
// existing runs keep their names.
struct CfgIntervalConfig : Config {
  double start = 0.0;
  double end = 1.0;
  void visit(FieldVisitor& v) override {
    v("start", start, "first time t (0 = noise, 1 = data) at which cfg_scale applies", in_range(0.0, 1.0));
    v("end", end, "cfg_scale applies while t < end; later steps use the conditional velocity (s = 1)",
      in_range(0.0, 1.0));
  }
  std::string validate() const override {
    return start < end ? std::string()
                       : fmt::format("start ({}) must be below end ({}); [0, 1] guides every step", start, end);
  }
  bool omitted_from_dump() const override { return start == 0.0 && end == 1.0; }
  bool contains(double t) const { return t >= start && t < end; }
};

struct FlowSamplerConfig : Config {
  int steps = 99;           // Euler updates over linspace(0, 1, steps + 1) (reference-facts §3: 100 points)
  double cfg_scale = 2.5;   // v = v_u + s (v_c - v_u)
  CfgIntervalConfig cfg_interval;
  int batch_size = 32;      // motions per network call (the CFG forward doubles it)
  void visit(FieldVisitor& v) override {
    v("steps", steps, "ODE updates; the time grid is linspace(0, 1, steps + 1)", in_range(1, 10000));
    v("cfg_scale", cfg_scale, "classifier-free guidance scale s (1 = conditional only, 0 = unconditional)",
      in_range(0.0, 100.0));
    v("cfg_interval", cfg_interval, "the times at which cfg_scale applies (default every step)");
    v("batch_size", batch_size, "motions per network call", at_least(1));
  }
  // The guidance scale of the step that starts at time t.
  double scale_at(double t) const { return cfg_interval.contains(t) ? cfg_scale : 1.0; }
  // "cfg 2.5" or "cfg 2.5 on t in [0, 0.6)": for generators' describe().
  std::string describe_cfg() const;
};

// What a step update sees. t_k = grid[index], x = x_k, v = guided velocity at (x_k, t_k).
struct FlowStep {
  int index = 0;       // k in 0 .. steps-1
  int steps = 0;
  double t = 0, t_next = 0;
  double cfg_scale = 1.0;  // the CFG scale v was guided with (FlowSamplerConfig::scale_at(t))
  torch::Tensor x, v;  // [B, T, J, 3] normalised
  torch::Tensor mask;  // [B, T] valid frames
  std::vector<int64_t> sample_ids;  // which requested samples the batch rows are (for per-sample constraints)
  at::Generator* generator = nullptr;  // the sampler's seeded generator (CPU), for extra noise
  // Fresh source noise x0 [B, T, J, 3] for this batch from `generator`: the prior's
  // (FlowPrior::draw_noise), N(0, I) when unset.
  torch::Tensor fresh_noise() const;
  const FlowPrior* prior = nullptr;
  // Endpoint predictions of the straight path through (x, t) with velocity v.
  torch::Tensor x1_hat() const { return x + (1 - t) * v; }
  torch::Tensor x0_hat() const { return x - t * v; }
};

// The per-step update rule; ProjFlow replaces Euler's with its projection and recomposition.
class FlowStepper {
 public:
  virtual ~FlowStepper() = default;
  // Called once per batch before the first step with x_0 (noise) and the mask; may
  // return a modified x_0.
  virtual torch::Tensor begin(const torch::Tensor& x0, const torch::Tensor& mask,
                              const std::vector<int64_t>& sample_ids) {
    (void)mask;
    (void)sample_ids;
    return x0;
  }
  virtual torch::Tensor step(const FlowStep& s) = 0;  // returns x_{k+1}
};

// x_{k+1} = x_k + (t_{k+1} - t_k) v: the explicit Euler step of eq. (1).
class EulerStepper : public FlowStepper {
 public:
  torch::Tensor step(const FlowStep& s) override { return s.x + (s.t_next - s.t) * s.v; }
};

struct FlowSampleResult {
  torch::Tensor world;        // [N, T, J, 3] world metres (CPU), zero past each length; T = max length
  std::vector<int> lengths;   // [N]
};

// Samples one motion per caption. Noise for all N samples is drawn up front from a
// generator seeded with `seed`, so a sample does not depend on batch_size. `stepper`
// null = Euler. UserError on non-finite output or a length outside 1..t_max.
FlowSampleResult sample_flow(const FlowPrior& prior, const std::vector<std::string>& captions,
                             const std::vector<int>& lengths, const FlowSamplerConfig& cfg, uint64_t seed,
                             FlowStepper* stepper = nullptr);

// The sample set as a motion file body: split "sample", captions = prompts, the
// prior's skeleton/fps/t_max and stats. Provenance is left to the caller.
MotionSet to_motion_set(const FlowPrior& prior, const FlowSampleResult& r, const std::vector<std::string>& captions,
                        const std::vector<std::string>& ids);

}  // namespace mc
