// AnchorRoute's tokenised text-to-motion priors over a VQ tokenizer's codes: TMD
// (model type `tmd_prior`, metric discrete flow, §3.3) and the MoMask-style masked
// baseline (`masked_prior`): configs, the dual-context text encoder, the network bundle
// of final.pt and the corruption maths both the trainer and the samplers use.
#pragma once
#include <string>
#include <vector>

#include "core/config.h"
#include "data/motion_set.h"
#include "models/token_transformer.h"
#include "models/vq_tokenizer.h"

namespace mc {

// `model:` section shared by both token priors; the subclasses pick the type.
struct TokenPriorConfig : Config {
  int depth = 8;
  int width = 384;
  int heads = 6;
  int mlp_hidden = 0;
  double dropout = 0.1;
  double cond_drop = 0.1;
  // Text encoder (trained jointly, as the flow prior's; no pretrained CLIP here).
  int text_width = 256;
  int text_layers = 2;
  int text_heads = 4;
  int text_ff = 512;
  double text_dropout = 0.1;
  int max_words = 32;
  // The tokenizer: a finished run, or a tokenizer training config run on demand.
  std::string tokenizer_run;
  std::string tokenizer_config = "configs/tokenizer/vq_tiny.yaml";
  std::vector<std::string> tokenizer_overrides;
  std::vector<double> eval_t = {0.1, 0.3, 0.5, 0.7, 0.9};

  void visit(FieldVisitor& v) override;
  std::string validate() const override;
  virtual bool is_tmd() const = 0;
  TokenTransformerOptions transformer_options(int64_t num_codes) const;

 protected:
  virtual void visit_extra(FieldVisitor& v) { (void)v; }
};

struct TmdPriorConfig : TokenPriorConfig {
  double beta_c = 3.0;  // beta(t) = c (t / (1 - t))^a, eq. (18)
  double beta_a = 0.9;
  double t_eps = 1e-3;  // training times t ~ U[0, 1 - t_eps) keep beta finite
  bool is_tmd() const override { return true; }

 protected:
  void visit_extra(FieldVisitor& v) override;
};

struct MaskedPriorConfig : TokenPriorConfig {
  bool is_tmd() const override { return false; }
};

// ---------------------------------------------------------------- TMD maths

// eq. (18): beta(t) = c (t / (1 - t))^a; t [..] in [0, 1).
torch::Tensor tmd_beta(const torch::Tensor& t, double c, double a);
// d beta / dt = c a (t / (1 - t))^(a - 1) / (1 - t)^2; t in (0, 1).
torch::Tensor tmd_beta_prime(const torch::Tensor& t, double c, double a);
// eq. (18): q_t(i | x1) = softmax_i(-beta d(i, x1)) for x1 [...] int64 and beta
// broadcastable to x1's shape; dist [K, K] symmetric. -> [..., K].
torch::Tensor tmd_path_probs(const torch::Tensor& dist, const torch::Tensor& x1, const torch::Tensor& beta);

// ---------------------------------------------------------------- masking

// MoMask's training mask count: round(n cos(pi t / 2)), at least 1 and at most n (n >= 1).
int64_t masked_train_count(int64_t n, double t);
// Tokens masked at sampling step k of `steps` (MoMask: t_k = k / (steps - 1) on the same
// cosine, so step 0 masks all n and the last step re-predicts one).
int64_t masked_sample_count(int64_t n, int step, int steps);

// ---------------------------------------------------------------- networks

// Word embeddings + positions + a transformer encoder: the per-word states are the
// sequence-level text memory, their masked mean (LayerNorm, Linear) the pooled vector.
struct TokenTextEncoderImpl : torch::nn::Module {
  TokenTextEncoderImpl(int vocab_size, const TokenPriorConfig& c);
  TextContext forward(const torch::Tensor& ids, const torch::Tensor& lengths);  // [B, W], [B]
  torch::nn::Embedding embedding{nullptr}, position{nullptr};
  torch::nn::TransformerEncoder encoder{nullptr};
  torch::nn::LayerNorm norm{nullptr};
  torch::nn::Linear out{nullptr};
};
TORCH_MODULE(TokenTextEncoder);

// Everything final.pt holds: text encoder, null condition, transformer and the
// tokenizer's K x K distance table it was trained with.
struct TokenPriorNetImpl : torch::nn::Module {
  TokenPriorNetImpl(int vocab_size, int64_t num_codes, const TokenPriorConfig& c);
  TextContext encode_text(const torch::Tensor& ids, const torch::Tensor& lengths);
  // The null condition (CFG / condition dropout): the learned null pooled vector and a
  // one-word learned null memory, padded to W words, for B samples.
  TextContext null_context(int64_t B, int64_t W);
  // Rows where drop [B] is true replaced by the null condition.
  TextContext drop_condition(const TextContext& c, const torch::Tensor& drop);
  TokenTextEncoder text{nullptr};
  TokenTransformer transformer{nullptr};
  torch::Tensor null_text;    // [text_width]
  torch::Tensor null_memory;  // [text_width]
  torch::Tensor distance;     // [K, K] buffer: d(i, j) of eq. (17)
};
TORCH_MODULE(TokenPriorNet);

// Concatenates two contexts along the batch (widths must agree).
TextContext cat_contexts(const TextContext& a, const TextContext& b);

// Every clip of a motion set as tokens: whole clips in the tokenizer's own
// normalisation, padded to a multiple of its stride (padding frames zeroed).
struct TokenizedClips {
  torch::Tensor tokens;   // [N, ceil(t_max / stride)] int64 CPU; past a clip's length: codes of padding
  torch::Tensor lengths;  // [N] int64 valid tokens = ceil(frames / stride)
};
TokenizedClips tokenize_clips(VqTokenizerImpl& tokenizer, const MotionSet& set, torch::Device device);

// run_train(config, overrides).run_dir, leaving torch's CPU generator state and thread
// count as they were (a run that trains reseeds both; a finished one does not).
std::string train_on_demand(const std::string& config, const std::vector<std::string>& overrides);

// The run directory of the tokenizer a token-prior config names (tokenizer_run, or
// tokenizer_config trained on demand with run_train).
std::string resolve_tokenizer_run(const TokenPriorConfig& c);

}  // namespace mc
