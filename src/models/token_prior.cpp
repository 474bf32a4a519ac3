// The token priors' configs, text encoder and network bundle, the TMD corruption
// maths, one trainer for both `tmd_prior` (eqs. (17)-(20)) and `masked_prior`, and
// the trained prior loaded from its run directory.
#include "models/token_prior.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>

#include "core/atomic_file.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"
#include "models/flow_prior.h"
#include "models/sharded_dropout.h"
#include "models/trained_run.h"
#include "models/vq_tokenizer.h"
#include "core/trained_runs.h"
#include "models/trainable.h"

namespace mc {
namespace nn = torch::nn;
namespace F = torch::nn::functional;

// ---------------------------------------------------------------- config

void TokenPriorConfig::visit(FieldVisitor& v) {
  v("depth", depth, "transformer blocks", in_range(1, 64));
  v("width", width, "hidden size d", at_least(8));
  v("heads", heads, "attention heads; width / heads must be even (RoPE)", at_least(1));
  v("mlp_hidden", mlp_hidden, "SwiGLU hidden size (0 = 8/3 * width rounded up to a multiple of 64)", at_least(0));
  v("dropout", dropout, "dropout on attention probabilities and the MLP hidden", in_range(0.0, 0.9));
  v("cond_drop", cond_drop, "probability of replacing the text by the learned null condition (for CFG)",
    in_range(0.0, 1.0));
  visit_text_fields(v, "text encoder width (pooled vector and text memory size)");
  v("tokenizer_run", tokenizer_run, "finished vq_tokenizer run directory ('' = train tokenizer_config on demand)");
  v("tokenizer_config", tokenizer_config, "tokenizer training config run on demand when tokenizer_run is ''");
  v("tokenizer_overrides", tokenizer_overrides, "key=value overrides for tokenizer_config (e.g. run.root=...)");
  v("eval_t", eval_t, "times (TMD) / mask times (masked) at which evaluate() reports the validation CE",
    each(in_range(0.0, 0.999)));
  visit_extra(v);
}

void TmdPriorConfig::visit_extra(FieldVisitor& v) {
  v("beta_c", beta_c, "c of beta(t) = c (t/(1-t))^a, eq. (18)", positive<double>());
  v("beta_a", beta_a, "a of beta(t) = c (t/(1-t))^a, eq. (18)", positive<double>());
  v("t_eps", t_eps, "training times are drawn from U[0, 1 - t_eps)", in_range(1e-6, 0.5));
  v("path", path, "metric of eq. (17) and its calibration to the codebook (the paper's by default)");
}

std::string TokenPriorConfig::validate() const {
  if (width % heads != 0) return fmt::format("width {} is not a multiple of heads {}", width, heads);
  if ((width / heads) % 2 != 0) return fmt::format("head size width/heads = {} must be even for RoPE", width / heads);
  if (auto e = text_fields_error(); !e.empty()) return e;
  if (tokenizer_run.empty() && tokenizer_config.empty())
    return "set model.tokenizer_run (a finished vq_tokenizer run) or model.tokenizer_config";
  if (eval_t.empty()) return "eval_t needs at least one time";
  return "";
}

TokenTransformerOptions TokenPriorConfig::transformer_options(int64_t num_codes) const {
  TokenTransformerOptions o;
  o.num_codes = num_codes;
  o.num_special = 1;
  o.depth = depth;
  o.width = width;
  o.heads = heads;
  o.mlp_hidden = mlp_hidden;
  o.dropout = dropout;
  o.text_dim = text_width;
  o.use_time = is_tmd();
  return o;
}

// ---------------------------------------------------------------- TMD maths

torch::Tensor tmd_beta(const torch::Tensor& t, double c, double a) {
  return c * torch::pow(t / (1 - t), a);  // eq. (18)
}

torch::Tensor tmd_beta_prime(const torch::Tensor& t, double c, double a) {
  return c * a * torch::pow(t / (1 - t), a - 1) / (1 - t).pow(2);
}

torch::Tensor tmd_path_probs(const torch::Tensor& dist, const torch::Tensor& x1, const torch::Tensor& beta) {
  auto rows = F::embedding(x1, dist);                        // d(., x1) = d(x1, .) [..., K]
  return torch::softmax(-beta.unsqueeze(-1) * rows, -1);     // eq. (18)
}

namespace {

// Mean over codes of q_t(x1|x1) = 1 / sum_i exp(-beta d(i, x1)) (d(x1, x1) = 0).
double mean_q_self(const torch::Tensor& d64, double beta) {
  return (1.0 / torch::exp(-beta * d64).sum(1)).mean().item<double>();
}

}  // namespace

TmdPathTable tmd_path_table(const torch::Tensor& codebook, const TmdPathConfig& path, double c, double a) {
  torch::NoGradGuard ng;
  auto e = codebook.detach().to(torch::kCPU, torch::kFloat64);
  const int64_t K = e.size(0), D = e.size(1);
  if (path.metric != "cosine") e = e - e.mean(0, true);
  if (path.metric == "whitened_cosine") {
    // ZCA whitening with a ridge of 1e-6 of the mean variance (rank-deficient codebooks).
    auto cov = torch::matmul(e.t(), e) / std::max<int64_t>(1, K - 1);
    auto ridge = 1e-6 * cov.diagonal().mean().item<double>() + 1e-12;
    auto [evals, evecs] = torch::linalg_eigh(cov + ridge * torch::eye(D, torch::kFloat64));
    auto w = torch::matmul(evecs * evals.clamp_min(ridge).rsqrt().unsqueeze(0), evecs.t());
    e = torch::matmul(e, w);
  }
  auto n = F::normalize(e, F::NormalizeFuncOptions().p(2).dim(1).eps(1e-12));
  auto d = (2.0 - 2.0 * torch::matmul(n, n.t()).clamp(-1.0, 1.0)).pow(2);
  d.fill_diagonal_(0.0);
  TmdPathTable out;
  if (path.calibration == "q_target") {
    const double t = path.target_t, beta = c * std::pow(t / (1 - t), a);
    if (mean_q_self(d, beta) < path.target_q) {
      double lo = 0.0, hi = std::log(1e8);  // log s
      if (mean_q_self(d, beta * std::exp(hi)) < path.target_q)
        fail("tmd path calibration: even s = 1e8 leaves mean q_{}(x1|x1) below {}: the codebook has (near-)duplicate "
             "codes; use path.metric centered_cosine / whitened_cosine or a lower target_q",
             t, path.target_q);
      for (int it = 0; it < 100; ++it) {
        const double mid = 0.5 * (lo + hi);
        (mean_q_self(d, beta * std::exp(mid)) < path.target_q ? lo : hi) = mid;
      }
      out.scale = std::exp(hi);
    }
  } else if (path.calibration != "none") {
    fail("unknown tmd path calibration '{}' (none or q_target)", path.calibration);
  }
  out.dist = (d * out.scale).to(torch::kFloat32);
  return out;
}

TmdPathStats tmd_path_stats(const torch::Tensor& dist, double t, double c, double a) {
  torch::NoGradGuard ng;
  auto d = dist.detach().to(torch::kCPU, torch::kFloat64);
  const double beta = t <= 0 ? 0.0 : c * std::pow(t / (1 - t), a);
  auto logq = torch::log_softmax(-beta * d, 1);  // row x1: log q_t(. | x1)
  TmdPathStats s;
  s.q_self = logq.diagonal().exp().mean().item<double>();
  s.effective_codes = torch::exp(-(logq.exp() * logq).sum(1)).mean().item<double>();
  return s;
}

// ---------------------------------------------------------------- masking

int64_t masked_train_count(int64_t n, double t) {
  auto m = static_cast<int64_t>(std::llround(static_cast<double>(n) * std::cos(M_PI * t / 2)));
  return std::clamp<int64_t>(m, 1, std::max<int64_t>(1, n));
}

int64_t masked_sample_count(int64_t n, int step, int steps) {
  double t = steps > 1 ? static_cast<double>(step) / (steps - 1) : 0.0;
  return masked_train_count(n, t);
}

// ---------------------------------------------------------------- text

TokenTextEncoderImpl::TokenTextEncoderImpl(int vocab_size, const TokenPriorConfig& c) {
  embedding = register_module("embedding",
                              nn::Embedding(nn::EmbeddingOptions(vocab_size, c.text_width).padding_idx(TextVocab::kPad)));
  position = register_module("position", nn::Embedding(c.max_words, c.text_width));
  auto layer = nn::TransformerEncoderLayer(nn::TransformerEncoderLayerOptions(c.text_width, c.text_heads)
                                               .dim_feedforward(c.text_ff)
                                               .dropout(c.text_dropout)
                                               .activation(torch::kGELU));
  encoder = register_module("encoder", nn::TransformerEncoder(nn::TransformerEncoderOptions(layer, c.text_layers)));
  norm = register_module("norm", nn::LayerNorm(nn::LayerNormOptions({c.text_width})));
  out = register_module("out", nn::Linear(c.text_width, c.text_width));
  torch::NoGradGuard ng;
  nn::init::normal_(embedding->weight, 0.0, 0.02);
  embedding->weight[TextVocab::kPad].zero_();
  nn::init::normal_(position->weight, 0.0, 0.02);
}

TextContext TokenTextEncoderImpl::forward(const torch::Tensor& ids, const torch::Tensor& lengths) {
  const int64_t L = ids.size(1);
  auto dev = ids.device();
  auto pos = torch::arange(L, torch::TensorOptions().dtype(torch::kInt64).device(dev));
  auto h = embedding(ids) + position(pos).unsqueeze(0);
  auto valid = pos.unsqueeze(0) < lengths.to(dev).unsqueeze(1);  // [B, W]
  h = transformer_encoder_forward(*encoder, h.transpose(0, 1), valid.logical_not()).transpose(0, 1);
  auto m = valid.unsqueeze(-1).to(h.dtype());
  TextContext c;
  c.pooled = out(norm((h * m).sum(1) / m.sum(1).clamp_min(1.0)));
  // Padding states are finite but unused: cross-attention masks them out.
  c.memory = norm(h) * m;
  c.memory_valid = valid;
  return c;
}

// ---------------------------------------------------------------- bundle

TokenPriorNetImpl::TokenPriorNetImpl(int vocab_size, int64_t num_codes, const TokenPriorConfig& c) {
  text = register_module("text", TokenTextEncoder(vocab_size, c));
  transformer = register_module("transformer", TokenTransformer(c.transformer_options(num_codes)));
  null_text = register_parameter("null_text", torch::randn({c.text_width}) * 0.02);
  null_memory = register_parameter("null_memory", torch::randn({c.text_width}) * 0.02);
  distance = register_buffer("distance", torch::zeros({num_codes, num_codes}));
}

TextContext TokenPriorNetImpl::encode_text(const torch::Tensor& ids, const torch::Tensor& lengths) {
  return text->forward(ids, lengths);
}

TextContext TokenPriorNetImpl::null_context(int64_t B, int64_t W) {
  const auto dev = null_text.device();
  TextContext c;
  c.pooled = null_text.unsqueeze(0).expand({B, -1});
  auto first = torch::zeros({W}, torch::TensorOptions().dtype(torch::kBool).device(dev));
  first[0] = true;
  c.memory = null_memory.view({1, 1, -1}) * first.view({1, W, 1}).to(null_memory.dtype());
  c.memory = c.memory.expand({B, W, -1});
  c.memory_valid = first.unsqueeze(0).expand({B, W});
  return c;
}

TextContext TokenPriorNetImpl::drop_condition(const TextContext& c, const torch::Tensor& drop) {
  const int64_t B = c.pooled.size(0), W = c.memory.size(1);
  auto n = null_context(B, W);
  auto d = drop.to(c.pooled.device(), torch::kBool);
  TextContext out;
  out.pooled = torch::where(d.view({B, 1}), n.pooled, c.pooled);
  out.memory = torch::where(d.view({B, 1, 1}), n.memory, c.memory);
  out.memory_valid = torch::where(d.view({B, 1}), n.memory_valid, c.memory_valid.to(torch::kBool));
  return out;
}

TextContext cat_contexts(const TextContext& a, const TextContext& b) {
  return {torch::cat({a.pooled, b.pooled}), torch::cat({a.memory, b.memory}),
          torch::cat({a.memory_valid, b.memory_valid})};
}

TokenizedClips tokenize_clips(VqTokenizerImpl& tok, const MotionSet& set, torch::Device device) {
  torch::NoGradGuard ng;
  const int64_t N = set.size(), J = set.num_joints(), Tm = set.t_max, stride = tok.stride();
  const int64_t L = (Tm + stride - 1) / stride, Tp = L * stride;
  TokenizedClips out;
  out.tokens = torch::zeros({N, L}, torch::kInt64);
  out.lengths = torch::zeros({N}, torch::kInt64);
  auto all = torch::from_blob(const_cast<float*>(set.joints.data()), {N, Tm, J, 3}, torch::kFloat32);
  for (int64_t s = 0; s < N; s += 64) {
    const int64_t n = std::min<int64_t>(64, N - s);
    auto world = torch::zeros({n, Tp, J, 3});
    world.narrow(1, 0, Tm).copy_(all.narrow(0, s, n));
    auto mask = torch::zeros({n, Tp}, torch::kBool);
    for (int64_t b = 0; b < n; ++b) {
      mask[b].narrow(0, 0, set.lengths[s + b]).fill_(true);
      out.lengths[s + b] = (set.lengths[s + b] + stride - 1) / stride;
    }
    auto x = tok.normalize(world.to(device)).flatten(2);
    out.tokens.narrow(0, s, n).copy_(tok.encode(x, mask.to(device)).to(torch::kCPU));
  }
  return out;
}

std::string resolve_tokenizer_run(const TokenPriorConfig& c) {
  return trained_run("model.tokenizer", c.tokenizer_run, c.tokenizer_config, c.tokenizer_overrides);
}

// ---------------------------------------------------------------- trainer

namespace {

const char* kMetaFile = "prior_meta.yaml";

class TokenPriorTrainer : public Trainable {
 public:
  TokenPriorTrainer(const TokenPriorConfig& c, const TrainContext& ctx) : ctx_(ctx) {
    if (auto* t = dynamic_cast<const TmdPriorConfig*>(&c)) {
      auto own = std::make_shared<TmdPriorConfig>(*t);
      tmd_ = own.get();
      own_ = own;
    } else {
      own_ = std::make_shared<MaskedPriorConfig>(dynamic_cast<const MaskedPriorConfig&>(c));
    }
    const MotionSet& set = ctx.data->set();
    tokenizer_run_ = resolve_tokenizer_run(c);
    auto tok = load_vq_tokenizer(tokenizer_run_, ctx.device);
    tok.check_compatible(set, ctx.data->source());
    K_ = tok.model->codebook_size();
    stride_ = tok.model->stride();
    vocab_ = set.vocab.empty() ? TextVocab::build(set) : TextVocab(set.vocab, ctx.data->source());
    net_ = TokenPriorNet(vocab_.size(), K_, c);
    {
      torch::NoGradGuard ng;
      if (tmd_) {
        auto table = tmd_path_table(tok.model->codebook(), tmd_->path, tmd_->beta_c, tmd_->beta_a);
        net_->distance.copy_(table.dist);
        path_scale_ = table.scale;
        paper_dist_ = tmd_path_table(tok.model->codebook(), TmdPathConfig{}, 3.0, 0.9).dist;
      } else {
        net_->distance.copy_(tok.model->token_distance_table());
      }
    }
    auto clips = tokenize_clips(*tok.model, set, ctx.device);
    tokens_ = clips.tokens;
    token_lengths_ = clips.lengths;
  }
  nn::Module& module() override { return *net_; }

