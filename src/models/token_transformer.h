// The bidirectional token transformer behind AnchorRoute's tokenised priors (TMD and
// the MoMask-style masked baseline): dual-context text conditioning (§3.2) and the hooks
// AnchorKV (eqs. (14)-(15)) and ControlNet-style adapters plug into.
#pragma once
#include <torch/torch.h>

#include <memory>
#include <vector>

#include "models/flow_transformer.h"

namespace mc {

struct TokenTransformerOptions {
  int64_t num_codes = 512;   // K: the tokenizer's codebook; logits cover these ids only
  int64_t num_special = 1;   // extra input ids after the codes; id K is [MASK] (mask_id())
  int64_t depth = 8;
  int64_t width = 384;
  int64_t heads = 6;
  int64_t mlp_hidden = 0;    // 0 = 8/3 * width rounded up to 64 (as FlowTransformerOptions)
  double dropout = 0.1;      // attention probabilities and MLP hidden
  int64_t text_dim = 256;    // size of the pooled sentence vector and of the text memory
  bool use_time = true;      // TMD: yes; the masked baseline has no time input
  int64_t freq_dim = 256;
  double time_scale = 1000;  // t in [0, 1] is scaled before the sinusoid
  double rope_base = 10000;
  int64_t resolved_mlp_hidden() const;
  int64_t head_dim() const { return width / heads; }
};

// The text branch's output (§3.2): a pooled sentence vector and the sequence-level memory.
struct TextContext {
  torch::Tensor pooled;        // [B, text_dim]
  torch::Tensor memory;        // [B, W, text_dim] per-word states
  torch::Tensor memory_valid;  // [B, W] bool, true on real words; every row needs >= 1 true
};

// Extra attention memory for one block (AnchorKV, eq. (15)): keys and values already
// projected to the block's attention space, [B, M, width] each (split into heads as
// head h = channels [h*head_dim, (h+1)*head_dim)). They are appended to the block's
// own keys/values as they are: no RoPE is added here (an adapter may rotate its keys
// itself) and no q/k RMS-norm (the block's own keys are per-head RMS-normalised times a
// learned weight, so an adapter should produce keys of similar scale). mask [B, M] bool,
// true = attend; undefined = all attend. M may be 0.
//   bias: optional additive score bias of the memory, [L, M] (query token x memory slot;
//     -inf = never attend; no batch dimension), e.g. AnchorKV's token-aligned window.
//   own_normaliser: false = eq. (15), one softmax over [K; K^s]; true = eq. (15)'s
//     numerator over the normaliser of the block's own keys only, i.e. the block's own
//     attention unchanged plus sum_m exp(s_nm - LSE_n(own)) V^s_m: zero memory values
//     then leave the block exactly as it was (docs/choices.md, "AnchorRoute: adapters").
struct LayerKV {
  torch::Tensor k, v, mask;
  torch::Tensor bias;
  bool own_normaliser = false;
  bool defined() const { return k.defined(); }
};

// How classifier-free guidance treats adapter hooks (AnchorRoute's anchors).
struct HookGuidance {
  bool in_uncond = true;  // the unconditional (null-text) pass gets the hooks too; false = the frozen prior's
  double scale = 1.0;     // s_a; != 1 adds a pass (text, no hooks) and (s_a - 1)(l_cH - l_c0)
};

// Optional adapter hooks of one forward. Empty vectors = no hook; otherwise one entry
// per block (undefined entries are skipped).
struct TokenTransformerHooks {
  std::vector<LayerKV> extra_kv;               // appended to block l's self-attention keys/values
  std::vector<torch::Tensor> block_residuals;  // [B, L, width] added to block l's output (ControlNet)
  bool collect_hidden = false;                 // fill TokenTransformerOutput::hidden
  HookGuidance guidance;                       // read by guided_token_logits only
  // The hooks of the null-text pass, when they depend on the text (an adapter with dual
  // context reads it): guided_token_logits gives that pass these instead, so it sees what
  // training's dropped-text draws saw. Null = the same hooks in every pass.
  std::shared_ptr<const TokenTransformerHooks> null_text;
};



struct TokenTransformerOutput {
  torch::Tensor logits;               // [B, L, num_codes]
  std::vector<torch::Tensor> hidden;  // per block output (after its residual hook), [B, L, width]
};

// Self-attention with q/k RMS-norm, RoPE over token positions, key padding and the
// optional extra key/value memory.
struct TokenSelfAttentionImpl : torch::nn::Module {
  explicit TokenSelfAttentionImpl(const TokenTransformerOptions& o);
  // x [B, L, d]; key_valid [B, L] bool; positions [L] float.
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& key_valid, const torch::Tensor& positions,
                        const LayerKV* extra = nullptr);
  torch::nn::Linear qkv{nullptr}, proj{nullptr};
  RMSNorm q_norm{nullptr}, k_norm{nullptr};
  ShardedDropout attn_drop{nullptr};
  int64_t heads, head_dim;
  double rope_base;
};
TORCH_MODULE(TokenSelfAttention);

