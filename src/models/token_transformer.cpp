// The token transformer of the tokenised priors: AdaLN-Zero blocks with RoPE
// self-attention (plus AnchorKV's extra memory), text cross-attention and SwiGLU.
#include "models/token_transformer.h"

#include <cmath>
#include <limits>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "core/error.h"

namespace mc {
namespace nn = torch::nn;

int64_t TokenTransformerOptions::resolved_mlp_hidden() const {
  if (mlp_hidden > 0) return mlp_hidden;
  int64_t h = (8 * width + 2) / 3;
  return (h + 63) / 64 * 64;
}

namespace {

constexpr float kNegInf = -std::numeric_limits<float>::infinity();

std::string shape_of(const torch::Tensor& t) {
  if (!t.defined()) return "undefined";
  return fmt::format("[{}]", fmt::join(t.sizes().vec(), ", "));
}

torch::Tensor modulate(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale) {
  return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1);
}

// [B, N, H*Dh] -> [B, H, N, Dh]
torch::Tensor split_heads(const torch::Tensor& x, int64_t heads, int64_t head_dim) {
  return x.view({x.size(0), x.size(1), heads, head_dim}).transpose(1, 2);
}

// softmax(q k^T / sqrt(Dh)) v over keys where key_valid [B, N] is true; -> [B, Lq, H*Dh].
torch::Tensor attend(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                     const torch::Tensor& key_valid, ShardedDropout& drop) {
  const int64_t B = q.size(0), H = q.size(1), Lq = q.size(2), Dh = q.size(3), N = k.size(2);
  auto s = torch::matmul(q, k.transpose(-2, -1)) / std::sqrt(static_cast<double>(Dh));  // [B, H, Lq, N]
  s = s.masked_fill(key_valid.logical_not().view({B, 1, 1, N}), kNegInf);
  auto a = drop(torch::softmax(s, -1));
  return torch::matmul(a, v).transpose(1, 2).reshape({B, Lq, H * Dh});
}

// The block's own attention with extra key/value memory (eq. (15)): scores of the own
// keys s [B, H, Lq, N] (padding masked) and of the memory sm [B, H, Lq, M] (+ bias,
// masked). Joint: softmax over [s; sm] times [V; V^s]. Own normaliser: both exponentiated
// against logsumexp(s) only, so the own part is the block's unchanged attention and
// the memory adds sum_m exp(sm - lse) V^s_m (exponent clamped at 30 against overflow).
torch::Tensor attend_with_memory(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                                 const torch::Tensor& key_valid, const torch::Tensor& mk, const torch::Tensor& mv,
                                 const torch::Tensor& mem_valid, const torch::Tensor& bias, bool own_normaliser,
                                 ShardedDropout& drop) {
  const int64_t B = q.size(0), H = q.size(1), Lq = q.size(2), Dh = q.size(3), N = k.size(2), M = mk.size(2);
  const double scale = 1.0 / std::sqrt(static_cast<double>(Dh));
  auto s = (torch::matmul(q, k.transpose(-2, -1)) * scale).masked_fill(key_valid.logical_not().view({B, 1, 1, N}),
                                                                      kNegInf);
  auto sm = torch::matmul(q, mk.transpose(-2, -1)) * scale;  // [B, H, Lq, M]
  if (bias.defined()) sm = sm + bias.view({1, 1, Lq, M});
  sm = sm.masked_fill(mem_valid.logical_not().view({B, 1, 1, M}), kNegInf);
  torch::Tensor out;
  if (!own_normaliser) {
    auto a = drop(torch::softmax(torch::cat({s, sm}, -1), -1));
    out = torch::matmul(a, torch::cat({v, mv}, 2));
  } else {
    auto lse = torch::logsumexp(s, -1, true);
    auto a = drop(torch::softmax(s, -1));  // bit-identical to the memory-free block
    auto am = drop(torch::exp((sm - lse).clamp_max(30.0)));
    out = torch::matmul(a, v) + torch::matmul(am, mv);
  }
  return out.transpose(1, 2).reshape({B, Lq, H * Dh});
}

}  // namespace

// ---------------------------------------------------------------- attention

TokenSelfAttentionImpl::TokenSelfAttentionImpl(const TokenTransformerOptions& o)
    : heads(o.heads), head_dim(o.head_dim()), rope_base(o.rope_base) {
  qkv = register_module("qkv", nn::Linear(o.width, 3 * o.width));
  proj = register_module("proj", nn::Linear(o.width, o.width));
  q_norm = register_module("q_norm", RMSNorm(head_dim));
  k_norm = register_module("k_norm", RMSNorm(head_dim));
  attn_drop = register_module("attn_drop", ShardedDropout(o.dropout));
}