  // Captions, t, drops, masking noise and corruptions are drawn for the whole batch
  // (train/batch_shard.h); a shard's CE and accuracy divide by the whole batch's
  // target-token count.
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    const std::vector<std::string> caps = ctx_.data->drawn_captions(idx);
    const int64_t B = idx.size();
    auto t = torch::rand({B});
    auto drop = torch::rand({B}) < cfg().cond_drop;
    torch::Tensor noise;  // masked prior: the random ranks choosing masked positions
    if (!tmd_) noise = torch::rand({B, tokens_.size(1)});
    auto r = token_loss(idx, caps, t, drop, noise, nullptr, shard);
    LossOutput out;
    out.loss = r.ce;
    out.parts = {{"ce", r.ce.detach()}, {"acc", r.acc}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Validation CE at fixed times (first caption, corruption from a constant-seeded
  // local generator): comparable across runs and leaves torch's RNG alone.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    net_->eval();
    auto gen = at::make_generator<at::CPUGeneratorImpl>(20240611);
    // CE and accuracy weighted by target tokens; CE also per time.
    auto chunk_values = [&](double tv, const std::vector<int64_t>& chunk) {
      const std::vector<std::string> caps = ctx_.data->first_captions(chunk);
      const int64_t B = chunk.size();
      auto t = torch::full({B}, tv);
      auto drop = torch::zeros({B}, torch::kBool);
      torch::Tensor noise;
      if (!tmd_) noise = torch::rand({B, tokens_.size(1)}, gen, torch::TensorOptions());
      auto r = token_loss(chunk, caps, t, drop, noise, &gen);
      return ChunkValues{{r.ce.item<double>(), r.acc.item<double>()}, r.count};
    };
    const TimedValidation v = validate_at_times(cfg().eval_t, ctx_.data->split("val"), 32, 2, chunk_values);
    std::map<std::string, double> out;
    for (size_t k = 0; k < cfg().eval_t.size(); ++k)
      out[fmt::format("val_ce_t{:.2f}", cfg().eval_t[k])] = v.at_time[k][0];
    out["val_ce"] = v.mean[0];
    out["val_acc"] = v.mean[1];
    if (tmd_) {
      // How concentrated the corruption path is on this codebook (issue 15): mean
      // q_t(x1|x1) and effective codes exp(H) per t, for the path trained with and for
      // the paper's (plain cosine, c = 3, a = 0.9) beside it.
      out["path_scale"] = path_scale_;
      out["path_c_effective"] = tmd_->beta_c * path_scale_;
      for (double tv : cfg().eval_t) {
        auto st = tmd_path_stats(net_->distance, tv, tmd_->beta_c, tmd_->beta_a);
        auto sp = tmd_path_stats(paper_dist_, tv, 3.0, 0.9);
        out[fmt::format("path_q_self_t{:.2f}", tv)] = st.q_self;
        out[fmt::format("path_eff_codes_t{:.2f}", tv)] = st.effective_codes;
        out[fmt::format("paper_path_q_self_t{:.2f}", tv)] = sp.q_self;
        out[fmt::format("paper_path_eff_codes_t{:.2f}", tv)] = sp.effective_codes;
      }
      // Code usage of the training data: exp entropy of the token histogram.
      auto counts = torch::bincount(tokens_.masked_select(torch::arange(tokens_.size(1)).unsqueeze(0) <
                                                          token_lengths_.unsqueeze(1)),
                                    {}, K_)
                        .to(torch::kFloat64);
      auto p = counts / counts.sum().clamp_min(1.0);
      out["data_code_perplexity"] = torch::exp(-(p * torch::log(p + 1e-12)).sum()).item<double>();
    }
    return out;
  }

  void save_artifacts(const fs::path& outputs) override {
    std::string words;
    for (auto& w : vocab_.words()) words += w + "\n";
    write_file_atomic(outputs / "vocab.txt", words);
    const MotionSet& set = ctx_.data->set();
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "fps" << YAML::Value << set.fps << YAML::Key << "t_max" << YAML::Value
      << set.t_max << YAML::Key << "num_joints" << YAML::Value << set.num_joints() << YAML::Key << "data"
      << YAML::Value << ctx_.data->source() << YAML::Key << "tokenizer_run" << YAML::Value << tokenizer_run_
      << YAML::Key << "codebook_size" << YAML::Value << K_ << YAML::Key << "stride" << YAML::Value << stride_;
    if (tmd_)
      e << YAML::Key << "path_scale" << YAML::Value << path_scale_ << YAML::Key << "beta_c_effective" << YAML::Value
        << tmd_->beta_c * path_scale_;
    e << YAML::Key << "skeleton" << YAML::Value << YAML::Literal << skeleton_to_yaml(set.skeleton) << YAML::EndMap;
    write_file_atomic(outputs / kMetaFile, std::string(e.c_str()) + "\n");
  }

 private:
  struct TokenLoss {
    torch::Tensor ce, acc;  // scalars
    double count = 0;       // tokens the CE averages over
  };

  // eq. (20) averaged over the tokens it covers: all valid tokens (TMD) or the masked
  // ones (masked baseline). gen = nullptr draws TMD corruptions from torch's generator.
  // Inputs are the whole batch's; a shard computes its rows (corruptions drawn for
  // all of them) and its share: CE and accuracy summed over its targets and divided
  // by the whole batch's target count.
  TokenLoss token_loss(const std::vector<int64_t>& idx, const std::vector<std::string>& caps, const torch::Tensor& t,
                       const torch::Tensor& drop, const torch::Tensor& noise, at::Generator* gen,
                       const BatchShard& shard = {}) {
    const auto dev = ctx_.device;
    const int64_t Bw = idx.size(), L = tokens_.size(1);
    const int64_t B = shard.rows(Bw).size();
    auto ix = torch::tensor(idx, torch::kInt64);
    auto x1 = tokens_.index_select(0, ix).to(dev);
    auto n = token_lengths_.index_select(0, ix);
    auto valid = (torch::arange(L).unsqueeze(0) < n.unsqueeze(1)).to(dev);
    torch::Tensor xin, target_mask, tt;
    if (tmd_) {
      // eq. (19): z_t,n ~ q_t(. | z_1,n) per token, t ~ U[0, 1 - eps).
      tt = (t * (1 - tmd_->t_eps)).to(dev);
      auto probs = tmd_path_probs(net_->distance, x1, tmd_beta(tt, tmd_->beta_c, tmd_->beta_a).view({Bw, 1}));
      auto flat = probs.reshape({Bw * L, K_}).to(torch::kCPU);
      auto draw = gen ? torch::multinomial(flat, 1, false, *gen) : torch::multinomial(flat, 1);
      xin = draw.view({Bw, L}).to(dev);
      target_mask = valid;
    } else {
      // MoMask: mask round(n cos(pi t / 2)) >= 1 random valid tokens.
      auto counts = torch::zeros({Bw}, torch::kInt64);
      auto ta = t.accessor<float, 1>();
      for (int64_t b = 0; b < Bw; ++b) counts[b] = masked_train_count(n[b].item<int64_t>(), ta[b]);
      auto scores = noise.masked_fill(valid.to(torch::kCPU).logical_not(), 2.0);
      auto ranks = scores.argsort(int64_t{1}).argsort(int64_t{1});  // continuous noise: ties have probability 0
      target_mask = (ranks < counts.unsqueeze(1)).to(dev);
      xin = torch::where(target_mask, torch::full_like(x1, net_->transformer->mask_id()), x1);
    }
    const double whole_count = target_mask.sum().item<double>();
    x1 = shard.local(x1);
    valid = shard.local(valid);
    xin = shard.local(xin);
    target_mask = shard.local(target_mask);
    if (tt.defined()) tt = shard.local(tt);
    auto enc = encode_captions(vocab_, shard.local(caps), cfg().max_words);
    auto text = net_->encode_text(enc.ids.to(dev), enc.lengths.to(dev));
    text = net_->drop_condition(text, shard.local(drop).to(dev));
    auto logits = net_->transformer->forward(xin, tt, text, valid).logits;  // [B, L, K]
    auto sel = target_mask.reshape({-1});
    auto lg = logits.reshape({B * L, K_}).index({sel});
    auto tg = x1.reshape({-1}).index({sel});
    TokenLoss r;
    if (shard.whole()) {
      r.ce = F::cross_entropy(lg, tg);
      r.acc = (lg.argmax(-1) == tg).to(torch::kFloat32).mean().detach();
    } else {
      const double denom = std::max(1.0, whole_count);
      r.ce = F::cross_entropy(lg, tg, F::CrossEntropyFuncOptions().reduction(torch::kSum)) / denom;
      r.acc = (lg.argmax(-1) == tg).to(torch::kFloat32).sum().detach() / denom;
    }
    r.count = whole_count;
    return r;
  }

  std::shared_ptr<TokenPriorConfig> own_;  // a copy of the model config (its dynamic type)
  const TokenPriorConfig& cfg() const { return *own_; }
  const TmdPriorConfig* tmd_ = nullptr;
  TrainContext ctx_;
  TextVocab vocab_{TextVocab::special_tokens()};
  TokenPriorNet net_{nullptr};
  std::string tokenizer_run_;
  int64_t K_ = 0, stride_ = 4;
  double path_scale_ = 1.0;      // TMD: s of the calibrated table (1 = the paper's path)
  torch::Tensor paper_dist_;     // TMD: the paper's table (plain cosine), for the diagnostics
  torch::Tensor tokens_;         // [N, L] int64 CPU: every clip's codes
  torch::Tensor token_lengths_;  // [N] valid tokens = ceil(length / stride)
};

std::unique_ptr<Trainable> make_token_trainer(const Config& c, const TrainContext& ctx) {
  return std::make_unique<TokenPriorTrainer>(dynamic_cast<const TokenPriorConfig&>(c), ctx);
}

}  // namespace

MC_REGISTER_MODEL("tmd_prior", TmdPriorConfig, make_token_trainer,
                  "AnchorRoute's TMD prior: metric discrete flow over VQ tokens, dual-context text (eqs. (17)-(20))");
MC_REGISTER_MODEL("masked_prior", MaskedPriorConfig, make_token_trainer,
                  "MoMask-style masked token prior (cosine masking) on the TMD backbone and tokenizer");

// ---------------------------------------------------------------- the trained prior

TokenPrior TokenPrior::load(const std::string& run_dir, torch::Device device) {
  TrainedRun run = open_trained_run(
      run_dir, {"token prior", {"tmd_prior", "masked_prior"}, {"vocab.txt", "prior_meta.yaml"},
                "train one with `motionctl train configs/tmd/tmd_tiny.yaml` (or configs/masked/masked_tiny.yaml), "
                "or set prior_config to train it first"});
  TokenPrior p;
  p.run_dir_ = run_dir;
  p.device_ = device;
  p.cfg_ = std::dynamic_pointer_cast<TokenPriorConfig>(run.model.cfg);
  p.vocab_ = std::make_shared<TextVocab>(run.vocab_words(), run.output("vocab.txt").string());
  std::string tokenizer_run;
  int64_t K = 0;
  run.read_meta("prior_meta.yaml", [&](const YAML::Node& meta) {
    p.t_max_ = meta["t_max"].as<int>();
    tokenizer_run = run.dependency(meta["tokenizer_run"].as<std::string>());
    K = meta["codebook_size"].as<int64_t>();
  });
  p.tok_ = load_vq_tokenizer(tokenizer_run, device);
  if (p.tok_.model->codebook_size() != K)
    fail("token prior '{}' was trained on {} codes but its tokenizer '{}' now has {}; retrain the prior", run_dir, K,
         tokenizer_run, p.tok_.model->codebook_size());
  p.net_ = std::make_shared<TokenPriorNet>(p.vocab_->size(), K, *p.cfg_);
  run.load_weights(**p.net_);
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

torch::Tensor tmd_sampler_step(const torch::Tensor& dist, const torch::Tensor& x, const torch::Tensor& logits,
                               double t, double h, double t_eps, double c, double a, bool argmax,
                               double temperature, const torch::Tensor& u_proposal, const torch::Tensor& u_jump,
                               const torch::Tensor& u_pick) {
  auto x1_hat = argmax ? logits.argmax(-1) : categorical_from_uniform(torch::softmax(logits / temperature, -1), u_proposal);
  const double tr = std::clamp(t, t_eps, 1.0 - t_eps);
  auto rates = tmd_transition_rates(dist, x, x1_hat, tr, c, a);  // eq. (21)
  return tmd_jump(x, rates, h, u_jump, u_pick);                 // eqs. (22)-(23)
}

}  // namespace mc