// Cross-attention of the motion tokens to the text memory (the sequence-level branch).
struct TextCrossAttentionImpl : torch::nn::Module {
  explicit TextCrossAttentionImpl(const TokenTransformerOptions& o);
  // x [B, L, d]; memory [B, W, text_dim]; memory_valid [B, W] bool.
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& memory, const torch::Tensor& memory_valid);
  torch::nn::Linear q{nullptr}, kv{nullptr}, proj{nullptr};
  RMSNorm q_norm{nullptr}, k_norm{nullptr};
  ShardedDropout attn_drop{nullptr};
  int64_t heads, head_dim;
};
TORCH_MODULE(TextCrossAttention);

// AdaLN-Zero block: self-attention, text cross-attention, SwiGLU MLP, each as
// x + gate * f(norm(x) * (1 + scale) + shift) with shift/scale/gate from c.
struct TokenBlockImpl : torch::nn::Module {
  explicit TokenBlockImpl(const TokenTransformerOptions& o);
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& c, const TextContext& text,
                        const torch::Tensor& key_valid, const torch::Tensor& positions,
                        const LayerKV* extra = nullptr);
  RMSNorm norm1{nullptr}, norm2{nullptr}, norm3{nullptr};
  TokenSelfAttention attn{nullptr};
  TextCrossAttention cross{nullptr};
  SwiGLU mlp{nullptr};
  torch::nn::Linear ada{nullptr};  // d -> 9d
};
TORCH_MODULE(TokenBlock);

struct TokenTransformerImpl : torch::nn::Module {
  explicit TokenTransformerImpl(const TokenTransformerOptions& o);
  // ids [B, L] int64 in [0, num_codes + num_special); t [B] in [0, 1] (ignored and may
  // be undefined when !use_time); text: the dual context (or the null one); valid [B, L]
  // bool, true on real tokens (padding is masked out as keys; its logits are
  // meaningless); hooks: adapters (nullptr = none).
  TokenTransformerOutput forward(const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                                 const torch::Tensor& valid, const TokenTransformerHooks* hooks = nullptr);
  // The AdaLN vector c [B, d]: MLP(sinusoid(t)) + Linear(pooled) (the pooled sentence
  // vector conditions every block through the time embedding), or Linear(pooled) alone.
  torch::Tensor conditioning(const torch::Tensor& t, const torch::Tensor& pooled);
  int64_t mask_id() const { return opt.num_codes; }

  TokenTransformerOptions opt;
  torch::nn::Embedding embed{nullptr};    // (K + specials) -> d
  torch::nn::Sequential t_mlp{nullptr};   // freq_dim -> d -> d (only when use_time)
  torch::nn::Linear cond_proj{nullptr};   // text_dim -> d
  torch::nn::ModuleList blocks{nullptr};
  RMSNorm final_norm{nullptr};
  torch::nn::Linear final_ada{nullptr};   // d -> 2d, zero-init
  torch::nn::Linear head{nullptr};        // d -> K, zero-init
};
TORCH_MODULE(TokenTransformer);

// Classifier-free guidance over one doubled (or tripled) forward of `net`:
//   l = l_u + s (l_cH - l_u) + (s_a - 1)(l_cH - l_c0),
// l_cH = (text, hooks), l_u = (null text, hooks if in_uncond else none), l_c0 = (text,
// no hooks), the last term only when s_a != 1 (s_a, in_uncond: hooks->guidance) (ACMDM's three-pass control guidance with
// the anchors as the control). "No hooks" rows have their memory masked out and zero
// residuals, which is exactly the network without hooks. With the defaults it is the
// two-pass l_u + s (l_cH - l_u), hooks in both halves. null_text: the null context of
// the same B rows and memory width.
torch::Tensor guided_token_logits(TokenTransformerImpl& net, const torch::Tensor& ids, const torch::Tensor& t,
                                  const TextContext& text, const TextContext& null_text, const torch::Tensor& valid,
                                  double cfg_scale, const TokenTransformerHooks* hooks);

}  // namespace mc