torch::Tensor TokenSelfAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& key_valid,
                                              const torch::Tensor& positions, const LayerKV* extra) {
  const int64_t B = x.size(0), L = x.size(1);
  auto qkv_ = qkv(x).view({B, L, 3, heads, head_dim}).permute({2, 0, 3, 1, 4});  // [3, B, H, L, Dh]
  auto q = apply_rope(q_norm(qkv_[0]), positions, rope_base);
  auto k = apply_rope(k_norm(qkv_[1]), positions, rope_base);
  auto v = qkv_[2];
  const auto& kv_valid = key_valid;
  if (extra && extra->defined()) {
    // eq. (15): softmax(Q [K; K^s]^T / sqrt(d)) [V; V^s], the memory after the block's own keys.
    const auto& ek = extra->k;
    const auto& ev = extra->v;
    if (ek.dim() != 3 || ek.size(0) != B || ek.size(2) != heads * head_dim || !ev.defined() ||
        ev.sizes() != ek.sizes())
      fail("extra key/value memory must be two [B={}, M, {}] tensors, got k {} and v {}", B, heads * head_dim,
           shape_of(ek), shape_of(ev));
    const int64_t M = ek.size(1);
    auto em = extra->mask.defined() ? extra->mask.to(x.device(), torch::kBool)
                                    : torch::ones({B, M}, torch::TensorOptions().dtype(torch::kBool).device(x.device()));
    if (em.sizes() != torch::IntArrayRef({B, M}))
      fail("extra key/value mask must be [B={}, M={}], got {}", B, M, shape_of(em));
    if (extra->bias.defined() && extra->bias.sizes() != torch::IntArrayRef({L, M}))
      fail("extra key/value bias must be [L={}, M={}], got {}", L, M, shape_of(extra->bias));
    return proj(attend_with_memory(q, k, v, kv_valid, split_heads(ek.to(k.dtype()), heads, head_dim),
                                   split_heads(ev.to(v.dtype()), heads, head_dim), em,
                                   extra->bias.defined() ? extra->bias.to(x.device(), k.dtype()) : torch::Tensor(),
                                   extra->own_normaliser, attn_drop));
  }
  return proj(attend(q, k, v, kv_valid, attn_drop));
}

TextCrossAttentionImpl::TextCrossAttentionImpl(const TokenTransformerOptions& o)
    : heads(o.heads), head_dim(o.head_dim()) {
  q = register_module("q", nn::Linear(o.width, o.width));
  kv = register_module("kv", nn::Linear(o.text_dim, 2 * o.width));
  proj = register_module("proj", nn::Linear(o.width, o.width));
  q_norm = register_module("q_norm", RMSNorm(head_dim));
  k_norm = register_module("k_norm", RMSNorm(head_dim));
  attn_drop = register_module("attn_drop", ShardedDropout(o.dropout));
}

torch::Tensor TextCrossAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& memory,
                                              const torch::Tensor& memory_valid) {
  auto qh = q_norm(split_heads(q(x), heads, head_dim));
  auto kvh = kv(memory).chunk(2, -1);
  auto kh = k_norm(split_heads(kvh[0].contiguous(), heads, head_dim));
  auto vh = split_heads(kvh[1].contiguous(), heads, head_dim);
  return proj(attend(qh, kh, vh, memory_valid.to(torch::kBool), attn_drop));
}

// ---------------------------------------------------------------- block

TokenBlockImpl::TokenBlockImpl(const TokenTransformerOptions& o) {
  norm1 = register_module("norm1", RMSNorm(o.width, false));
  norm2 = register_module("norm2", RMSNorm(o.width, false));
  norm3 = register_module("norm3", RMSNorm(o.width, false));
  attn = register_module("attn", TokenSelfAttention(o));
  cross = register_module("cross", TextCrossAttention(o));
  mlp = register_module("mlp", SwiGLU(o.width, o.resolved_mlp_hidden(), o.dropout));
  ada = register_module("ada", nn::Linear(o.width, 9 * o.width));
}

torch::Tensor TokenBlockImpl::forward(const torch::Tensor& x, const torch::Tensor& c, const TextContext& text,
                                      const torch::Tensor& key_valid, const torch::Tensor& positions,
                                      const LayerKV* extra) {
  auto m = ada(torch::silu(c)).chunk(9, -1);  // (shift, scale, gate) for self-attn, cross-attn, MLP
  auto h = x + m[2].unsqueeze(1) * attn(modulate(norm1(x), m[0], m[1]), key_valid, positions, extra);
  h = h + m[5].unsqueeze(1) * cross(modulate(norm2(h), m[3], m[4]), text.memory, text.memory_valid);
  return h + m[8].unsqueeze(1) * mlp(modulate(norm3(h), m[6], m[7]));
}

