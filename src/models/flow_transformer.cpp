// The ACMDM-style flow transformer: PS22 tokens, AdaLN-Zero blocks (RMSNorm,
// q/k norm, RoPE, SwiGLU), key padding; DiT initialisation with zeroed modulations.
#include "models/flow_transformer.h"

#include <cmath>
#include <limits>

namespace mc {
namespace nn = torch::nn;

// ---------------------------------------------------------------- pieces

RMSNormImpl::RMSNormImpl(int64_t dim, bool affine, double eps_) : eps(eps_) {
  if (affine) weight = register_parameter("weight", torch::ones({dim}));
}

torch::Tensor RMSNormImpl::forward(const torch::Tensor& x) {
  auto y = x * torch::rsqrt(x.pow(2).mean(-1, true) + eps);
  return weight.defined() ? y * weight : y;
}

torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& positions, double base) {
  const int64_t D = x.size(-1), half = D / 2;
  TORCH_CHECK(D % 2 == 0, "RoPE needs an even head dimension, got ", D);
  auto opts = torch::TensorOptions().dtype(torch::kFloat32).device(x.device());
  auto inv_freq = torch::pow(base, -torch::arange(0, half, opts) * (2.0 / D));  // [D/2]
  auto ang = positions.to(opts).unsqueeze(-1) * inv_freq;                          // [T, D/2]
  auto cos = ang.cos().to(x.dtype()), sin = ang.sin().to(x.dtype());
  auto x1 = x.narrow(-1, 0, half), x2 = x.narrow(-1, half, half);
  return torch::cat({x1 * cos - x2 * sin, x1 * sin + x2 * cos}, -1);
}

torch::Tensor timestep_sinusoid(const torch::Tensor& t, int64_t dim, double max_period) {
  const int64_t half = dim / 2;
  auto opts = torch::TensorOptions().dtype(torch::kFloat32).device(t.device());
  auto freqs = torch::exp(-std::log(max_period) * torch::arange(0, half, opts) / half);
  auto args = t.to(torch::kFloat32).unsqueeze(-1) * freqs;
  auto emb = torch::cat({args.cos(), args.sin()}, -1);
  if (dim % 2) emb = torch::cat({emb, torch::zeros_like(emb.narrow(-1, 0, 1))}, -1);
  return emb;
}

int64_t FlowTransformerOptions::resolved_mlp_hidden() const {
  if (mlp_hidden > 0) return mlp_hidden;
  int64_t h = (8 * width + 2) / 3;
  return (h + 63) / 64 * 64;
}

// ---------------------------------------------------------------- attention

FlowAttentionImpl::FlowAttentionImpl(const FlowTransformerOptions& o)
    : heads(o.heads), head_dim(o.width / o.heads), rope_base(o.rope_base) {
  TORCH_CHECK(o.width % o.heads == 0, "width ", o.width, " is not a multiple of heads ", o.heads);
  qkv = register_module("qkv", nn::Linear(o.width, 3 * o.width));
  proj = register_module("proj", nn::Linear(o.width, o.width));
  q_norm = register_module("q_norm", RMSNorm(head_dim));
  k_norm = register_module("k_norm", RMSNorm(head_dim));
  attn_drop = register_module("attn_drop", ShardedDropout(o.dropout));
}

std::array<torch::Tensor, 3> FlowAttentionImpl::project(const torch::Tensor& x, const torch::Tensor& positions) {
  const int64_t B = x.size(0), T = x.size(1);
  auto qkv_ = qkv(x).view({B, T, 3, heads, head_dim}).permute({2, 0, 3, 1, 4});  // [3, B, H, T, Dh]
  // Normalising q and k before the rotation bounds the logits (stable with bf16 / high lr).
  auto q = apply_rope(q_norm(qkv_[0]), positions, rope_base);
  auto k = apply_rope(k_norm(qkv_[1]), positions, rope_base);
  return {q, k, qkv_[2]};
}

