// DNO baseline (reference-facts §4): optimise the initial noise of the flow prior
// through a short deterministic Euler chain so the clean output meets the task's
// linear observation (masked L1), with Adam, warm-up + cosine and unit-norm gradients.
#pragma once
#include <string>
#include <vector>

#include "control/linear_observation.h"
#include "core/config.h"
#include "samplers/flow_sampler.h"

namespace mc {

struct DnoConfig : Config {
  int ode_steps = 10;        // Euler updates of the differentiable chain z -> x1
  double cfg_scale = 2.5;    // CFG inside the chain (ProjFlow's prior setting)
  int opt_steps = 500;       // the paper's runs use 300-800
  double lr = 5e-2;          // Adam peak learning rate on the noise
  int warmup = 50;           // linear warm-up steps, then cosine decay
  double min_lr_ratio = 0.0; // cosine floor (fraction of lr)
  std::vector<double> betas = {0.9, 0.999};
  bool normalize_grad = true;       // per-sample gradient scaled to unit L2 before each Adam step
  double decorrelation_weight = 0;  // DNO's multi-scale noise decorrelation penalty (0 = off)
  int decorrelation_min_frames = 2; // stop halving the time axis at this many frames
  int batch_size = 16;              // samples optimised together (results do not depend on it)
  void visit(FieldVisitor& v) override {
    v("ode_steps", ode_steps, "Euler updates of the differentiable ODE chain from noise to motion", in_range(1, 1000));
    v("cfg_scale", cfg_scale, "classifier-free guidance scale inside the chain", in_range(0.0, 100.0));
    v("opt_steps", opt_steps, "Adam steps on the initial noise (paper: 300-800)", in_range(0, 100000));
    v("lr", lr, "peak Adam learning rate on the noise", positive<double>());
    v("warmup", warmup, "linear warm-up steps (then cosine decay to min_lr_ratio * lr)", at_least(0));
    v("min_lr_ratio", min_lr_ratio, "cosine floor as a fraction of lr", in_range(0.0, 1.0));
    v("betas", betas, "Adam betas", each(in_range(0.0, 0.999999)));
    v("normalize_grad", normalize_grad, "scale each sample's noise gradient to unit L2 norm before the Adam step");
    v("decorrelation_weight", decorrelation_weight,
      "weight of DNO's noise decorrelation penalty (squared lag-1 autocorrelation over frames at every "
      "2x-downsampled scale); 0 = off", at_least(0.0));
    v("decorrelation_min_frames", decorrelation_min_frames, "the penalty stops halving the time axis here",
      at_least(1));
    v("batch_size", batch_size, "samples optimised together", at_least(1));
  }
  std::string validate() const override {
    return betas.size() == 2 ? "" : "betas needs two numbers, e.g. [0.9, 0.999]";
  }
};

// Learning rate at optimisation step `step` (0-based): lr (step+1)/warmup during
// warm-up, then cosine from lr down to min_lr_ratio * lr at the last step.
double dno_lr(const DnoConfig& c, int step);

// The differentiable chain: Euler over linspace(0, 1, steps + 1) with CFG from x0 = z,
// gradients flowing through every network call. z [B, T, J, 3] normalised.
torch::Tensor dno_chain(const FlowPrior& prior, const torch::Tensor& z, const torch::Tensor& text,
                        const torch::Tensor& mask, int steps, double cfg_scale);

// DNO's decorrelation penalty per sample, [B]: sum over scales of the squared mean
// lag-1 (circular) product of the noise along frames, restricted to each sample's
// valid frames, halving the time axis (2-frame average; an odd last frame is
// dropped) until at most `min_frames` remain.
torch::Tensor decorrelation_penalty(const torch::Tensor& z, const std::vector<int>& lengths, int min_frames);

struct DnoResult {
  torch::Tensor world;                // [N, T, J, 3] world metres, CPU, zero past each length
  std::vector<int> lengths;
  std::vector<double> loss_history;   // per optimisation step: mean over samples of the task loss (before the step)
  torch::Tensor initial_residual;     // [N] mean |A x - y| (metres) of the chain from the unoptimised noise
  torch::Tensor final_residual;       // [N] the same for the returned motions
};

// One motion per caption with obs[i] (model units, see model_observations) as its
// constraint. Noise is drawn up front for all N from a generator seeded with
// `seed`, and every sample's update depends on its own loss only, so results do not
// depend on batch_size. UserError on non-finite losses or outputs and on lengths
// outside 1..t_max.
DnoResult dno_generate(const FlowPrior& prior, const std::vector<std::string>& captions,
                       const std::vector<int>& lengths, const std::vector<LinearObservation>& obs,
                       const DnoConfig& cfg, uint64_t seed);

}  // namespace mc