// ---------------------------------------------------------------- transformer

TokenTransformerImpl::TokenTransformerImpl(const TokenTransformerOptions& o) : opt(o) {
  if (o.width % o.heads != 0 || (o.width / o.heads) % 2 != 0)
    fail("token transformer: width {} must be heads ({}) times an even head size (RoPE)", o.width, o.heads);
  const int64_t d = o.width;
  embed = register_module("embed", nn::Embedding(o.num_codes + o.num_special, d));
  if (o.use_time)
    t_mlp = register_module("t_mlp", nn::Sequential(nn::Linear(o.freq_dim, d), nn::SiLU(), nn::Linear(d, d)));
  cond_proj = register_module("cond_proj", nn::Linear(o.text_dim, d));
  blocks = register_module("blocks", nn::ModuleList());
  for (int64_t i = 0; i < o.depth; ++i) blocks->push_back(TokenBlock(o));
  final_norm = register_module("final_norm", RMSNorm(d, false));
  final_ada = register_module("final_ada", nn::Linear(d, 2 * d));
  head = register_module("head", nn::Linear(d, o.num_codes));

  // DiT initialisation as the flow transformer: xavier linears, zero biases, zero
  // AdaLN modulations and head, so an untrained prior predicts the uniform distribution.
  torch::NoGradGuard ng;
  for (auto& m : modules(false))
    if (auto* lin = m->as<nn::Linear>()) {
      nn::init::xavier_uniform_(lin->weight);
      nn::init::zeros_(lin->bias);
    }
  nn::init::normal_(embed->weight, 0.0, 0.02);
  if (o.use_time)
    for (auto& m : t_mlp->modules(false))
      if (auto* lin = m->as<nn::Linear>()) nn::init::normal_(lin->weight, 0.0, 0.02);
  for (auto& b : *blocks) {
    auto* blk = b->as<TokenBlockImpl>();
    nn::init::zeros_(blk->ada->weight);
    nn::init::zeros_(blk->ada->bias);
  }
  for (auto* lin : {final_ada.get(), head.get()}) {
    nn::init::zeros_(lin->weight);
    nn::init::zeros_(lin->bias);
  }
}

torch::Tensor TokenTransformerImpl::conditioning(const torch::Tensor& t, const torch::Tensor& pooled) {
  auto c = cond_proj(pooled);
  if (opt.use_time) c = c + t_mlp->forward(timestep_sinusoid(t.to(pooled.device()) * opt.time_scale, opt.freq_dim));
  return c;
}

TokenTransformerOutput TokenTransformerImpl::forward(const torch::Tensor& ids, const torch::Tensor& t,
                                                     const TextContext& text, const torch::Tensor& valid,
                                                     const TokenTransformerHooks* hooks) {
  const int64_t B = ids.size(0), L = ids.size(1);
  const auto dev = ids.device();
  if (opt.use_time && !t.defined()) fail("token transformer: this network needs a time t per sample");
  const size_t depth = static_cast<size_t>(opt.depth);
  if (hooks && !hooks->extra_kv.empty() && hooks->extra_kv.size() != depth)
    fail("token transformer: {} extra key/value entries for {} blocks; give one per block (or none)",
         hooks->extra_kv.size(), depth);
  if (hooks && !hooks->block_residuals.empty() && hooks->block_residuals.size() != depth)
    fail("token transformer: {} block residuals for {} blocks; give one per block (or none)",
         hooks->block_residuals.size(), depth);
  auto pos = torch::arange(L, torch::TensorOptions().dtype(torch::kFloat32).device(dev));
  auto c = conditioning(opt.use_time ? t.to(dev, torch::kFloat32).reshape({-1}).expand({B}) : torch::Tensor(),
                        text.pooled);
  auto key_valid = valid.to(dev, torch::kBool);
  TokenTransformerOutput out;
  auto h = embed(ids);
  for (size_t l = 0; l < depth; ++l) {
    const LayerKV* extra = hooks && !hooks->extra_kv.empty() ? &hooks->extra_kv[l] : nullptr;
    h = blocks[l]->as<TokenBlockImpl>()->forward(h, c, text, key_valid, pos, extra);
    if (hooks && !hooks->block_residuals.empty() && hooks->block_residuals[l].defined())
      h = h + hooks->block_residuals[l];
    if (hooks && hooks->collect_hidden) out.hidden.push_back(h);
  }
  auto m = final_ada(torch::silu(c)).chunk(2, -1);
  out.logits = head(modulate(final_norm(h), m[0], m[1]));
  return out;
}

