// AnchorRoute's anchor condition path on a frozen TMD prior (§3.2, eqs. (13)-(16)):
// the scaffold encoder, AnchorKV and the Table IV baselines (cross-attention, ControlNet),
// the adapter feature layout, the controlled trainer (`anchor_adapter`) and its run loader.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "control/anchors.h"
#include "core/config.h"
#include "core/trained_runs.h"
#include "models/token_transformer.h"

namespace mc {

class TokenPrior;
struct Skeleton;

// AnchorKV's memory attention (issue 15). The defaults are eq. (15) as written (one
// softmax over [K; K^s], every token sees every memory slot) and are left out of the
// dumped config, so runs trained before these switches keep their names and hashes.
// Deviations and the evidence behind them: docs/choices.md ("AnchorRoute: adapters").
// Text slots beside H^s (ours: dual context read as a text branch kept apart from the
// anchor memory): a condition MLP of the pooled sentence vector (one slot) and the
// sequence-level text memory (one slot per word), projected like eq. (14), values zero-init.
// Off by default and then left out of the dump.
struct AnchorKvTextSlotsConfig : Config {
  bool enabled = false;
  void visit(FieldVisitor& v) override;
  bool omitted_from_dump() const override { return !enabled; }
};

struct AnchorKvMemoryConfig : Config {
  std::string normaliser = "joint";  // joint: eq. (15) | own: the block's own normaliser (identity at init)
  int window = -1;                   // -1: every slot (eq. (15)); w >= 0: token n sees slots |n - m| <= w
  AnchorKvTextSlotsConfig text_slots;
  void visit(FieldVisitor& v) override;
  bool paper() const { return normaliser == "joint" && window < 0; }
  bool omitted_from_dump() const override { return paper() && !text_slots.enabled; }
};

// The loss of a rollout batch. Defaults (left out of the dump): eq. (16) as on path batches.
struct AdapterRolloutLossConfig : Config {
  double ce_weight = 1.0;       // weight of the CE toward the ground-truth tokens
  double anchor_weight = -1.0;  // weight of the anchor loss (eq. (10)); -1 = lambda_anc
  void visit(FieldVisitor& v) override;
  bool omitted_from_dump() const override { return ce_weight == 1.0 && anchor_weight == -1.0; }
};

// Rollout states (issue 15, ours): a fraction of training batches starts not from the
// corruption path of eq. (19) but from the sampler's own state at t_k = k / steps, reached
// by running the TMD sampler (eqs. (21)-(23), CFG, the adapter being trained, no gradient)
// from uniform tokens with the clip's caption and anchors; the targets stay the clip's
// ground-truth tokens (DAgger-style: the sampler's late states, whose heading the prior has
// already decided, are otherwise never seen in training). Off (prob 0) by default and then
// left out of the dump.
struct AdapterRolloutConfig : Config {
  double prob = 0.0;       // fraction of training batches built from rollout states
  int steps = 10;          // the rollout sampler's grid: k ~ U{1, ..., steps - 1}
  double cfg_scale = 4.0;  // the rollout sampler's CFG on logits (the generator's default)
  int val_clips = 64;      // validation: full rollouts of the first val clips (generator-only error)
  AdapterRolloutLossConfig loss;
  void visit(FieldVisitor& v) override;
  bool omitted_from_dump() const override { return prob == 0.0; }
};

// Where controlled training spends its signal, and an audit switch (issue 15). Defaults:
// eq. (19)'s uniform t and the real features, left out of the dumped config.
struct AdapterTrainingConfig : Config {
  double t_power = 1.0;        // t = u^p, u ~ U[0, 1): p > 1 puts more draws at low (noisy) t
  bool zero_features = false;  // audit twin: the adapter sees all-zero features (no anchor information)
  AdapterRolloutConfig rollout;
  void visit(FieldVisitor& v) override;
  bool omitted_from_dump() const override { return t_power == 1.0 && !zero_features && rollout.omitted_from_dump(); }
};

// Feedback channels (issue 15, ours; control/anchor_feedback.h): the anchors said against
// the frozen prior's own soft estimate of the clean motion at the current tokens, in the
// estimate's facing frame, recomputed at every network call (one more frozen forward and
// soft decode per call). Off by default and then left out of the dump.
struct AdapterFeedbackConfig : Config {
  bool enabled = false;
  void visit(FieldVisitor& v) override;
  bool omitted_from_dump() const override { return !enabled; }
};

// The adapter's input features (issue 15). `delta_scale`: eq. (6)'s path difference Delta p
// is in metres per frame (~0.02 at 20 fps) beside positions of metres. `frame`: the
// world-frame features of eqs. (5)-(6) (world), or the same anchors said in the frame of
// the interpolation prior's own path (path: control/anchors.h anchor_path_features,
// invariant to rotating the anchors about y and moving them in xz), or both side by side.
// Defaults: as written, left out of the dumped config.
struct AdapterFeatureConfig : Config {
  double delta_scale = 1.0;     // multiplies every world Delta p channel (20 = metres per second at 20 fps)
  std::string frame = "world";  // world (eqs. (5)-(6)) | path (ours) | both
  AdapterFeedbackConfig feedback;
  void visit(FieldVisitor& v) override;
  bool world() const { return frame != "path"; }
  bool path() const { return frame != "world"; }
  bool omitted_from_dump() const override { return delta_scale == 1.0 && frame == "world" && !feedback.enabled; }
};

// `model:` section of a controlled-training run (model.type = anchor_adapter).
// Defaults and the readings behind them: docs/choices.md ("AnchorRoute: adapters").
struct AnchorAdapterConfig : Config, DeclaresDependencies {
  std::string adapter = "anchorkv";  // anchorkv | cross_attention | controlnet (Table IV)
  int memory_width = 0;              // d_s of H^s; 0 = the backbone's width (eq. (13): H^s in R^{L x d})
  int encoder_blocks = 2;            // residual conv blocks after the scaffold encoder's downsampling
  int rank = 16;                     // r of eq. (14)
  bool dual_context = true;          // text-conditioned scaffold memory (see dual_context help)
  int heads = 4;                     // heads of the scaffold encoder's text attention / the cross-attention adapter
  double dropout = 0.0;              // inside trainable adapter layers
  // Anchor draws per training clip (from the clip's ground truth).
  std::vector<std::string> families = {"root_3d", "planar_root", "body_point"};
  std::vector<int> anchor_counts = {2, 4, 8, 16, 32};
  std::vector<int> body_joints = {0, 10, 11, 15, 20, 21};
  double sparse_keyjoint_prob = 0.0;  // probability of a Table II six-point set instead
  double sparse_keyjoint_ratio = 0.3;
  AnchorKvMemoryConfig anchorkv;
  AdapterTrainingConfig training;
  AdapterFeatureConfig features;
  // eq. (16)
  double lambda_anc = 0.3;
  int delta = 2;
  double cond_drop = 0.1;
  // The frozen TMD prior: a finished run, or its training config trained on demand.
  std::string tmd_run;
  std::string tmd_config = "configs/tmd/tmd_tiny.yaml";
  std::vector<std::string> tmd_overrides;

