// The TMD transition sampler (eqs. (21)-(23)) and the MoMask re-masking sampler
// over a loaded token prior.
#include "samplers/tmd_sampler.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <stdexcept>
#include <fstream>
#include <limits>

#include "core/error.h"
#include "models/flow_prior.h"

namespace mc {

// ---------------------------------------------------------------- sampling

namespace {

// Per-sample generators: a sample's randomness is its own, whatever the batching.
at::Generator sample_generator(uint64_t seed, int64_t index) {
  uint64_t s = seed ^ (0x9E3779B97F4A7C15ull * static_cast<uint64_t>(index + 1));
  return at::make_generator<at::CPUGeneratorImpl>(s);
}

// [B, rows, L] uniforms, row b from gens[b]. Every draw takes `full` >= L numbers per
// row so a generator's stream does not depend on the batch's padded length L.
torch::Tensor draw_uniform(std::vector<at::Generator>& gens, int64_t rows, int64_t L, int64_t full) {
  std::vector<torch::Tensor> out;
  for (auto& g : gens) out.push_back(torch::rand({rows, full}, g, torch::TensorOptions()).narrow(1, 0, L));
  return torch::stack(out);
}

struct Batch {
  int64_t start = 0, B = 0, L = 0;
  int64_t full = 0;          // the prior's maximum token count (random draws are this long)
  std::vector<std::string> captions;
  torch::Tensor valid;       // [B, L] bool on the prior's device
  torch::Tensor n_tokens;    // [B] int64 CPU
  std::vector<at::Generator> gens;
};

using BatchSampler = std::function<torch::Tensor(Batch&)>;  // -> tokens [B, L]

TokenSampleResult run_sampler(const TokenPrior& prior, const std::vector<std::string>& captions,
                              const std::vector<int>& lengths, int batch_size, uint64_t seed,
                              const BatchSampler& sample_batch) {
  torch::NoGradGuard ng;
  const int64_t N = captions.size(), J = prior.num_joints(), s = prior.stride();
  if (lengths.size() != captions.size())
    fail("{} captions but {} lengths; give one length per caption", captions.size(), lengths.size());
  int64_t T = 1;
  for (size_t i = 0; i < lengths.size(); ++i) {
    if (lengths[i] < 1 || lengths[i] > prior.t_max())
      fail("sample {} asks for {} frames; the token prior '{}' was trained on clips of 1..{} frames", i, lengths[i],
           prior.run_dir(), prior.t_max());
    T = std::max<int64_t>(T, lengths[i]);
  }
  TokenSampleResult out;
  out.world = torch::zeros({N, T, J, 3});
  out.lengths = lengths;
  for (int64_t start = 0; start < N; start += batch_size) {
    Batch b;
    b.start = start;
    b.full = prior.max_tokens();
    b.B = std::min<int64_t>(batch_size, N - start);
    b.captions.assign(captions.begin() + start, captions.begin() + start + b.B);
    b.n_tokens = torch::zeros({b.B}, torch::kInt64);
    for (int64_t i = 0; i < b.B; ++i) {
      // Rounded up: the decoder yields whole strides and the surplus (< stride frames) is cut.
      int64_t n = (lengths[start + i] + s - 1) / s;
      b.n_tokens[i] = n;
      b.L = std::max(b.L, n);
      b.gens.push_back(sample_generator(seed, start + i));
    }
    b.valid = (torch::arange(b.L).unsqueeze(0) < b.n_tokens.unsqueeze(1)).to(prior.device());
    auto tokens = sample_batch(b).to(torch::kCPU);
    for (int64_t i = 0; i < b.B; ++i) {
      const int64_t n = b.n_tokens[i].item<int64_t>(), len = lengths[start + i];
      auto ids = tokens[i].narrow(0, 0, n).clone();
      auto world = prior.decode_world(ids);
      if (!torch::isfinite(world).all().item<bool>())
        fail("sampling from '{}' produced non-finite joints (sample {}); nothing was written", prior.run_dir(),
             start + i);
      out.world[start + i].narrow(0, 0, len).copy_(world.narrow(0, 0, len));
      out.tokens.push_back(ids);
    }
  }
  return out;
}

}  // namespace

TokenSampleResult sample_tmd(const TokenPrior& prior, const std::vector<std::string>& captions,
                             const std::vector<int>& lengths, const TmdSamplerConfig& cfg, uint64_t seed,
                             const TokenHooksFn& hooks) {
  if (!prior.is_tmd())
    fail("'{}' is a masked prior; sample it with the masked sampler (generator type masked)", prior.run_dir());
  const auto& pc = prior.tmd_config();
  const int64_t K = prior.codebook_size();
  const auto dev = prior.device();
  auto dist = prior.distance();
  return run_sampler(prior, captions, lengths, cfg.batch_size, seed, [&](Batch& b) {
    // Start from uniform random tokens (the t = 0 marginal of eq. (18)).
    std::vector<torch::Tensor> init;
    for (auto& g : b.gens)
      init.push_back(torch::randint(0, K, {b.full}, g, torch::TensorOptions().dtype(torch::kInt64)).narrow(0, 0, b.L));
    auto x = torch::stack(init).to(dev);
    auto text = prior.encode_texts(b.captions);
    const double h = 1.0 / cfg.steps;
    for (int k = 0; k < cfg.steps; ++k) {
      const double t = k * h;
      auto tv = torch::full({b.B}, t);
      TokenTransformerHooks hk;
      if (hooks) hk = hooks(b.start, x, tv.to(dev), text, b.valid);
      auto logits = prior.guided_logits(x, tv, text, b.valid, cfg.cfg_scale, hooks ? &hk : nullptr);
      auto u = draw_uniform(b.gens, 3, b.L, b.full).to(dev);
      if (k + 1 == cfg.steps) {
        // The final state is the clean proposal.
        x = cfg.last_step == "argmax"
                ? logits.argmax(-1)
                : categorical_from_uniform(torch::softmax(logits / cfg.temperature, -1), u.select(1, 0));
        break;
      }
      x = tmd_sampler_step(dist, x, logits, t, h, cfg.t_eps, pc.beta_c, pc.beta_a, cfg.proposal == "argmax",
                           cfg.temperature, u.select(1, 0), u.select(1, 1), u.select(1, 2));
    }
    return x;
  });
}

TokenSampleResult sample_masked(const TokenPrior& prior, const std::vector<std::string>& captions,
                                const std::vector<int>& lengths, const MaskedSamplerConfig& cfg, uint64_t seed) {
  if (prior.is_tmd())
    fail("'{}' is a TMD prior; sample it with the TMD sampler (generator type tmd)", prior.run_dir());
  const int64_t K = prior.codebook_size();
  const int64_t mask_id = prior.net()->transformer->mask_id();
  const int64_t keep = std::max<int64_t>(1, static_cast<int64_t>(std::ceil(cfg.topk_keep * K)));
  const auto dev = prior.device();
  return run_sampler(prior, captions, lengths, cfg.batch_size, seed, [&](Batch& b) {
    auto ids = torch::full({b.B, b.L}, mask_id, torch::TensorOptions().dtype(torch::kInt64).device(dev));
    // Scores: confidence of the tokens predicted last step; fixed tokens and padding never re-mask.
    auto scores = torch::zeros({b.B, b.L}, torch::TensorOptions().device(dev)).masked_fill(b.valid.logical_not(), 1e5);
    auto text = prior.encode_texts(b.captions);
    for (int k = 0; k < cfg.steps; ++k) {
      auto counts = torch::zeros({b.B, 1}, torch::kInt64);
      for (int64_t i = 0; i < b.B; ++i) counts[i][0] = masked_sample_count(b.n_tokens[i].item<int64_t>(), k, cfg.steps);
      auto order = std::get<1>(torch::sort(scores, c10::optional<bool>(true), 1, false));
      auto ranks = order.argsort(int64_t{1});
      auto is_mask = (ranks < counts.to(dev)) & b.valid;
      ids = torch::where(is_mask, torch::full_like(ids, mask_id), ids);
      auto logits = prior.guided_logits(ids, torch::Tensor(), text, b.valid, cfg.cfg_scale);
      auto thresh = std::get<0>(logits.topk(keep, -1)).narrow(-1, keep - 1, 1);
      auto filtered = logits.masked_fill(logits < thresh, -std::numeric_limits<float>::infinity());
      auto u = draw_uniform(b.gens, 1, b.L, b.full).to(dev).select(1, 0);
      auto pred = categorical_from_uniform(torch::softmax(filtered / cfg.temperature, -1), u);
      ids = torch::where(is_mask, pred, ids);
      auto conf = torch::softmax(logits, -1).gather(-1, pred.unsqueeze(-1)).squeeze(-1);
      scores = torch::where(is_mask, conf, torch::full_like(conf, 1e5));
    }
    return ids;
  });
}

}  // namespace mc
