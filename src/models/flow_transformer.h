// The ACMDM-style velocity network of the flow prior (reference-facts §2): one token
// per frame holding all joints (PS22), AdaLN-Zero blocks with RMSNorm, q/k norm, 1D RoPE.
#pragma once
#include <torch/torch.h>

#include <array>

#include "models/sharded_dropout.h"

namespace mc {

// Root-mean-square layer norm (LibTorch 1.13 has none): x / rms(x) * weight.
struct RMSNormImpl : torch::nn::Module {
  RMSNormImpl(int64_t dim, bool affine = true, double eps = 1e-6);
  torch::Tensor forward(const torch::Tensor& x);
  torch::Tensor weight;  // undefined when !affine
  double eps;
};
TORCH_MODULE(RMSNorm);

// Rotary position embedding over the last dim (even size D) of x [..., T, D] at
// `positions` [T] (float): pairs (i, i + D/2) rotate by pos * base^(-2i/D), so
// <rope(q, m), rope(k, n)> depends on m - n only.
torch::Tensor apply_rope(const torch::Tensor& x, const torch::Tensor& positions, double base = 10000.0);

// Sinusoidal embedding of t [B] (any scale) to `dim` features (cos half, sin half).
torch::Tensor timestep_sinusoid(const torch::Tensor& t, int64_t dim, double max_period = 10000.0);

struct FlowTransformerOptions {
  int64_t num_joints = 22;
  int64_t depth = 8;
  int64_t width = 512;
  int64_t heads = 8;
  // SwiGLU hidden size; 0 = 8/3 * width rounded up to a multiple of 64, which keeps
  // the parameter count of the reference's 4x GELU MLP (three matrices instead of two).
  int64_t mlp_hidden = 0;
  double dropout = 0.0;      // attention probabilities and MLP hidden
  int64_t cond_dim = 256;    // size of the pooled text vector
  int64_t freq_dim = 256;    // sinusoidal timestep features
  double time_scale = 1000;  // t in [0, 1] is scaled before the sinusoid so its frequencies resolve it
  double rope_base = 10000;
  // Frames the input embedding and the output head see (odd). 1 = ACMDM's
  // per-frame Linear (PS22); k > 1 = a temporal convolution over k frames, which
  // lets the first and last layers compare neighbouring frames (noise is white in
  // time, motion is not) at a cost of k x those two layers.
  int64_t temporal_kernel = 1;
  // Channels the head writes per frame; 0 = num_joints * 3 (the output is then
  // [B, T, J, 3], else [B, T, out_channels]: the flow prior's kinematic head).
  int64_t out_channels = 0;
  int64_t resolved_mlp_hidden() const;
  int64_t resolved_out_channels() const { return out_channels > 0 ? out_channels : num_joints * 3; }
};

// Multi-head self-attention with q/k RMS-normalisation, RoPE and key padding.
struct FlowAttentionImpl : torch::nn::Module {
  explicit FlowAttentionImpl(const FlowTransformerOptions& o);
  // x [B, T, d]; key_valid [B, T] bool (true = real frame); positions [T] float.
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& key_valid, const torch::Tensor& positions);
  // Pre-softmax scores [B, H, T, T] (no mask): exposed for the RoPE test.
  torch::Tensor scores(const torch::Tensor& x, const torch::Tensor& positions);
  torch::nn::Linear qkv{nullptr}, proj{nullptr};
  RMSNorm q_norm{nullptr}, k_norm{nullptr};
  ShardedDropout attn_drop{nullptr};
  int64_t heads, head_dim;
  double rope_base;

 private:
  std::array<torch::Tensor, 3> project(const torch::Tensor& x, const torch::Tensor& positions);
};
TORCH_MODULE(FlowAttention);

struct SwiGLUImpl : torch::nn::Module {
  SwiGLUImpl(int64_t dim, int64_t hidden, double dropout);
  torch::Tensor forward(const torch::Tensor& x);  // w2(silu(w1 x) * w3 x)
  torch::nn::Linear w1{nullptr}, w3{nullptr}, w2{nullptr};
  ShardedDropout drop{nullptr};
};
TORCH_MODULE(SwiGLU);

// x + gate * f(norm(x) * (1 + scale) + shift), shift/scale/gate from the condition
// through a zero-initialised Linear (AdaLN-Zero: every block starts as identity).
struct FlowBlockImpl : torch::nn::Module {
  explicit FlowBlockImpl(const FlowTransformerOptions& o);
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& c, const torch::Tensor& key_valid,
                        const torch::Tensor& positions);
  RMSNorm norm1{nullptr}, norm2{nullptr};
  FlowAttention attn{nullptr};
  SwiGLU mlp{nullptr};
  torch::nn::Linear ada{nullptr};  // d -> 6d
};
TORCH_MODULE(FlowBlock);

struct FlowTransformerOutput {
  // [B, T, J, 3], or [B, T, out_channels] when the options set another channel count
  // (the owner decodes it: FlowPriorNetImpl::to_velocity).
  torch::Tensor velocity;
};

struct FlowTransformerImpl : torch::nn::Module {
  explicit FlowTransformerImpl(const FlowTransformerOptions& o);
  // x [B, T, J, 3] normalised; t [B] in [0, 1]; cond [B, cond_dim] pooled text (or
  // the null embedding); mask [B, T] bool, true on valid frames (padding is masked
  // out of attention as keys; its outputs are meaningless); positions [T] float
  // frame indices (default 0..T-1).
  FlowTransformerOutput forward(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& cond,
                                const torch::Tensor& mask, const torch::Tensor& positions = {});
  // The AdaLN conditioning vector c = MLP(sinusoid(t)) + Linear(cond), [B, d].
  torch::Tensor conditioning(const torch::Tensor& t, const torch::Tensor& cond);
  // Tokens [B, T, d] of x [B, T, J, 3]; padded frames are zeroed first so a
  // temporal kernel never reads them. valid [B, T] bool.
  torch::Tensor embed_tokens(const torch::Tensor& x, const torch::Tensor& valid);
  // The output [B, T, J, 3] of the last hidden states h [B, T, d] under condition c.
  torch::Tensor output(const torch::Tensor& h, const torch::Tensor& c, const torch::Tensor& valid);

  FlowTransformerOptions opt;
  torch::nn::Linear embed{nullptr};                       // J*3 -> d
  torch::nn::Sequential t_mlp{nullptr};                   // freq_dim -> d -> d
  torch::nn::Linear cond_proj{nullptr};                   // cond_dim -> d
  torch::nn::ModuleList blocks{nullptr};
  RMSNorm final_norm{nullptr};
  torch::nn::Linear final_ada{nullptr};                   // d -> 2d, zero-init
  torch::nn::Linear head{nullptr};                        // d -> J*3 (or out_channels), zero-init
  torch::nn::Conv1d embed_conv{nullptr}, head_conv{nullptr};  // temporal_kernel > 1 in place of embed / head
};
TORCH_MODULE(FlowTransformer);

}  // namespace mc
