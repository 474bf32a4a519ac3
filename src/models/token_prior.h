// AnchorRoute's tokenised text-to-motion priors over a VQ tokenizer's codes: TMD
// (model type `tmd_prior`, metric discrete flow, §3.3) and the MoMask-style masked
// baseline (`masked_prior`): configs, the dual-context text encoder, the network bundle
// of final.pt, the corruption maths both the trainer and the samplers use, and the
// trained prior loaded from its run directory with its tokenizer (TokenPrior: CFG on
// logits, decoding to world joints).
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "core/trained_runs.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"
#include "models/text_encoder.h"
#include "models/token_transformer.h"
#include "models/vq_tokenizer.h"

namespace mc {

// `model:` section shared by both token priors; the subclasses pick the type.
// The text encoder's text_* fields (TextEncoderFields) are trained jointly, as the
// flow prior's (no pretrained CLIP here).
struct TokenPriorConfig : Config, TextEncoderFields, DeclaresDependencies {
  int depth = 8;
  int width = 384;
  int heads = 6;
  int mlp_hidden = 0;
  double dropout = 0.1;
  double cond_drop = 0.1;
  // The tokenizer: a finished run, or a tokenizer training config run on demand.
  std::string tokenizer_run;
  std::string tokenizer_config = "configs/tokenizer/vq_tiny.yaml";
  std::vector<std::string> tokenizer_overrides;
  std::vector<double> eval_t = {0.1, 0.3, 0.5, 0.7, 0.9};

  void visit(FieldVisitor& v) override;
  void dependencies(DependencyVisitor& d) override {
    d("model.tokenizer", tokenizer_run, tokenizer_config, tokenizer_overrides);
  }
  std::string validate() const override;
  virtual bool is_tmd() const = 0;
  TokenTransformerOptions transformer_options(int64_t num_codes) const;

 protected:
  virtual void visit_extra(FieldVisitor& v) { (void)v; }
};

// `model.path` of a TMD prior: how the metric d of eq. (17) is built from the
// codebook and calibrated to it. Absent from the dump at the paper's setting (plain
// cosine, no calibration), so priors trained before it keep their config hash.
struct TmdPathConfig : Config {
  std::string metric = "cosine";      // cosine | centered_cosine | whitened_cosine
  std::string calibration = "none";   // none | q_target
  double target_q = 0.5;              // q_target: mean over codes of q_t(x1 | x1) ...
  double target_t = 0.9;              // ... reaches target_q at this t
  void visit(FieldVisitor& v) override {
    v("metric", metric,
      "codebook vectors the cosine of eq. (17) reads: cosine (the paper: raw codes), centered_cosine (codebook mean "
      "removed), whitened_cosine (centred and ZCA-whitened)",
      one_of({"cosine", "centered_cosine", "whitened_cosine"}));
    v("calibration", calibration,
      "none (the paper's beta(t)) or q_target: the distance table is scaled by s >= 1 (equivalently c -> c s) so "
      "that the mean over codes of q_t(x1|x1) is target_q at t = target_t",
      one_of({"none", "q_target"}));
    v("target_q", target_q, "q_target: mean q_t(x1|x1) to reach at target_t", in_range(0.01, 0.99));
    v("target_t", target_t, "q_target: the time at which target_q is reached", in_range(0.05, 0.99));
  }
  bool omitted_from_dump() const override {
    return metric == "cosine" && calibration == "none" && target_q == 0.5 && target_t == 0.9;
  }
};

struct TmdPriorConfig : TokenPriorConfig {
  double beta_c = 3.0;  // beta(t) = c (t / (1 - t))^a, eq. (18)
  double beta_a = 0.9;
  double t_eps = 1e-3;  // training times t ~ U[0, 1 - t_eps) keep beta finite
  TmdPathConfig path;   // metric and calibration (the paper's by default)
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

// The distance table of eq. (17) for a codebook [K, D] under `path`: d(i, j) =
// s (2 - 2 cos(e~_i, e~_j))^2 with e~ the raw, centred or whitened codes, zero
// diagonal, and s = 1 (calibration none) or the smallest s >= 1 making the mean over
// codes of q_{target_t}(x1|x1) >= target_q with beta(t) = c (t/(1-t))^a (bisection;
// scaling d by s is the same path as c -> c s). Deterministic (double precision).
struct TmdPathTable {
  torch::Tensor dist;  // [K, K] float32
  double scale = 1.0;  // s
};
TmdPathTable tmd_path_table(const torch::Tensor& codebook, const TmdPathConfig& path, double c, double a);
// Concentration of the path q_t(.|x1) at time t, averaged uniformly over x1: mean
// q_t(x1|x1) and the effective number of codes exp(H(q_t(.|x1))).
struct TmdPathStats {
  double q_self = 0, effective_codes = 0;
};
TmdPathStats tmd_path_stats(const torch::Tensor& dist, double t, double c, double a);

// TMD transitions (the sampler's step, also used by controlled training's rollouts).

// eq. (21): u_t(i | x_t, x1_hat) = q_t(i | x1_hat) beta'(t) [d(x_t, x1_hat) - d(i, x1_hat)]_+,
// with u(x_t) = 0. xt, x1_hat [...] int64; t in (0, 1). -> [..., K].
torch::Tensor tmd_transition_rates(const torch::Tensor& dist, const torch::Tensor& xt, const torch::Tensor& x1_hat,
                                   double t, double c, double a);
// eqs. (22)-(23): jump with probability 1 - exp(-h sum_i u(i)), to i ~ u / sum u. The
// randomness is given: u_jump, u_pick [...] uniforms in [0, 1).
torch::Tensor tmd_jump(const torch::Tensor& xt, const torch::Tensor& rates, double h, const torch::Tensor& u_jump,
                       const torch::Tensor& u_pick);
// i ~ probs [..., K] (rows summing to 1, or any non-negative weights) by inverse CDF at u [...].
torch::Tensor categorical_from_uniform(const torch::Tensor& probs, const torch::Tensor& u);

// One non-final step of the TMD sampler from t to t + h given the step's logits [..., K]:
// the clean proposal x1_hat (argmax, or a draw from softmax(logits / temperature) at
// u_proposal), then eqs. (21)-(23) with rates at t clamped to [t_eps, 1 - t_eps] and the
// given jump uniforms. The sampler and controlled training's rollouts share it.
torch::Tensor tmd_sampler_step(const torch::Tensor& dist, const torch::Tensor& x, const torch::Tensor& logits,
                               double t, double h, double t_eps, double c, double a, bool argmax,
                               double temperature, const torch::Tensor& u_proposal, const torch::Tensor& u_jump,
                               const torch::Tensor& u_pick);

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

// The run directory of the tokenizer a token-prior config names: tokenizer_run, or
// the run of tokenizer_config the job resolved (core/trained_runs.h).
std::string resolve_tokenizer_run(const TokenPriorConfig& c);

// A finished `tmd_prior` or `masked_prior` run (config.yaml, checkpoints/final.pt,
// outputs/vocab.txt, outputs/prior_meta.yaml) and the tokenizer run it names.
class TokenPrior {
 public:
  // UserError naming a missing file, a wrong model type, an unreadable checkpoint or a
  // tokenizer whose codebook no longer matches the one the prior was trained with.
  static TokenPrior load(const std::string& run_dir, torch::Device device = torch::kCPU);