// ---------------------------------------------------------------- guidance

torch::Tensor guided_token_logits(TokenTransformerImpl& net, const torch::Tensor& ids, const torch::Tensor& t,
                                  const TextContext& text, const TextContext& null_text, const torch::Tensor& valid,
                                  double cfg_scale, const TokenTransformerHooks* hooks) {
  const HookGuidance g = hooks ? hooks->guidance : HookGuidance{};
  const int64_t B = ids.size(0);
  const auto dev = ids.device();
  const bool third = hooks && g.scale != 1.0;
  // Passes: (text, hooks), (null, hooks or none), [(text, none)].
  std::vector<bool> on = {true, !hooks || g.in_uncond};
  if (third) on.push_back(false);
  const int64_t P = static_cast<int64_t>(on.size());
  auto rep = [&](const torch::Tensor& x) {
    if (!x.defined()) return x;
    std::vector<torch::Tensor> parts(P, x);
    return torch::cat(parts);
  };
  TokenTransformerHooks hp;
  if (hooks) {
    // Pass p's hooks: the null-text pass takes hooks->null_text when the adapter's hooks
    // depend on the text, so it sees what training's dropped-text draws saw.
    const TokenTransformerHooks& nh = hooks->null_text ? *hooks->null_text : *hooks;
    if (nh.extra_kv.size() != hooks->extra_kv.size() || nh.block_residuals.size() != hooks->block_residuals.size())
      fail("token transformer: the null-text hooks have {} key/value entries and {} residuals, the text hooks {} and {}",
           nh.extra_kv.size(), nh.block_residuals.size(), hooks->extra_kv.size(), hooks->block_residuals.size());
    auto of_pass = [&](int64_t p) -> const TokenTransformerHooks& { return p == 1 ? nh : *hooks; };
    for (size_t l = 0; l < hooks->extra_kv.size(); ++l) {
      const LayerKV& kv = hooks->extra_kv[l];
      if (!kv.defined()) {
        hp.extra_kv.push_back(kv);
        continue;
      }
      std::vector<torch::Tensor> ks, vs, masks;
      for (int64_t p = 0; p < P; ++p) {
        const LayerKV& src = of_pass(p).extra_kv[l];
        if (!src.defined() || src.k.sizes() != kv.k.sizes())
          fail("token transformer: block {}'s null-text key/value memory does not match the text one's shape", l);
        const int64_t M = src.k.size(1);
        auto m = src.mask.defined() ? src.mask.to(dev, torch::kBool)
                                    : torch::ones({B, M}, torch::TensorOptions().dtype(torch::kBool).device(dev));
        ks.push_back(src.k);
        vs.push_back(src.v);
        masks.push_back(on[p] ? m : torch::zeros_like(m));
      }
      LayerKV r = kv;
      r.k = torch::cat(ks);
      r.v = torch::cat(vs);
      r.mask = torch::cat(masks);
      hp.extra_kv.push_back(r);  // bias has no batch dimension: shared
    }
    for (size_t l = 0; l < hooks->block_residuals.size(); ++l) {
      const auto& res = hooks->block_residuals[l];
      if (!res.defined()) {
        hp.block_residuals.push_back(res);
        continue;
      }
      std::vector<torch::Tensor> parts;
      for (int64_t p = 0; p < P; ++p) {
        const auto& src = of_pass(p).block_residuals[l];
        if (!src.defined() || src.sizes() != res.sizes())
          fail("token transformer: block {}'s null-text residual does not match the text one's shape", l);
        parts.push_back(on[p] ? src : torch::zeros_like(res));
      }
      hp.block_residuals.push_back(torch::cat(parts));
    }
  }
  std::vector<torch::Tensor> tt(P, t), texts_p, texts_m, texts_v;
  for (int64_t p = 0; p < P; ++p) {
    const TextContext& c = p == 1 ? null_text : text;
    texts_p.push_back(c.pooled);
    texts_m.push_back(c.memory);
    texts_v.push_back(c.memory_valid);
  }
  TextContext all{torch::cat(texts_p), torch::cat(texts_m), torch::cat(texts_v)};
  auto l = net.forward(rep(ids), t.defined() ? torch::cat(tt) : t, all, rep(valid), hooks ? &hp : nullptr).logits;
  auto lc = l.narrow(0, 0, B), lu = l.narrow(0, B, B);
  auto out = lu + cfg_scale * (lc - lu);
  if (third) out = out + (g.scale - 1.0) * (lc - l.narrow(0, 2 * B, B));
  return out;
}

}  // namespace mc