  void visit(FieldVisitor& v) override;
  void dependencies(DependencyVisitor& d) override { d("model.tmd", tmd_run, tmd_config, tmd_overrides); }
  std::string validate() const override;
};

// ---------------------------------------------------------------- features

// The adapter's frame-level input: per family layout (root_3d, planar_root, body_point over
// `body_joints`) a block of that family's features; the set fills its own family's blocks,
// the others stay 0; last a one-hot of the family, so one model with one input width
// serves every family. features.frame picks the blocks: world = eqs. (5)-(6), width
// 11 + 8 + (3 * 3G + 2G) + 3 for G body joints; path = anchor_path_features, width
// 14 + 10 + 17G + 3; both = the world blocks, then the path blocks, then the one-hot.
// features.feedback adds kFeedbackWidth channels last (after the one-hot).
int64_t adapter_feature_width(const std::vector<int>& body_joints, const AdapterFeatureConfig& features = {});
// [frames, width] float CPU. UserError if a body-point anchor's joint is not in body_joints.
// The feedback block (if any) is left 0: it needs an estimate (fill_feedback_features).
torch::Tensor adapter_features(const AnchorSet& set, const std::vector<int>& body_joints,
                               const AdapterFeatureConfig& features = {});

// Feedback (features.feedback): the frozen prior's soft estimate of the clean motion at
// tokens `ids` (no adapter): softmax of its logits -> expected code embedding -> frozen
// decoder (eq. (12)'s soft decode) -> world metres [B, L * stride, J, 3], CPU, no grad.
torch::Tensor frozen_soft_estimate(const TokenPrior& prior, const torch::Tensor& ids, const torch::Tensor& t,
                                   const TextContext& text, const torch::Tensor& valid);
// Writes the feedback block of feats [B, >= frames, width] (CPU) for row b = sets[b]
// from estimate [B, >= frames, J, 3]; no-op when features.feedback is off.
void fill_feedback_features(torch::Tensor& feats, const std::vector<AnchorSet>& sets, const torch::Tensor& estimate,
                            const Skeleton& skeleton, const std::vector<int>& body_joints,
                            const AdapterFeatureConfig& features);

// ---------------------------------------------------------------- modules

// What an adapter sees for one backbone call (all on the backbone's device).
struct AdapterInputs {
  torch::Tensor ids;       // [B, L] current tokens
  torch::Tensor t;         // [B] times (TMD)
  TextContext text;        // the (possibly dropped) text context of the same call
  torch::Tensor valid;     // [B, L] bool
  torch::Tensor features;  // [B, L * stride, F] adapter_features, zero past each clip
};

// Scaffold encoder (eq. (13)): Linear(F -> d_s), log2(stride) stride-2 convs (the
// tokenizer's temporal downsampling), residual conv blocks, RMS-normalised; with dual
// context also a condition MLP of the pooled text (zero-init FiLM) and a zero-init
// cross-attention of the memory to the text memory. -> H^s [B, L, d_s].
struct ScaffoldEncoderImpl : torch::nn::Module {
  ScaffoldEncoderImpl(int64_t feature_width, int64_t memory_width, int64_t stride, int64_t blocks,
                      bool dual_context, int64_t text_dim, int64_t heads);
  torch::Tensor forward(const torch::Tensor& features, const TextContext& text);
  torch::nn::Linear in{nullptr};
  torch::nn::ModuleList down{nullptr}, res{nullptr};
  torch::nn::LayerNorm norm{nullptr};
  bool dual_context;
  int64_t heads;
  torch::nn::Linear film{nullptr};                 // pooled text -> (scale, shift), zero-init
  torch::nn::Linear tq{nullptr}, tkv{nullptr}, to{nullptr};  // memory -> text memory attention, `to` zero-init
};
TORCH_MODULE(ScaffoldEncoder);

// Common interface: an adapter turns the features (and the call's tokens, time and
// text) into the backbone's hooks. Parameters of the backbone are never registered.
struct AnchorAdapterModule : torch::nn::Module {
  virtual TokenTransformerHooks hooks(const AdapterInputs& in) = 0;
  // Whether the hooks depend on in.text (dual context; the ControlNet copy's blocks always).
  virtual bool reads_text() const { return scaffold && scaffold->dual_context; }
  // The hooks of one CFG sampling call: when they read the text, the null-text pass gets
  // hooks computed from `null_text` (TokenTransformerHooks::null_text), which is what
  // training's dropped-text draws (cond_drop) showed the adapter; otherwise one set
  // serves every pass.
  TokenTransformerHooks guided_hooks(const AdapterInputs& in, const TextContext& null_text);
  ScaffoldEncoder scaffold{nullptr};
};

// AnchorKV, eqs. (14)-(15): per block K^s = H^s P U^K, V^s = H^s P U^V (rank r), appended to
// the block's self-attention. The keys get RoPE at their token index (the backbone's
// queries carry RoPE, so scores depend on n - m). U^V starts at zero. c.anchorkv picks
// the normaliser (joint = eq. (15); own = the block's attention unchanged plus the
// memory, so the untrained adapter is the identity) and the token-aligned window (token
// n sees slots |n - m| <= w only, as a -inf score bias outside it).
struct AnchorKVAdapterImpl : AnchorAdapterModule {
  AnchorKVAdapterImpl(const AnchorAdapterConfig& c, const TokenTransformerOptions& backbone, int64_t stride,
                      int64_t feature_width);
  TokenTransformerHooks hooks(const AdapterInputs& in) override;
  bool reads_text() const override { return AnchorAdapterModule::reads_text() || memory.text_slots.enabled; }
  std::vector<torch::Tensor> P, UK, UV;  // per block [d_s, r], [r, d], [r, d]
  std::vector<torch::Tensor> PT, UKT, UVT;  // text slots (memory.text_slots.enabled): [text_dim, r], [r, d], [r, d]
  torch::nn::Sequential text_cond{nullptr};  // condition MLP of the pooled sentence vector
  int64_t heads, head_dim;
  double rope_base;
  AnchorKvMemoryConfig memory;
};
TORCH_MODULE(AnchorKVAdapter);

// Table IV "Cross Attention": a side stream started from the frozen token embeddings
// runs one (cross-attention to H^s, MLP) layer per block; a zero-init Linear of its
// state after layer l is block l's residual (block_residuals; the side stream's queries
// are its own state, not the backbone's hidden state, which the hooks cannot read).
struct CrossAttentionAdapterImpl : AnchorAdapterModule {
  CrossAttentionAdapterImpl(const AnchorAdapterConfig& c, TokenTransformer backbone, int64_t stride,
                            int64_t feature_width);
  TokenTransformerHooks hooks(const AdapterInputs& in) override;
  TokenTransformer backbone{nullptr};  // not registered: frozen
  torch::nn::ModuleList q{nullptr}, kv{nullptr}, o_{nullptr}, mlp{nullptr}, norm1{nullptr}, norm2{nullptr},
      out{nullptr};
  torch::nn::Linear mem_proj{nullptr};
  int64_t heads;
};
TORCH_MODULE(CrossAttentionAdapter);

// Table IV "ControlNet" (reference-facts §6): a trainable copy of every backbone block,
// initialised from it, fed the frozen token embedding plus a zero-init projection of the
// control encoder's memory H^s; a zero-init Linear of copy l's output is block l's residual.
struct ControlNetAdapterImpl : AnchorAdapterModule {
  ControlNetAdapterImpl(const AnchorAdapterConfig& c, TokenTransformer backbone, int64_t stride,
                        int64_t feature_width);
  TokenTransformerHooks hooks(const AdapterInputs& in) override;
  bool reads_text() const override { return true; }  // its block copies see the call's text
  TokenTransformer backbone{nullptr};  // not registered: frozen
  torch::nn::ModuleList blocks{nullptr}, zero_out{nullptr};
  torch::nn::Linear zero_in{nullptr};
};
TORCH_MODULE(ControlNetAdapter);

// The adapter `c.adapter` names, for `backbone` (whose tokenizer has `stride`).
std::shared_ptr<AnchorAdapterModule> make_anchor_adapter(const AnchorAdapterConfig& c, TokenTransformer backbone,
                                                         int64_t stride);
int64_t count_parameters(torch::nn::Module& m);

// ---------------------------------------------------------------- loading

// A finished anchor_adapter run (config.yaml, checkpoints/final.pt, outputs/adapter_meta.yaml)
// with the TMD prior it was trained on, in eval mode.
struct LoadedAnchorAdapter {
  std::shared_ptr<AnchorAdapterModule> module;
  std::shared_ptr<TokenPrior> prior;
  AnchorAdapterConfig cfg;
  std::string run_dir;
  int64_t trainable_parameters = 0;
};
LoadedAnchorAdapter load_anchor_adapter(const std::string& run_dir, torch::Device device = torch::kCPU);

}  // namespace mc
