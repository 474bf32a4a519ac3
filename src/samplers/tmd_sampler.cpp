// Loading a token prior with its tokenizer, CFG on logits, the TMD transition
// sampler (eqs. (21)-(23)) and the MoMask re-masking sampler.
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
#include "train/trainer.h"

namespace mc {

// ---------------------------------------------------------------- loading

TokenPrior TokenPrior::load(const std::string& run_dir, torch::Device device) {
  fs::path dir(run_dir);
  if (!fs::is_directory(dir))
    fail("token prior run directory '{}' does not exist; train one with `motionctl train configs/tmd/tmd_tiny.yaml` "
         "(or configs/masked/masked_tiny.yaml), or set prior_config to train it on demand",
         run_dir);
  fs::path final_pt = dir / "checkpoints" / "final.pt", meta_path = dir / "outputs" / "prior_meta.yaml";
  for (const fs::path& p : {dir / "config.yaml", final_pt, dir / "outputs" / "vocab.txt", meta_path})
    if (!fs::exists(p))
      fail("token prior run '{}' is incomplete: '{}' is missing; finish it with `motionctl train {}/config.yaml` "
           "(or point at a finished tmd_prior / masked_prior run)",
           run_dir, p.string(), run_dir);
  TrainJobConfig job;
  parse_config(compose_config((dir / "config.yaml").string()), job);
  if (job.model.type != "tmd_prior" && job.model.type != "masked_prior")
    fail("'{}' is a run of model type '{}', not a token prior (tmd_prior or masked_prior)", run_dir, job.model.type);
  TokenPrior p;
  p.run_dir_ = run_dir;
  p.device_ = device;
  p.cfg_ = std::dynamic_pointer_cast<TokenPriorConfig>(job.model.cfg);
  std::vector<std::string> words;
  {
    std::ifstream f(dir / "outputs" / "vocab.txt");
    for (std::string w; std::getline(f, w);) words.push_back(w);
  }
  p.vocab_ = std::make_shared<TextVocab>(words, (dir / "outputs" / "vocab.txt").string());
  std::string tokenizer_run;
  int64_t K = 0;
  try {
    YAML::Node meta = YAML::LoadFile(meta_path.string());
    p.t_max_ = meta["t_max"].as<int>();
    tokenizer_run = meta["tokenizer_run"].as<std::string>();
    K = meta["codebook_size"].as<int64_t>();
  } catch (const YAML::Exception& e) {
    fail("'{}' is corrupt: {}", meta_path.string(), e.what());
  }
  p.tok_ = load_vq_tokenizer(tokenizer_run, device);
  if (p.tok_.model->codebook_size() != K)
    fail("token prior '{}' was trained on {} codes but its tokenizer '{}' now has {}; retrain the prior", run_dir, K,
         tokenizer_run, p.tok_.model->codebook_size());
  p.net_ = std::make_shared<TokenPriorNet>(p.vocab_->size(), K, *p.cfg_);
  try {
    torch::serialize::InputArchive ar;
    ar.load_from(final_pt.string());
    (*p.net_)->load(ar);
  } catch (const std::exception&) {  // c10::Error, or torch::jit::ErrorReport on a damaged file
    fail("token prior checkpoint '{}' is unreadable or does not match its config.yaml", final_pt.string());
  }
  (*p.net_)->to(device);
  (*p.net_)->eval();
  // The codes the prior learned are only meaningful with the codebook it was trained on.
  torch::Tensor d_now;
  if (auto* t = dynamic_cast<const TmdPriorConfig*>(p.cfg_.get()))
    d_now = tmd_path_table(p.tok_.model->codebook(), t->path, t->beta_c, t->beta_a).dist.to(device);
  else
    d_now = p.tok_.model->token_distance_table().to(device);
  if (!torch::allclose((*p.net_)->distance, d_now, 1e-4, 1e-4))
    fail("the tokenizer '{}' no longer has the codebook token prior '{}' was trained with (distance tables differ); "
         "retrain the prior on this tokenizer",
         tokenizer_run, run_dir);
  return p;
}

const TmdPriorConfig& TokenPrior::tmd_config() const {
  auto* t = dynamic_cast<const TmdPriorConfig*>(cfg_.get());
  if (!t) throw std::logic_error("token prior '" + run_dir_ + "' is a masked prior, not TMD");
  return *t;
}

// ---------------------------------------------------------------- logits

TextContext TokenPrior::encode_texts(const std::vector<std::string>& captions) const {
  torch::NoGradGuard ng;
  auto enc = encode_captions(*vocab_, captions, cfg_->max_words);
  return (*net_)->encode_text(enc.ids.to(device_), enc.lengths.to(device_));
}

TextContext TokenPrior::null_texts(int64_t B, int64_t W) const {
  torch::NoGradGuard ng;
  return (*net_)->null_context(B, W);
}

torch::Tensor TokenPrior::raw_logits(const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                                     const torch::Tensor& valid, const TokenTransformerHooks* hooks) const {
  torch::Tensor tt;
  if (is_tmd()) tt = t.to(device_, torch::kFloat32).reshape({-1}).expand({ids.size(0)});
  return (*net_)->transformer->forward(ids.to(device_), tt, text, valid.to(device_), hooks).logits;
}

torch::Tensor TokenPrior::guided_logits(const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                                        const torch::Tensor& valid, double cfg_scale,
                                        const TokenTransformerHooks* hooks) const {
  torch::NoGradGuard ng;
  const int64_t B = ids.size(0), W = text.memory.size(1);
  torch::Tensor tt;
  if (is_tmd()) tt = t.to(device_, torch::kFloat32).reshape({-1}).expand({B});
  // Hooks in both halves unless hooks->guidance says otherwise (AnchorRoute's anchor guidance).
  auto l = guided_token_logits(*(*net_)->transformer, ids.to(device_), tt, text, null_texts(B, W), valid.to(device_),
                               cfg_scale, hooks);
  auto v = valid.to(device_, torch::kBool).unsqueeze(-1).expand_as(l);
  if (!torch::isfinite(l.masked_select(v)).all().item<bool>())
    fail("the token prior '{}' produced non-finite logits; the checkpoint is broken or diverged — retrain it "
         "(lower optim.lr) before sampling",
         run_dir_);
  return l;
}

torch::Tensor TokenPrior::decode_world(const torch::Tensor& ids) const {
  torch::NoGradGuard ng;
  const int64_t L = ids.size(0);
  VqTokenizer model = tok_.model;  // a handle: decode() is not const
  auto x = model->decode(ids.to(device_).view({1, L}));  // [1, L*s, J*3] normalised
  return tok_.model->denormalize(x.view({L * stride(), num_joints(), 3})).to(torch::kCPU);
}

// ---------------------------------------------------------------- TMD transitions

torch::Tensor tmd_transition_rates(const torch::Tensor& dist, const torch::Tensor& xt, const torch::Tensor& x1_hat,
                                   double t, double c, double a) {
  auto tt = torch::tensor(t, torch::kFloat64);
  double beta = tmd_beta(tt, c, a).item<double>(), dbeta = tmd_beta_prime(tt, c, a).item<double>();
  auto rows = torch::nn::functional::embedding(x1_hat, dist);           // d(., x1_hat) [..., K]
  auto q = torch::softmax(-beta * rows, -1);                             // q_t(. | x1_hat), eq. (18)
  auto d_xt = rows.gather(-1, xt.unsqueeze(-1));                         // d(x_t, x1_hat) [..., 1]
  auto u = q * dbeta * torch::relu(d_xt - rows);                         // eq. (21)
  // d(x_t, x_t) gain is 0 already; the explicit zero also covers ties in rounding.
  return u.scatter(-1, xt.unsqueeze(-1), 0.0);
}

torch::Tensor categorical_from_uniform(const torch::Tensor& probs, const torch::Tensor& u) {
  auto cdf = probs.cumsum(-1);
  auto target = u.to(cdf.dtype()).unsqueeze(-1) * cdf.narrow(-1, probs.size(-1) - 1, 1);
  // Entries with cdf <= target are passed over, so a zero-weight entry is never picked.
  return (cdf <= target).sum(-1).clamp_max(probs.size(-1) - 1);
}

torch::Tensor tmd_jump(const torch::Tensor& xt, const torch::Tensor& rates, double h, const torch::Tensor& u_jump,
                       const torch::Tensor& u_pick) {
  auto lambda = rates.sum(-1);                                   // eq. (22)
  auto p_jump = 1 - torch::exp(-h * lambda);                     // eq. (23)
  auto target = categorical_from_uniform(rates, u_pick.to(rates.device()));
  auto picked_rate = rates.gather(-1, target.unsqueeze(-1)).squeeze(-1);
  auto jump = (u_jump.to(rates.device()) < p_jump) & (lambda > 0) & (picked_rate > 0);
  return torch::where(jump, target, xt);
}

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
      auto probs = torch::softmax(logits / cfg.temperature, -1);
      const bool last = k + 1 == cfg.steps;
      const std::string& rule = last ? cfg.last_step : cfg.proposal;
      auto x1_hat = rule == "argmax" ? logits.argmax(-1) : categorical_from_uniform(probs, u.select(1, 0));
      if (last) {
        x = x1_hat;  // the final state is the clean proposal
        break;
      }
      const double tr = std::clamp(t, cfg.t_eps, 1.0 - cfg.t_eps);
      auto rates = tmd_transition_rates(dist, x, x1_hat, tr, pc.beta_c, pc.beta_a);  // eq. (21)
      x = tmd_jump(x, rates, h, u.select(1, 1), u.select(1, 2));                        // eqs. (22)-(23)
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
