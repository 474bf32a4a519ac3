// Sampling a trained token prior (TMD or masked, models/token_prior.h): the TMD
// transition sampler (eqs. (21)-(23)) and the MoMask-style confidence re-masking
// sampler; both decode to world joints.
#pragma once
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"
#include "models/token_prior.h"
#include "models/vq_tokenizer.h"

namespace mc {

struct TmdSamplerConfig : Config {
  int steps = 50;            // transition steps over t_k = k / steps (reference-facts §6: 32-50)
  double cfg_scale = 4.0;    // logits l_u + s (l_c - l_u)
  std::string proposal = "sample";  // x1_hat per step: sample from softmax(logits / temperature), or argmax
  double temperature = 1.0;
  std::string last_step = "argmax";  // the last step's x1_hat: argmax or sample
  double t_eps = 1e-3;       // rates are evaluated at t clamped to [t_eps, 1 - t_eps]
  int batch_size = 32;
  void visit(FieldVisitor& v) override {
    v("steps", steps, "transition steps; times t_k = k / steps, step size h = 1 / steps", in_range(1, 10000));
    v("cfg_scale", cfg_scale, "classifier-free guidance on logits (1 = conditional only, 0 = unconditional)",
      in_range(0.0, 100.0));
    v("proposal", proposal, "clean-token proposal x1_hat at each step", one_of({"sample", "argmax"}));
    v("temperature", temperature, "softmax temperature of sampled proposals", positive<double>());
    v("last_step", last_step, "the final tokens are the last proposal: its argmax or a sample",
      one_of({"argmax", "sample"}));
    v("t_eps", t_eps, "clamp of t in beta'(t) (infinite at t = 0 for a < 1 and at t = 1)", in_range(1e-8, 0.5));
    v("batch_size", batch_size, "motions per network call (the CFG forward doubles it)", at_least(1));
  }
};

struct MaskedSamplerConfig : Config {
  int steps = 10;            // re-masking iterations (MoMask: ~10)
  double cfg_scale = 4.0;
  double temperature = 1.0;
  double topk_keep = 0.1;    // keep the top ceil(topk_keep * K) logits before sampling (MoMask 0.9 filter)
  int batch_size = 32;
  void visit(FieldVisitor& v) override {
    v("steps", steps, "iterations; step k re-masks round(n cos(pi/2 k/(steps-1))) >= 1 tokens", in_range(1, 1000));
    v("cfg_scale", cfg_scale, "classifier-free guidance on logits", in_range(0.0, 100.0));
    v("temperature", temperature, "sampling temperature", positive<double>());
    v("topk_keep", topk_keep, "fraction of the codebook kept by the top-k logit filter (1 = no filter)",
      in_range(1e-6, 1.0));
    v("batch_size", batch_size, "motions per network call (the CFG forward doubles it)", at_least(1));
  }
};

// ---------------------------------------------------------------- sampling

struct TokenSampleResult {
  torch::Tensor world;                 // [N, T, J, 3] world metres (CPU), zero past each length; T = max length
  std::vector<int> lengths;            // [N] frames as requested
  std::vector<torch::Tensor> tokens;   // [N] final codes, ceil(length / stride) each (CPU int64)
};

// One motion per caption of `lengths[i]` frames (1..t_max): ceil(length / stride) tokens
// are generated, decoded and trimmed. Each sample draws from its own generator seeded
// by (seed, index), so a sample depends on neither batch_size nor the other samples.
// Adapter hooks for one network call on rows [start, start + ids.size(0)) of a request:
// current tokens ids [B, L], times t [B], the conditional text, valid [B, L] (AnchorRoute).
using TokenHooksFn = std::function<TokenTransformerHooks(int64_t start, const torch::Tensor& ids,
                                                         const torch::Tensor& t, const TextContext& text,
                                                         const torch::Tensor& valid)>;
// `hooks` (optional) conditions every step; guided_logits gives them to the CFG passes
// their `guidance` names (both halves by default).
TokenSampleResult sample_tmd(const TokenPrior& prior, const std::vector<std::string>& captions,
                             const std::vector<int>& lengths, const TmdSamplerConfig& cfg, uint64_t seed,
                             const TokenHooksFn& hooks = {});
TokenSampleResult sample_masked(const TokenPrior& prior, const std::vector<std::string>& captions,
                                const std::vector<int>& lengths, const MaskedSamplerConfig& cfg, uint64_t seed);

}  // namespace mc
