// AnchorRoute's anchor condition path: adapter features, scaffold encoder, AnchorKV
// (eqs. (13)-(15)), the cross-attention and ControlNet baselines of Table IV, the
// controlled trainer of eq. (16) (`anchor_adapter`) and the run loader.
#include "models/anchor_adapters.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <limits>
#include <random>

#include "core/atomic_file.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "models/flow_prior.h"
#include "models/flow_transformer.h"
#include "models/token_prior.h"
#include "control/anchor_loss.h"
#include "control/anchor_feedback.h"
#include "core/trained_runs.h"
#include "models/trainable.h"
#include "models/trained_run.h"

namespace mc {
namespace nn = torch::nn;
namespace F = torch::nn::functional;

// ---------------------------------------------------------------- config

void AnchorKvMemoryConfig::visit(FieldVisitor& v) {
  v("normaliser", normaliser,
    "softmax normaliser of AnchorKV's appended memory: joint (eq. (15): one softmax over the block's keys and "
    "the memory; the memory takes attention mass from the frozen block even at initialisation) or own (the "
    "block's own keys only: its attention stays as trained and the memory adds exp(score - LSE_own) V^s, so an "
    "untrained adapter is the identity)",
    one_of({"joint", "own"}));
  v("window", window,
    "token-aligned memory: token n attends to memory slots |n - m| <= window only (-1 = every slot, eq. (15) "
    "as written)",
    at_least(-1));
  v("text_slots", text_slots, "ours: dual context as a text branch beside H^s (see text_slots.enabled)");
}

void AnchorKvTextSlotsConfig::visit(FieldVisitor& v) {
  v("enabled", enabled,
    "ours: dual context as a text branch apart from the anchor memory: the pooled sentence vector (through a "
    "condition MLP) and the word memory appended as extra key/value slots beside H^s (values zero-init; not "
    "windowed). Use with dual_context: false to keep H^s anchors-only");
}

void AdapterTrainingConfig::visit(FieldVisitor& v) {
  v("t_power", t_power,
    "training times t = u^t_power, u ~ U[0, 1) (1 = uniform as eq. (19); 2-3 put most draws at low, noisy t "
    "where the frozen prior knows least and anchors help most)",
    in_range(0.1, 10.0));
  v("zero_features", zero_features,
    "audit twin: train (and validate) with all-zero adapter features, i.e. no anchor information; with the same "
    "seed it draws the same batches, times and anchors as its real-feature twin");
  v("rollout", rollout, "ours: train a fraction of batches on the sampler's own states (see rollout.prob)");
}

void AdapterRolloutConfig::visit(FieldVisitor& v) {
  v("prob", prob,
    "ours, not the paper: fraction of training batches whose input tokens are the TMD sampler's own state at "
    "t_k = k / steps (k uniform in 1..steps-1), reached with the adapter being trained (no gradient), the "
    "clip's caption and anchors; targets stay the clip's ground-truth tokens (0 = eq. (19) only)",
    in_range(0.0, 1.0));
  v("steps", steps, "the rollout sampler's steps (its grid t_k = k / steps); cost: up to steps - 1 CFG calls "
    "per rolled-out batch", in_range(2, 1000));
  v("cfg_scale", cfg_scale, "the rollout sampler's classifier-free guidance on logits", in_range(0.0, 100.0));
  v("val_clips", val_clips, "validation: the first val clips sampled to the end by the rollout sampler "
    "(val_rollout_control_error: generator-only anchor error of the hard decode)", at_least(1));
  v("loss", loss, "the loss of a rollout batch (default: eq. (16), as on path batches)");
}

void AdapterRolloutLossConfig::visit(FieldVisitor& v) {
  v("ce_weight", ce_weight,
    "weight of the CE toward the clip's ground-truth tokens on a rollout batch (from a state that has already "
    "decided another gait or heading the exact tokens are unpredictable, and their CE teaches blurred proposals)",
    in_range(0.0, 100.0));
  v("anchor_weight", anchor_weight,
    "weight of the anchor loss (eq. (10), soft decode of the logits at the rollout state) on a rollout batch; "
    "-1 = model.lambda_anc", in_range(-1.0, 1000.0));
}

void AdapterFeatureConfig::visit(FieldVisitor& v) {
  v("delta_scale", delta_scale,
    "multiplies eq. (6)'s path-difference channels Delta p (metres per frame) so the root's required speed "
    "reaches the scale of the positions (1 = as written; 20 = metres per second at 20 fps)",
    in_range(1e-3, 1e3));
  v("frame", frame,
    "frame the anchors are said in: world (eqs. (5)-(6): anchor values, prior, Delta p in world metres), path "
    "(ours: speed, turn rate, vertical speed, height and the next/previous anchor in the frame of the "
    "interpolation prior's own path, invariant to rotating and moving the anchor set; docs/choices.md) or both",
    one_of({"world", "path", "both"}));
  v("feedback", feedback, "ours: feedback channels against the frozen prior's own estimate (see feedback.enabled)");
}

void AdapterFeedbackConfig::visit(FieldVisitor& v) {
  v("enabled", enabled,
    "ours, not the paper: add the anchors' residual and bearing against the frozen prior's soft estimate of the "
    "clean motion at the current tokens, in the estimate's facing frame, recomputed at every network call "
    "(control/anchor_feedback.h; one more frozen forward per call; docs/choices.md)");
}

void AnchorAdapterConfig::visit(FieldVisitor& v) {
  v("adapter", adapter, "condition path: anchorkv (eqs. (14)-(15)), cross_attention or controlnet (Table IV baselines)",
    one_of({"anchorkv", "cross_attention", "controlnet"}));
  v("memory_width", memory_width, "width d_s of the token-aligned memory H^s (0 = the backbone's width)", at_least(0));
  v("encoder_blocks", encoder_blocks, "residual conv blocks of the scaffold encoder after downsampling",
    in_range(0, 8));
  v("rank", rank, "rank r of AnchorKV's P_l U_l^K / P_l U_l^V, eq. (14)", at_least(1));
  v("dual_context", dual_context,
    "dual context: the scaffold memory also sees the text (condition MLP of the pooled sentence vector as a "
    "zero-init FiLM, and a zero-init attention to the sequence-level text memory); off = anchors only");
  v("heads", heads, "heads of the scaffold encoder's text attention and of the cross-attention adapter", at_least(1));
  v("dropout", dropout, "dropout inside the trainable adapter layers", in_range(0.0, 0.9));
  v("families", families, "control families drawn per training clip (root_3d, planar_root, body_point)");
  v("anchor_counts", anchor_counts, "anchor counts K drawn per training clip (clamped to the clip's length)",
    each(at_least(1)));
  v("body_joints", body_joints, "joints a body-point anchor may control (fixes the feature width)",
    each(at_least(0)));
  v("sparse_keyjoint_prob", sparse_keyjoint_prob,
    "probability that a training clip gets Table II's six-point set (all body_joints at the same frames)",
    in_range(0.0, 1.0));
  v("sparse_keyjoint_ratio", sparse_keyjoint_ratio, "fraction of frames of a six-point set", in_range(1e-6, 1.0));
  v("anchorkv", anchorkv, "AnchorKV's memory attention (defaults: eq. (15) as written)");
  v("training", training, "where controlled training spends its signal, and the zeroed-feature audit twin "
    "(defaults: uniform t, real features)");
  v("features", features, "the adapter's input features: frame and scale (default: eqs. (5)-(6) as written)");
  v("lambda_anc", lambda_anc, "lambda_anc of eq. (16) (0 = CE only, Table IV 'without anchor loss')", at_least(0.0));
  v("delta", delta, "support radius delta of eqs. (7)-(10), frames", in_range(0, 50));
  v("cond_drop", cond_drop, "probability of the null text during adapter training (keeps CFG usable)",
    in_range(0.0, 1.0));
  v("tmd_run", tmd_run, "finished tmd_prior run directory ('' = train tmd_config on demand)");
  v("tmd_config", tmd_config, "TMD training config run on demand when tmd_run is ''");
  v("tmd_overrides", tmd_overrides, "key=value overrides for tmd_config");
}

std::string AnchorAdapterConfig::validate() const {
  if (families.empty()) return "families is empty; give e.g. [root_3d, planar_root, body_point]";
  for (auto& f : families) parse_anchor_family(f, "model.families");
  if (anchor_counts.empty()) return "anchor_counts is empty; give e.g. [2, 4, 8, 16, 32]";
  if (body_joints.empty()) return "body_joints is empty";
  if (tmd_run.empty() && tmd_config.empty()) return "set model.tmd_run (a finished tmd_prior run) or model.tmd_config";
  return "";
}

// ---------------------------------------------------------------- features

namespace {
const AnchorFamily kFamilies[3] = {AnchorFamily::root_3d, AnchorFamily::planar_root, AnchorFamily::body_point};
}

int64_t adapter_feature_width(const std::vector<int>& body_joints, const AdapterFeatureConfig& features) {
  int64_t w = 3;
  for (auto f : kFamilies) {
    auto layout = anchor_feature_layout(f, body_joints);
    if (features.world()) w += layout.width();
    if (features.path()) w += path_feature_width(layout);
  }
  if (features.feedback.enabled) w += kFeedbackWidth;
  return w;
}

torch::Tensor adapter_features(const AnchorSet& set, const std::vector<int>& body_joints,
                               const AdapterFeatureConfig& features) {
  const int64_t T = set.frames;
  auto out = torch::zeros({T, adapter_feature_width(body_joints, features)});
  int64_t col = 0;
  auto fill = [&](const FeatureMatrix& m) {
    out.narrow(1, col, m.cols()).copy_(torch::from_blob(const_cast<float*>(m.data()), {T, m.cols()}, torch::kFloat32));
  };
  if (features.world())
    for (int i = 0; i < 3; ++i) {
      auto layout = anchor_feature_layout(kFamilies[i], body_joints);
      if (set.family == kFamilies[i] && set.size() > 0) {
        FeatureMatrix m = anchor_features(set, layout);  // eqs. (5)-(6)
        if (features.delta_scale != 1.0)
          m.middleCols(2 * layout.d_f, layout.d_f) *= static_cast<float>(features.delta_scale);
        fill(m);
      }
      col += layout.width();
    }
  if (features.path())
    for (int i = 0; i < 3; ++i) {
      auto layout = anchor_feature_layout(kFamilies[i], body_joints);
      if (set.family == kFamilies[i] && set.size() > 0) fill(anchor_path_features(set, layout));
      col += path_feature_width(layout);
    }
  for (int i = 0; i < 3; ++i)
    if (set.family == kFamilies[i]) out.select(1, col + i).fill_(1.0);
  return out;
}

torch::Tensor frozen_soft_estimate(const TokenPrior& prior, const torch::Tensor& ids, const torch::Tensor& t,
                                   const TextContext& text, const torch::Tensor& valid) {
  torch::NoGradGuard ng;
  const int64_t B = ids.size(0), L = ids.size(1), J = prior.num_joints();
  auto logits = prior.raw_logits(ids, t, text, valid);
  VqTokenizer handle = prior.tokenizer().model;
  auto& tok = *handle;
  return tok.denormalize(tok.soft_decode(torch::softmax(logits, -1)).view({B, L * prior.stride(), J, 3}))
      .to(torch::kCPU, torch::kFloat32)
      .contiguous();
}

void fill_feedback_features(torch::Tensor& feats, const std::vector<AnchorSet>& sets, const torch::Tensor& estimate,
                            const Skeleton& skeleton, const std::vector<int>& body_joints,
                            const AdapterFeatureConfig& features) {
  if (!features.feedback.enabled) return;
  const int64_t col = adapter_feature_width(body_joints, features) - kFeedbackWidth;
  auto est = estimate.to(torch::kCPU, torch::kFloat32).contiguous();
  for (size_t b = 0; b < sets.size(); ++b) {
    const int T = sets[b].frames;
    if (T == 0 || sets[b].size() == 0) continue;
    auto e = est[static_cast<int64_t>(b)];
    FeatureMatrix m = anchor_feedback_features(sets[b], e.data_ptr<float>(), static_cast<int>(e.size(0)), skeleton);
    feats[static_cast<int64_t>(b)].narrow(0, 0, T).narrow(1, col, kFeedbackWidth)
        .copy_(torch::from_blob(m.data(), {T, kFeedbackWidth}, torch::kFloat32));
  }
}

// ---------------------------------------------------------------- helpers

namespace {

// Multi-head attention of q [B, Lq, D] over k, v [B, N, D] where key_valid [B, N] is true.
torch::Tensor multi_head(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                         const torch::Tensor& key_valid, int64_t heads) {
  const int64_t B = q.size(0), Lq = q.size(1), N = k.size(1), D = q.size(2), Dh = D / heads;
  auto sh = [&](const torch::Tensor& x, int64_t n) { return x.view({B, n, heads, Dh}).transpose(1, 2); };
  auto s = torch::matmul(sh(q, Lq), sh(k, N).transpose(-2, -1)) / std::sqrt(static_cast<double>(Dh));
  s = s.masked_fill(key_valid.logical_not().view({B, 1, 1, N}), -1e9);
  return torch::matmul(torch::softmax(s, -1), sh(v, N)).transpose(1, 2).reshape({B, Lq, D});
}

// Sinusoidal embedding of the token index, [L, dim].
torch::Tensor token_positions(int64_t L, int64_t dim, torch::Device dev) {
  return timestep_sinusoid(torch::arange(L, torch::TensorOptions().dtype(torch::kFloat32).device(dev)), dim);
}

nn::Linear zero_linear(int64_t in, int64_t out) {
  nn::Linear l(in, out);
  torch::NoGradGuard ng;
  l->weight.zero_();
  l->bias.zero_();
  return l;
}

int64_t resolved_memory_width(const AnchorAdapterConfig& c, const TokenTransformerOptions& o) {
  return c.memory_width > 0 ? c.memory_width : o.width;
}

int64_t log2_stride(int64_t stride) {
  int64_t k = 0;
  while ((int64_t{1} << k) < stride) ++k;
  if ((int64_t{1} << k) != stride) fail("adapter: tokenizer stride {} is not a power of two", stride);
  return k;
}

}  // namespace

int64_t count_parameters(nn::Module& m) {
  int64_t n = 0;
  for (auto& p : m.parameters())
    if (p.requires_grad()) n += p.numel();
  return n;
}

// ---------------------------------------------------------------- scaffold encoder

ScaffoldEncoderImpl::ScaffoldEncoderImpl(int64_t feature_width, int64_t d, int64_t stride, int64_t blocks,
                                         bool dual, int64_t text_dim, int64_t heads_)
    : dual_context(dual), heads(heads_) {
  in = register_module("input_proj", nn::Linear(feature_width, d));  // not "in": a TorchScript keyword in archives
  down = register_module("down", nn::ModuleList());
  for (int64_t k = 0, n = log2_stride(stride); k < n; ++k)  // the tokenizer's x2 stages
    down->push_back(nn::Conv1d(nn::Conv1dOptions(d, d, 4).stride(2).padding(1)));
  res = register_module("res", nn::ModuleList());
  for (int64_t b = 0; b < 2 * blocks; ++b) {
    int64_t dil = 1;
    for (int64_t i = 0; i < b / 2; ++i) dil *= 3;
    res->push_back(nn::Conv1d(nn::Conv1dOptions(d, d, 3).padding(dil).dilation(dil)));
  }
  norm = register_module("norm", nn::LayerNorm(nn::LayerNormOptions({d})));
  if (dual_context) {
    if (d % heads != 0) fail("adapter: memory width {} is not a multiple of heads {}", d, heads);
    film = register_module("film", zero_linear(text_dim, 2 * d));
    tq = register_module("tq", nn::Linear(d, d));
    tkv = register_module("tkv", nn::Linear(text_dim, 2 * d));
    to = register_module("to", zero_linear(d, d));
  }
}

torch::Tensor ScaffoldEncoderImpl::forward(const torch::Tensor& features, const TextContext& text) {
  auto h = torch::silu(in(features)).transpose(1, 2);  // [B, d, T]
  for (auto& m : *down) h = torch::silu(m->as<nn::Conv1d>()->forward(h));
  for (size_t b = 0; b + 1 < res->size(); b += 2)
    h = h + res[b + 1]->as<nn::Conv1d>()->forward(torch::silu(res[b]->as<nn::Conv1d>()->forward(torch::silu(h))));
  h = h.transpose(1, 2);  // [B, L, d], eq. (13)
  const int64_t L = h.size(1);
  h = h + token_positions(L, h.size(2), h.device()).unsqueeze(0);
  h = norm(h);
  if (dual_context) {
    auto fs = film(text.pooled).unsqueeze(1).chunk(2, -1);  // condition MLP of the pooled sentence vector
    h = h * (1 + fs[0]) + fs[1];
    auto kv = tkv(text.memory).chunk(2, -1);                 // the sequence-level text memory
    h = h + to(multi_head(tq(h), kv[0], kv[1], text.memory_valid.to(torch::kBool), heads));
  }
  return h;
}

TokenTransformerHooks AnchorAdapterModule::guided_hooks(const AdapterInputs& in, const TextContext& null_text) {
  auto h = hooks(in);
  if (reads_text()) {
    AdapterInputs n = in;
    n.text = null_text;
    h.null_text = std::make_shared<TokenTransformerHooks>(hooks(n));
  }
  return h;
}

// ---------------------------------------------------------------- AnchorKV

AnchorKVAdapterImpl::AnchorKVAdapterImpl(const AnchorAdapterConfig& c, const TokenTransformerOptions& o,
                                         int64_t stride, int64_t feature_width)
    : heads(o.heads), head_dim(o.head_dim()), rope_base(o.rope_base), memory(c.anchorkv) {
  const int64_t ds = resolved_memory_width(c, o), r = c.rank, d = o.width;
  scaffold = register_module(
      "scaffold", ScaffoldEncoder(feature_width, ds, stride, c.encoder_blocks, c.dual_context, o.text_dim, c.heads));
  for (int64_t l = 0; l < o.depth; ++l) {
    P.push_back(register_parameter(fmt::format("P{}", l), torch::randn({ds, r}) / std::sqrt(double(ds))));
    UK.push_back(register_parameter(fmt::format("UK{}", l), torch::randn({r, d}) / std::sqrt(double(r))));
    // Zero values: at initialisation the memory adds no content (with the joint
    // normaliser of eq. (15) it still takes attention mass; with `own` it is the identity).
    UV.push_back(register_parameter(fmt::format("UV{}", l), torch::zeros({r, d})));
  }
  if (memory.text_slots.enabled) {
    const int64_t td = o.text_dim;
    text_cond = register_module("text_cond", nn::Sequential(nn::Linear(td, td), nn::SiLU(), nn::Linear(td, td)));
    for (int64_t l = 0; l < o.depth; ++l) {
      PT.push_back(register_parameter(fmt::format("PT{}", l), torch::randn({td, r}) / std::sqrt(double(td))));
      UKT.push_back(register_parameter(fmt::format("UKT{}", l), torch::randn({r, d}) / std::sqrt(double(r))));
      UVT.push_back(register_parameter(fmt::format("UVT{}", l), torch::zeros({r, d})));
    }
  }
}

TokenTransformerHooks AnchorKVAdapterImpl::hooks(const AdapterInputs& in) {
  auto Hs = scaffold(in.features, in.text);  // [B, L, d_s]
  const int64_t B = Hs.size(0), L = Hs.size(1);
  auto pos = torch::arange(L, torch::TensorOptions().dtype(torch::kFloat32).device(Hs.device()));
  torch::Tensor bias;  // token-aligned window: slot m is visible to token n iff |n - m| <= window
  if (memory.window >= 0) {
    auto d = (pos.unsqueeze(1) - pos.unsqueeze(0)).abs();
    bias = torch::zeros({L, L}, Hs.options()).masked_fill(d > memory.window, -std::numeric_limits<float>::infinity());
  }
  // Text slots: [pooled through the condition MLP; word memory], not token-aligned (no
  // RoPE, outside the window).
  torch::Tensor text_mem, text_valid;
  if (memory.text_slots.enabled) {
    text_mem = torch::cat({text_cond->forward(in.text.pooled).unsqueeze(1), in.text.memory}, 1);
    text_valid = torch::cat({torch::ones({B, 1}, in.text.memory_valid.options().dtype(torch::kBool)),
                             in.text.memory_valid.to(torch::kBool)},
                            1);
    if (bias.defined()) bias = torch::cat({bias, torch::zeros({L, text_mem.size(1)}, bias.options())}, 1);
  }
  TokenTransformerHooks h;
  for (size_t l = 0; l < P.size(); ++l) {
    auto low = torch::matmul(Hs, P[l]);                         // H^s P_l
    auto k = torch::matmul(low, UK[l]), v = torch::matmul(low, UV[l]);  // eq. (14)
    // RoPE at the memory slot's token index: the backbone's queries carry RoPE, so
    // <q_n, K^s_m> depends on n - m.
    k = apply_rope(k.view({B, L, heads, head_dim}).transpose(1, 2), pos, rope_base).transpose(1, 2).reshape({B, L, -1});
    LayerKV kv{k, v, in.valid.to(torch::kBool)};  // eq. (15)
    if (memory.text_slots.enabled) {
      auto tl = torch::matmul(text_mem, PT[l]);
      kv.k = torch::cat({kv.k, torch::matmul(tl, UKT[l])}, 1);
      kv.v = torch::cat({kv.v, torch::matmul(tl, UVT[l])}, 1);
      kv.mask = torch::cat({kv.mask, text_valid}, 1);
    }
    kv.bias = bias;
    kv.own_normaliser = memory.normaliser == "own";
    h.extra_kv.push_back(kv);
  }
  return h;
}

// ---------------------------------------------------------------- cross-attention baseline

CrossAttentionAdapterImpl::CrossAttentionAdapterImpl(const AnchorAdapterConfig& c, TokenTransformer bb,
                                                     int64_t stride, int64_t feature_width)
    : backbone(bb), heads(c.heads) {
  const auto& o = bb->opt;
  const int64_t ds = resolved_memory_width(c, o), d = o.width;
  if (d % heads != 0) fail("cross_attention adapter: backbone width {} is not a multiple of heads {}", d, heads);
  scaffold = register_module(
      "scaffold", ScaffoldEncoder(feature_width, ds, stride, c.encoder_blocks, c.dual_context, o.text_dim, c.heads));
  mem_proj = register_module("mem_proj", nn::Linear(ds, d));
  q = register_module("q", nn::ModuleList());
  kv = register_module("kv", nn::ModuleList());
  o_ = register_module("o", nn::ModuleList());
  mlp = register_module("mlp", nn::ModuleList());
  norm1 = register_module("norm1", nn::ModuleList());
  norm2 = register_module("norm2", nn::ModuleList());
  out = register_module("out", nn::ModuleList());
  for (int64_t l = 0; l < o.depth; ++l) {
    q->push_back(nn::Linear(d, d));
    kv->push_back(nn::Linear(d, 2 * d));
    o_->push_back(nn::Linear(d, d));
    mlp->push_back(nn::Sequential(nn::Linear(d, 4 * d), nn::SiLU(), ShardedDropout(c.dropout), nn::Linear(4 * d, d)));
    norm1->push_back(nn::LayerNorm(nn::LayerNormOptions({d})));
    norm2->push_back(nn::LayerNorm(nn::LayerNormOptions({d})));
    out->push_back(zero_linear(d, d));
  }
}

TokenTransformerHooks CrossAttentionAdapterImpl::hooks(const AdapterInputs& in) {
  auto Hs = scaffold(in.features, in.text);
  const int64_t L = Hs.size(1), d = backbone->opt.width;
  auto pe = token_positions(L, d, Hs.device()).unsqueeze(0);
  auto mem = mem_proj(Hs) + pe;
  torch::Tensor a;
  {
    torch::NoGradGuard ng;  // the frozen embedding table
    a = backbone->embed(in.ids);
  }
  a = a + pe;
  auto valid = in.valid.to(torch::kBool);
  TokenTransformerHooks h;
  for (size_t l = 0; l < q->size(); ++l) {
    auto m = kv[l]->as<nn::Linear>()->forward(mem).chunk(2, -1);
    auto qq = q[l]->as<nn::Linear>()->forward(norm1[l]->as<nn::LayerNorm>()->forward(a));
    a = a + o_[l]->as<nn::Linear>()->forward(multi_head(qq, m[0], m[1], valid, heads));
    a = a + mlp[l]->as<nn::Sequential>()->forward(norm2[l]->as<nn::LayerNorm>()->forward(a));
    h.block_residuals.push_back(out[l]->as<nn::Linear>()->forward(a));
  }
  return h;
}

// ---------------------------------------------------------------- ControlNet baseline

ControlNetAdapterImpl::ControlNetAdapterImpl(const AnchorAdapterConfig& c, TokenTransformer bb, int64_t stride,
                                             int64_t feature_width)
    : backbone(bb) {
  const auto& o = bb->opt;
  const int64_t ds = resolved_memory_width(c, o), d = o.width;
  scaffold = register_module(
      "scaffold", ScaffoldEncoder(feature_width, ds, stride, c.encoder_blocks, c.dual_context, o.text_dim, c.heads));
  zero_in = register_module("zero_in", zero_linear(ds, d));
  blocks = register_module("blocks", nn::ModuleList());
  zero_out = register_module("zero_out", nn::ModuleList());
  torch::NoGradGuard ng;
  for (int64_t l = 0; l < o.depth; ++l) {
    TokenBlock copy(o);
    // The trainable copy starts as the frozen block.
    auto src = bb->blocks[l]->named_parameters();
    for (auto& p : copy->named_parameters()) p.value().copy_(src[p.key()]);
    auto srcb = bb->blocks[l]->named_buffers();
    for (auto& b : copy->named_buffers()) b.value().copy_(srcb[b.key()]);
    blocks->push_back(copy);
    zero_out->push_back(zero_linear(d, d));
  }
}

TokenTransformerHooks ControlNetAdapterImpl::hooks(const AdapterInputs& in) {
  auto Hs = scaffold(in.features, in.text);
  const int64_t B = in.ids.size(0), L = in.ids.size(1);
  torch::Tensor x, c;
  {
    torch::NoGradGuard ng;  // frozen embedding and conditioning
    x = backbone->embed(in.ids);
    c = backbone->conditioning(backbone->opt.use_time ? in.t.reshape({-1}).expand({B}) : torch::Tensor(),
                               in.text.pooled);
  }
  auto h = x + zero_in(Hs);
  auto pos = torch::arange(L, torch::TensorOptions().dtype(torch::kFloat32).device(h.device()));
  auto valid = in.valid.to(torch::kBool);
  TokenTransformerHooks hk;
  for (size_t l = 0; l < blocks->size(); ++l) {
    h = blocks[l]->as<TokenBlockImpl>()->forward(h, c, in.text, valid, pos);
    hk.block_residuals.push_back(zero_out[l]->as<nn::Linear>()->forward(h));
  }
  return hk;
}

std::shared_ptr<AnchorAdapterModule> make_anchor_adapter(const AnchorAdapterConfig& c, TokenTransformer backbone,
                                                         int64_t stride) {
  const int64_t fw = adapter_feature_width(c.body_joints, c.features);
  if (c.adapter == "anchorkv") return AnchorKVAdapter(c, backbone->opt, stride, fw).ptr();
  if (c.adapter == "cross_attention") return CrossAttentionAdapter(c, backbone, stride, fw).ptr();
  if (c.adapter == "controlnet") return ControlNetAdapter(c, backbone, stride, fw).ptr();
  fail("model.adapter: unknown adapter '{}'; use anchorkv, cross_attention or controlnet", c.adapter);
}

// ---------------------------------------------------------------- trainer

namespace {

const char* kMetaFile = "adapter_meta.yaml";

void freeze(nn::Module& m) {
  for (auto& p : m.parameters()) p.set_requires_grad(false);
}

class AnchorAdapterTrainer : public Trainable {
 public:
  AnchorAdapterTrainer(const AnchorAdapterConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    tmd_run_ = trained_run("model.tmd", c.tmd_run, c.tmd_config, c.tmd_overrides);
    prior_ = std::make_shared<TokenPrior>(TokenPrior::load(tmd_run_, ctx.device));
    if (!prior_->is_tmd()) fail("model.tmd_run: '{}' is not a tmd_prior run", tmd_run_);
    prior_->tokenizer().check_compatible(ctx.data->set(), ctx.data->source());
    // eq. (16) trains the condition path only: backbone, text encoder and decoder are frozen.
    freeze(*prior_->net());
    VqTokenizer tok = prior_->tokenizer().model;  // a handle: the loader's copy is const
    freeze(*tok);
    for (auto& f : c.families) families_.push_back(parse_anchor_family(f, "model.families"));
    stride_ = prior_->stride();
    adapter_ = make_anchor_adapter(c, prior_->net()->transformer, stride_);
    adapter_->to(ctx.device);
    tokenize_dataset();
  }
  nn::Module& module() override { return *adapter_; }
  std::vector<torch::Tensor> trainable_parameters() override {
    std::vector<torch::Tensor> out;
    for (auto& p : adapter_->parameters())
      if (p.requires_grad()) out.push_back(p);
    return out;
  }