torch::Tensor FlowAttentionImpl::scores(const torch::Tensor& x, const torch::Tensor& positions) {
  auto [q, k, v] = project(x, positions);
  return torch::matmul(q, k.transpose(-2, -1)) / std::sqrt(static_cast<double>(head_dim));
}

torch::Tensor FlowAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& key_valid,
                                         const torch::Tensor& positions) {
  const int64_t B = x.size(0), T = x.size(1);
  auto [q, k, v] = project(x, positions);
  auto s = torch::matmul(q, k.transpose(-2, -1)) / std::sqrt(static_cast<double>(head_dim));  // [B, H, T, T]
  s = s.masked_fill(key_valid.logical_not().view({B, 1, 1, T}), -std::numeric_limits<float>::infinity());
  auto a = attn_drop(torch::softmax(s, -1));
  auto out = torch::matmul(a, v).transpose(1, 2).reshape({B, T, heads * head_dim});
  return proj(out);
}

SwiGLUImpl::SwiGLUImpl(int64_t dim, int64_t hidden, double dropout) {
  w1 = register_module("w1", nn::Linear(dim, hidden));
  w3 = register_module("w3", nn::Linear(dim, hidden));
  w2 = register_module("w2", nn::Linear(hidden, dim));
  drop = register_module("drop", ShardedDropout(dropout));
}

torch::Tensor SwiGLUImpl::forward(const torch::Tensor& x) { return w2(drop(torch::silu(w1(x)) * w3(x))); }

// ---------------------------------------------------------------- blocks

namespace {
torch::Tensor modulate(const torch::Tensor& x, const torch::Tensor& shift, const torch::Tensor& scale) {
  return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1);
}
}  // namespace

FlowBlockImpl::FlowBlockImpl(const FlowTransformerOptions& o) {
  // No affine weights: AdaLN's scale takes their place.
  norm1 = register_module("norm1", RMSNorm(o.width, false));
  norm2 = register_module("norm2", RMSNorm(o.width, false));
  attn = register_module("attn", FlowAttention(o));
  mlp = register_module("mlp", SwiGLU(o.width, o.resolved_mlp_hidden(), o.dropout));
  ada = register_module("ada", nn::Linear(o.width, 6 * o.width));
}

torch::Tensor FlowBlockImpl::forward(const torch::Tensor& x, const torch::Tensor& c, const torch::Tensor& key_valid,
                                     const torch::Tensor& positions) {
  auto m = ada(torch::silu(c)).chunk(6, -1);  // shift, scale, gate for attention then MLP
  auto h = x + m[2].unsqueeze(1) * attn(modulate(norm1(x), m[0], m[1]), key_valid, positions);
  return h + m[5].unsqueeze(1) * mlp(modulate(norm2(h), m[3], m[4]));
}

// ---------------------------------------------------------------- transformer