  TextContext encode_texts(const std::vector<std::string>& captions) const;
  TextContext null_texts(int64_t B, int64_t W) const;

  // One network call: ids [B, L], t [B] or scalar (ignored by the masked prior), valid [B, L].
  torch::Tensor raw_logits(const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                           const torch::Tensor& valid, const TokenTransformerHooks* hooks = nullptr) const;
  // l_u + s (l_c - l_u), both halves in one doubled forward (hooks, if any, are given
  // for B rows; hooks->guidance says which passes get them: guided_token_logits).
  // UserError when a valid position's logits are not finite.
  torch::Tensor guided_logits(const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                              const torch::Tensor& valid, double cfg_scale,
                              const TokenTransformerHooks* hooks = nullptr) const;
  // Tokens [L] of one motion -> world joints [L * stride, J, 3] (CPU).
  torch::Tensor decode_world(const torch::Tensor& ids) const;

  bool is_tmd() const { return cfg_->is_tmd(); }
  const TokenPriorConfig& config() const { return *cfg_; }
  const TmdPriorConfig& tmd_config() const;  // logic_error for a masked prior
  const LoadedVqTokenizer& tokenizer() const { return tok_; }
  torch::Tensor distance() const { return (*net_)->distance; }  // [K, K]
  int64_t codebook_size() const { return tok_.model->codebook_size(); }
  int64_t stride() const { return tok_.model->stride(); }
  int64_t max_tokens() const { return (t_max_ + stride() - 1) / stride(); }
  const Skeleton& skeleton() const { return tok_.skeleton; }
  const TextVocab& vocab() const { return *vocab_; }
  double fps() const { return tok_.fps; }
  int t_max() const { return t_max_; }
  int num_joints() const { return skeleton().num_joints(); }
  const std::string& run_dir() const { return run_dir_; }
  torch::Device device() const { return device_; }
  TokenPriorNet& net() const { return *net_; }

 private:
  std::shared_ptr<TokenPriorNet> net_;
  std::shared_ptr<TextVocab> vocab_;
  std::shared_ptr<TokenPriorConfig> cfg_;
  LoadedVqTokenizer tok_;
  int t_max_ = 196;
  std::string run_dir_;
  torch::Device device_ = torch::kCPU;
};

}  // namespace mc