  // Every draw (captions, anchor sets, t, drops, corruptions) is made for the whole
  // batch and cut to the shard's rows (train/batch_shard.h).
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    const MotionSet& set = ctx_.data->set();
    std::vector<std::string> caps;
    std::vector<AnchorSet> sets;
    for (int64_t i : idx) {
      const auto& c = set.captions[i];
      caps.push_back(c[torch::randint(0, static_cast<int64_t>(c.size()), {1}).item<int64_t>()]);
      sets.push_back(draw_training_set(i, torch::randint(0, int64_t{1} << 62, {1}).item<int64_t>()));
    }
    const int64_t B = idx.size();
    auto t = torch::rand({B});
    if (cfg_.training.t_power != 1.0) t = t.pow(cfg_.training.t_power);  // low-t emphasis
    auto drop = torch::rand({B}) < cfg_.cond_drop;
    // Rollout states (ours): drawn for the whole batch, and only when enabled, so runs
    // without them keep their random stream.
    Rollout ro;
    const auto& rc = cfg_.training.rollout;
    if (rc.prob > 0) {
      ro.on = torch::rand({1}).item<double>() < rc.prob;
      ro.k = torch::randint(1, rc.steps, {1}).item<int64_t>();
      auto s = torch::randint(0, int64_t{1} << 62, {B}, torch::kInt64);
      ro.seeds.assign(s.data_ptr<int64_t>(), s.data_ptr<int64_t>() + B);
    }
    auto r = controlled_loss(idx, caps, sets, t, drop, nullptr, cfg_.training.zero_features, shard, &ro);
    LossOutput out;
    out.loss = cfg_.lambda_anc > 0 ? r.ce + cfg_.lambda_anc * r.anc : r.ce;  // eq. (16)
    if (ro.on) {
      // A rollout batch (ours): its own weights when rollout.loss sets them.
      const auto& lw = rc.loss;
      const double wa = lw.anchor_weight < 0 ? cfg_.lambda_anc : lw.anchor_weight;
      out.loss = lw.ce_weight * r.ce + (wa > 0 ? wa * r.anc : torch::zeros_like(r.ce));
    }
    out.parts = {{"ce", r.ce.detach()}, {"anc", r.anc.detach()}, {"ctrl_err", r.ctrl}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Validation CE and soft-decoded anchor error with fixed draws (the same clips, anchors,
  // captions and corruption at every call): at t = 0.5, and at t = 0.1 (mostly noise, where
  // anchors should matter most) with the real and with zeroed adapter features. The gap
  // between the last two is what the adapter takes from the anchors.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    adapter_->eval();
    auto idx = ctx_.data->split("val");
    const MotionSet& set = ctx_.data->set();
    struct Acc {
      double ce = 0, ctrl = 0, n = 0;
    };
    auto pass = [&](double t, bool zero_features) {
      auto gen = at::make_generator<at::CPUGeneratorImpl>(20240611);
      Acc a;
      for (size_t s = 0; s < idx.size(); s += 32) {
        std::vector<int64_t> chunk(idx.begin() + s, idx.begin() + std::min(idx.size(), s + 32));
        std::vector<std::string> caps;
        std::vector<AnchorSet> sets;
        for (int64_t i : chunk) {
          caps.push_back(set.captions[i][0]);
          sets.push_back(draw_training_set(i, static_cast<int64_t>(i) * 7919 + 17));
        }
        const int64_t B = chunk.size();
        auto r = controlled_loss(chunk, caps, sets, torch::full({B}, t), torch::zeros({B}, torch::kBool), &gen,
                                 zero_features);
        a.ce += r.ce.item<double>() * B;
        a.ctrl += r.ctrl.item<double>() * B;
        a.n += B;
      }
      a.n = std::max(1.0, a.n);
      return a;
    };
    const bool z = cfg_.training.zero_features;
    auto mid = pass(0.5, z), low = pass(0.1, z), low0 = pass(0.1, true);
    std::map<std::string, double> extra;
    if (cfg_.training.rollout.prob > 0) extra["val_rollout_control_error"] = rollout_validation(idx);
    adapter_->train();
    std::map<std::string, double> out = {{"val_ce", mid.ce / mid.n},
            {"val_soft_control_error", mid.ctrl / mid.n},
            {"val_ce_t01", low.ce / low.n},
            {"val_soft_control_error_t01", low.ctrl / low.n},
            {"val_ce_t01_zeroed", low0.ce / low0.n},
            {"val_soft_control_error_t01_zeroed", low0.ctrl / low0.n},
            {"adapter_parameters", static_cast<double>(count_parameters(*adapter_))}};
    out.insert(extra.begin(), extra.end());
    return out;
  }

  void save_artifacts(const fs::path& outputs) override {
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "tmd_run" << YAML::Value << tmd_run_ << YAML::Key << "adapter"
      << YAML::Value << cfg_.adapter << YAML::Key << "trainable_parameters" << YAML::Value
      << count_parameters(*adapter_) << YAML::Key << "feature_width" << YAML::Value
      << adapter_feature_width(cfg_.body_joints, cfg_.features) << YAML::Key << "data" << YAML::Value << ctx_.data->source()
      << YAML::EndMap;
    write_file_atomic(outputs / kMetaFile, std::string(e.c_str()) + "\n");
    write_file_atomic(outputs / "trainable_parameters.txt", fmt::format("{}\n", count_parameters(*adapter_)));
  }

 private:
  struct Losses {
    torch::Tensor ce, anc, ctrl;  // scalars; ctrl = mean anchor error of the soft decode (metres)
  };
  struct Rollout {
    bool on = false;
    int64_t k = 0;               // the state after k of training.rollout.steps sampler steps
    std::vector<int64_t> seeds;  // per row of the whole batch
  };

  // The adapter's features of each row's anchors (zero past each clip; all zero for the
  // audit twin), without the feedback block. [B, frames, width] CPU.
  torch::Tensor anchor_features(const std::vector<AnchorSet>& sets, int64_t frames, bool zero_features) const {
    auto feats = torch::zeros({static_cast<int64_t>(sets.size()), frames,
                               adapter_feature_width(cfg_.body_joints, cfg_.features)});
    if (!zero_features)
      for (size_t b = 0; b < sets.size(); ++b)
        feats[b].narrow(0, 0, sets[b].frames).copy_(adapter_features(sets[b], cfg_.body_joints, cfg_.features));
    return feats;
  }

  // feats with the feedback block filled against the frozen prior's estimate at `ids`
  // (a copy; feats itself when feedback is off or the features are zeroed).
  torch::Tensor with_feedback(const torch::Tensor& feats, const std::vector<AnchorSet>& sets, const torch::Tensor& ids,
                              const torch::Tensor& t, const TextContext& caption_text, const torch::Tensor& valid,
                              bool zero_features) const {
    if (!cfg_.features.feedback.enabled || zero_features) return feats;
    auto f = feats.clone();
    fill_feedback_features(f, sets, frozen_soft_estimate(*prior_, ids, t, caption_text, valid), prior_->skeleton(),
                           cfg_.body_joints, cfg_.features);
    return f;
  }

  // The TMD sampler's state after k of training.rollout.steps steps from uniform tokens
  // (final: the last step's argmax after all of them), conditioned by the adapter being
  // trained (eval mode, no gradient) through CFG on the caption, as the generator samples
  // (samplers/tmd_sampler.cpp; the step is tmd_sampler_step). Row b's randomness comes
  // from its own generator seeded by seeds[b], so a row's state depends neither on the
  // batch nor on the data-parallel shard.
  torch::Tensor rollout_tokens(const std::vector<AnchorSet>& sets, const torch::Tensor& feats,
                               const TextContext& caption_text, const torch::Tensor& valid, int64_t k, bool final,
                               const std::vector<int64_t>& seeds, bool zero_features) {
    torch::NoGradGuard ng;
    const auto& rc = cfg_.training.rollout;
    const auto& pc = prior_->tmd_config();
    const auto dev = ctx_.device;
    const int64_t B = valid.size(0), L = valid.size(1), full = tokens_.size(1), K = prior_->codebook_size();
    constexpr double kRateEps = 1e-3;  // the sampler's default t_eps
    std::vector<at::Generator> gens;
    std::vector<torch::Tensor> init;
    for (int64_t b = 0; b < B; ++b) {
      gens.push_back(at::make_generator<at::CPUGeneratorImpl>(static_cast<uint64_t>(seeds[b])));
      init.push_back(
          torch::randint(0, K, {full}, gens.back(), torch::TensorOptions().dtype(torch::kInt64)).narrow(0, 0, L));
    }
    auto x = torch::stack(init).to(dev);
    const bool was_training = adapter_->is_training();
    adapter_->eval();
    const auto null_text = prior_->null_texts(B, caption_text.memory.size(1));
    const auto dist = prior_->distance();
    const double h = 1.0 / rc.steps;
    const int64_t calls = final ? rc.steps : k;
    for (int64_t j = 0; j < calls; ++j) {
      auto tv = torch::full({B}, j * h);
      auto f = with_feedback(feats, sets, x, tv.to(dev), caption_text, valid, zero_features);
      AdapterInputs in{x, tv.to(dev), caption_text, valid, f.to(dev)};
      auto hooks = adapter_->guided_hooks(in, null_text);
      auto logits = prior_->guided_logits(x, tv, caption_text, valid, rc.cfg_scale, &hooks);
      if (final && j + 1 == calls) {
        x = logits.argmax(-1);
        break;
      }
      std::vector<torch::Tensor> u;
      for (auto& g : gens) u.push_back(torch::rand({3, full}, g, torch::TensorOptions()).narrow(1, 0, L));
      auto uu = torch::stack(u).to(dev);
      x = tmd_sampler_step(dist, x, logits, j * h, h, kRateEps, pc.beta_c, pc.beta_a, false, 1.0, uu.select(1, 0),
                           uu.select(1, 1), uu.select(1, 2));
    }
    if (was_training) adapter_->train();
    return x;
  }

  // Generator-only anchor error of full rollouts (hard decode of the final tokens, each
  // clip at its own length) on the first rollout.val_clips val clips, fixed draws.
  double rollout_validation(const std::vector<int64_t>& val) {
    const MotionSet& set = ctx_.data->set();
    const int64_t n = std::min<int64_t>(cfg_.training.rollout.val_clips, val.size());
    const int64_t L = tokens_.size(1), Tp = L * stride_, J = prior_->num_joints();
    double sum = 0, count = 0;
    for (int64_t s = 0; s < n; s += 32) {
      std::vector<int64_t> chunk(val.begin() + s, val.begin() + std::min(n, s + 32));
      std::vector<std::string> caps;
      std::vector<AnchorSet> sets;
      std::vector<int64_t> seeds;
      for (int64_t i : chunk) {
        caps.push_back(set.captions[i][0]);
        sets.push_back(draw_training_set(i, static_cast<int64_t>(i) * 7919 + 17));
        seeds.push_back(static_cast<int64_t>(i) * 104729 + 3);
      }
      const int64_t B = chunk.size();
      auto n_tok = token_lengths_.index_select(0, torch::tensor(chunk, torch::kInt64));
      auto valid = (torch::arange(L).unsqueeze(0) < n_tok.unsqueeze(1)).to(ctx_.device);
      const bool z = cfg_.training.zero_features;
      auto x = rollout_tokens(sets, anchor_features(sets, Tp, z), prior_->encode_texts(caps), valid, 0, true, seeds, z)
                   .to(torch::kCPU);
      auto world = torch::zeros({B, Tp, J, 3});
      for (int64_t b = 0; b < B; ++b) {
        const int64_t nt = n_tok[b].item<int64_t>(), len = set.lengths[chunk[b]];
        world[b].narrow(0, 0, len).copy_(prior_->decode_world(x[b].narrow(0, 0, nt).clone()).narrow(0, 0, len));
      }
      auto anchors = make_anchor_batch(sets, torch::kCPU);
      sum += anchor_errors(world, anchors).sum().item<double>();
      count += anchors.valid.sum().item<double>();
    }
    return count > 0 ? sum / count : 0.0;
  }

  AnchorSet draw_training_set(int64_t clip, int64_t seed) const {
    const MotionSet& set = ctx_.data->set();
    std::mt19937_64 rng(static_cast<uint64_t>(seed));
    const int T = set.lengths[clip], J = set.num_joints();
    const float* m = set.joints.data() + clip * set.clip_stride();
    std::uniform_real_distribution<double> u(0.0, 1.0);
    if (cfg_.sparse_keyjoint_prob > 0 && u(rng) < cfg_.sparse_keyjoint_prob)
      return draw_sparse_keyjoint_set(m, T, J, rng, cfg_.sparse_keyjoint_ratio, cfg_.body_joints);
    AnchorFamily f = families_[rng() % families_.size()];
    int K = std::min(cfg_.anchor_counts[rng() % cfg_.anchor_counts.size()], T);
    return draw_anchor_set(f, K, m, T, J, rng, cfg_.body_joints);
  }

  void tokenize_dataset() {
    const MotionSet& set = ctx_.data->set();
    VqTokenizer handle = prior_->tokenizer().model;
    auto tc = tokenize_clips(*handle, set, ctx_.device);
    tokens_ = tc.tokens;
    token_lengths_ = tc.lengths;
    // The ground truth of eq. (10), zero-padded to the tokens' frames.
    const int64_t N = set.size(), J = set.num_joints(), Tm = set.t_max, Tp = tokens_.size(1) * stride_;
    world_ = torch::zeros({N, Tp, J, 3});
    world_.narrow(1, 0, Tm).copy_(
        torch::from_blob(const_cast<float*>(set.joints.data()), {static_cast<int64_t>(N), Tm, J, 3}, torch::kFloat32));
  }

  // Inputs are the whole batch's (corruptions drawn for all of it); a shard computes
  // its rows and its share: sums over its targets and anchors divided by the whole
  // batch's counts.
  Losses controlled_loss(const std::vector<int64_t>& idx_whole, const std::vector<std::string>& caps_whole,
                         const std::vector<AnchorSet>& sets_whole, const torch::Tensor& t, const torch::Tensor& drop,
                         at::Generator* gen, bool zero_features = false, const BatchShard& shard = {},
                         const Rollout* rollout = nullptr) {
    const auto dev = ctx_.device;
    const auto& pc = prior_->tmd_config();
    const int64_t Bw = idx_whole.size(), L = tokens_.size(1), Tp = L * stride_, K = prior_->codebook_size();
    auto ixw = torch::tensor(idx_whole, torch::kInt64);
    auto x1 = tokens_.index_select(0, ixw).to(dev);
    auto n = token_lengths_.index_select(0, ixw);
    auto valid = (torch::arange(L).unsqueeze(0) < n.unsqueeze(1)).to(dev);
    // eq. (19): the TMD corruption path, t ~ U[0, 1 - eps).
    auto tt = (t * (1 - pc.t_eps)).to(dev);
    auto probs = tmd_path_probs(prior_->distance(), x1, tmd_beta(tt, pc.beta_c, pc.beta_a).view({Bw, 1}));
    auto flat = probs.reshape({Bw * L, K}).to(torch::kCPU);
    auto xin = (gen ? torch::multinomial(flat, 1, false, *gen) : torch::multinomial(flat, 1)).view({Bw, L}).to(dev);
    const double whole_tokens = valid.sum().item<double>();
    const std::vector<int64_t> idx = shard.local(idx_whole);
    const std::vector<AnchorSet> sets = shard.local(sets_whole);
    const int64_t B = idx.size();
    auto ix = torch::tensor(idx, torch::kInt64);
    x1 = shard.local(x1);
    valid = shard.local(valid);
    xin = shard.local(xin);
    tt = shard.local(tt);
    auto text = prior_->encode_texts(shard.local(caps_whole));
    const TextContext caption_text = text;  // the feedback estimate reads the caption, as at sampling
    {
      torch::NoGradGuard ng;
      text = prior_->net()->drop_condition(text, shard.local(drop).to(dev));
    }
    auto feats = anchor_features(sets, Tp, zero_features);
    if (rollout && rollout->on) {
      // Rollout states (ours): the sampler's own tokens at t_k replace the path's draw.
      const auto& rc = cfg_.training.rollout;
      xin = rollout_tokens(sets, feats, caption_text, valid, rollout->k, false, shard.local(rollout->seeds),
                           zero_features);
      tt = torch::full({B}, static_cast<double>(rollout->k) / rc.steps).to(dev);
    }
    // Feedback (ours): the anchors against the frozen prior's own estimate at the input tokens.
    feats = with_feedback(feats, sets, xin, tt, caption_text, valid, zero_features);
    AdapterInputs in{xin, tt, text, valid, feats.to(dev)};
    auto hooks = adapter_->hooks(in);
    auto logits = prior_->net()->transformer->forward(xin, tt, text, valid, &hooks).logits;  // [B, L, K]
    auto sel = valid.reshape({-1});
    Losses r;
    if (shard.whole())
      r.ce = F::cross_entropy(logits.reshape({B * L, K}).index({sel}), x1.reshape({-1}).index({sel}));  // eq. (20)
    else
      r.ce = F::cross_entropy(logits.reshape({B * L, K}).index({sel}), x1.reshape({-1}).index({sel}),
                              F::CrossEntropyFuncOptions().reduction(torch::kSum)) /
             std::max(1.0, whole_tokens);
    // eq. (10) through the differentiable soft decode: expected code embedding -> frozen decoder.
    VqTokenizer handle = prior_->tokenizer().model;
    auto& tok = *handle;
    const int64_t J = prior_->num_joints();
    auto world = tok.denormalize(tok.soft_decode(torch::softmax(logits, -1)).view({B, Tp, J, 3}));
    auto gt = world_.index_select(0, ix).to(dev);
    auto support = make_support_batch(sets, cfg_.delta, gt);
    // Mean over support entries (not the sum) so lambda_anc does not scale with K.
    if (shard.whole()) {
      r.anc = anchor_loss(world, support).sum() / support.valid.sum().clamp_min(1.0);
      r.ctrl = mean_control_error(world, make_anchor_batch(sets, dev)).detach();
    } else {
      auto anchors = make_anchor_batch(sets, dev);
      const double entries = shard.sum(support.valid.sum().item<double>());
      const double count = shard.sum(anchors.valid.sum().item<double>());
      r.anc = anchor_loss(world, support).sum() / std::max(1.0, entries);
      r.ctrl = count > 0 ? (anchor_errors(world, anchors).sum() / count).detach() : torch::zeros({}, world.options());
      return r;  // non-finite values are the trainer's to catch: every rank sees the summed loss
    }
    if (!torch::isfinite(r.ce).item<bool>() || !torch::isfinite(r.anc).item<bool>())
      fail("anchor_adapter: non-finite loss (ce {}, anchor {}); lower optim.lr", r.ce.item<double>(),
           r.anc.item<double>());
    return r;
  }

  AnchorAdapterConfig cfg_;
  TrainContext ctx_;
  std::string tmd_run_;
  std::shared_ptr<TokenPrior> prior_;
  std::shared_ptr<AnchorAdapterModule> adapter_;
  std::vector<AnchorFamily> families_;
  int64_t stride_ = 4;
  torch::Tensor tokens_, token_lengths_;  // [N, L], [N] CPU
  torch::Tensor world_;                   // [N, L * stride, J, 3] ground truth, zero-padded
};

std::unique_ptr<Trainable> make_adapter_trainer(const Config& c, const TrainContext& ctx) {
  return std::make_unique<AnchorAdapterTrainer>(dynamic_cast<const AnchorAdapterConfig&>(c), ctx);
}

}  // namespace

MC_REGISTER_MODEL("anchor_adapter", AnchorAdapterConfig, make_adapter_trainer,
                  "AnchorRoute's anchor condition path (AnchorKV / cross-attention / ControlNet) on a frozen TMD "
                  "prior, eq. (16)");

// ---------------------------------------------------------------- loading

LoadedAnchorAdapter load_anchor_adapter(const std::string& run_dir, torch::Device device) {
  TrainedRun run = open_trained_run(run_dir, {"anchor adapter", {"anchor_adapter"}, {kMetaFile},
                                              "train one with `motionctl train configs/adapter/anchorkv_tiny.yaml` "
                                              "(or set adapter_config to train it first)"});
  LoadedAnchorAdapter out;
  out.run_dir = run_dir;
  out.cfg = run.model.as<AnchorAdapterConfig>();
  std::string tmd_run;
  run.read_meta(kMetaFile, [&](const YAML::Node& meta) { tmd_run = run.dependency(meta["tmd_run"].as<std::string>()); });
  out.prior = std::make_shared<TokenPrior>(TokenPrior::load(tmd_run, device));
  out.module = make_anchor_adapter(out.cfg, out.prior->net()->transformer, out.prior->stride());
  run.load_weights(*out.module);
  out.module->to(device);
  out.module->eval();
  out.trainable_parameters = count_parameters(*out.module);
  return out;
}

}  // namespace mc