FlowTransformerImpl::FlowTransformerImpl(const FlowTransformerOptions& o) : opt(o) {
  const int64_t d = o.width, io = o.num_joints * 3, oc = o.resolved_out_channels();
  TORCH_CHECK(o.temporal_kernel >= 1 && o.temporal_kernel % 2 == 1, "temporal_kernel must be odd, got ",
              o.temporal_kernel);
  const int64_t k = o.temporal_kernel;
  if (k == 1) {
    embed = register_module("embed", nn::Linear(io, d));
  } else {
    embed_conv = register_module("embed_conv", nn::Conv1d(nn::Conv1dOptions(io, d, k).padding(k / 2)));
    head_conv = register_module("head_conv", nn::Conv1d(nn::Conv1dOptions(d, oc, k).padding(k / 2)));
  }
  t_mlp = register_module("t_mlp", nn::Sequential(nn::Linear(o.freq_dim, d), nn::SiLU(), nn::Linear(d, d)));
  cond_proj = register_module("cond_proj", nn::Linear(o.cond_dim, d));
  blocks = register_module("blocks", nn::ModuleList());
  for (int64_t i = 0; i < o.depth; ++i) blocks->push_back(FlowBlock(o));
  final_norm = register_module("final_norm", RMSNorm(d, false));
  final_ada = register_module("final_ada", nn::Linear(d, 2 * d));
  if (k == 1) head = register_module("head", nn::Linear(d, oc));

  // DiT initialisation: xavier linears with zero bias, N(0, 0.02) timestep MLP,
  // zero modulations and output head so the initial network outputs exactly 0.
  torch::NoGradGuard ng;
  for (auto& m : modules(false))
    if (auto* lin = m->as<nn::Linear>()) {
      nn::init::xavier_uniform_(lin->weight);
      nn::init::zeros_(lin->bias);
    }
  for (auto& m : t_mlp->modules(false))
    if (auto* lin = m->as<nn::Linear>()) nn::init::normal_(lin->weight, 0.0, 0.02);
  for (auto& b : *blocks) {
    auto* blk = b->as<FlowBlockImpl>();
    nn::init::zeros_(blk->ada->weight);
    nn::init::zeros_(blk->ada->bias);
  }
  nn::init::zeros_(final_ada->weight);
  nn::init::zeros_(final_ada->bias);
  if (head) {
    nn::init::zeros_(head->weight);
    nn::init::zeros_(head->bias);
  } else {
    nn::init::xavier_uniform_(embed_conv->weight);
    nn::init::zeros_(embed_conv->bias);
    nn::init::zeros_(head_conv->weight);
    nn::init::zeros_(head_conv->bias);
  }
}

torch::Tensor FlowTransformerImpl::embed_tokens(const torch::Tensor& x, const torch::Tensor& valid) {
  const int64_t B = x.size(0), T = x.size(1), J = x.size(2);
  auto flat = x.reshape({B, T, J * 3});
  if (embed) return embed(flat);
  flat = flat * valid.unsqueeze(-1).to(flat.dtype());
  return embed_conv(flat.transpose(1, 2)).transpose(1, 2);
}

torch::Tensor FlowTransformerImpl::output(const torch::Tensor& h, const torch::Tensor& c, const torch::Tensor& valid) {
  const int64_t B = h.size(0), T = h.size(1);
  auto m = final_ada(torch::silu(c)).chunk(2, -1);
  auto z = modulate(final_norm(h), m[0], m[1]);
  torch::Tensor out;
  if (head) {
    out = head(z);
  } else {
    z = z * valid.unsqueeze(-1).to(z.dtype());
    out = head_conv(z.transpose(1, 2)).transpose(1, 2);
  }
  if (opt.resolved_out_channels() != opt.num_joints * 3) return out;
  return out.reshape({B, T, opt.num_joints, 3});
}

torch::Tensor FlowTransformerImpl::conditioning(const torch::Tensor& t, const torch::Tensor& cond) {
  auto te = t_mlp->forward(timestep_sinusoid(t * opt.time_scale, opt.freq_dim));
  return te + cond_proj(cond);
}

FlowTransformerOutput FlowTransformerImpl::forward(const torch::Tensor& x, const torch::Tensor& t,
                                                   const torch::Tensor& cond, const torch::Tensor& mask,
                                                   const torch::Tensor& positions) {
  const int64_t B = x.size(0), T = x.size(1), J = x.size(2);
  TORCH_CHECK(J == opt.num_joints && x.size(3) == 3, "flow transformer expects [B, T, ", opt.num_joints,
              ", 3] joints, got ", x.sizes());
  auto pos = positions.defined() ? positions.to(x.device(), torch::kFloat32)
                                 : torch::arange(T, torch::TensorOptions().dtype(torch::kFloat32).device(x.device()));
  auto c = conditioning(t.to(x.device()).expand({B}), cond);
  auto key_valid = mask.to(x.device(), torch::kBool);
  auto h = embed_tokens(x, key_valid);
  for (auto& b : *blocks) h = b->as<FlowBlockImpl>()->forward(h, c, key_valid, pos);
  return {output(h, c, key_valid)};
}

}  // namespace mc
