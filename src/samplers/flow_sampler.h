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

struct FlowSamplerConfig : Config {
  int steps = 99;           // Euler updates over linspace(0, 1, steps + 1) (reference-facts §3: 100 points)
  double cfg_scale = 2.5;   // v = v_u + s (v_c - v_u)
  int batch_size = 32;      // motions per network call (the CFG forward doubles it)
  void visit(FieldVisitor& v) override {
    v("steps", steps, "ODE updates; the time grid is linspace(0, 1, steps + 1)", in_range(1, 10000));
    v("cfg_scale", cfg_scale, "classifier-free guidance scale s (1 = conditional only, 0 = unconditional)",
      in_range(0.0, 100.0));
    v("batch_size", batch_size, "motions per network call", at_least(1));
  }
};

// What a step update sees. t_k = grid[index], x = x_k, v = guided velocity at (x_k, t_k).
struct FlowStep {
  int index = 0;       // k in 0 .. steps-1
  int steps = 0;
  double t = 0, t_next = 0;
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
