// The contrastive text encoder (model type `text_clip`): motion encoder, symmetric
// InfoNCE, pooled retrieval accuracy, its trainer, and loading its text half into
// a prior.
#include "models/text_clip.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <optional>
#include <ostream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "models/flow_transformer.h"
#include "models/sharded_dropout.h"
#include "models/token_prior.h"
#include "core/trained_runs.h"
#include "models/trainable.h"
#include "models/trained_run.h"

namespace mc {
namespace nn = torch::nn;

// ---------------------------------------------------------------- config

std::string TextClipConfig::validate() const {
  if (auto e = text_fields_error(); !e.empty()) return e;
  if (motion_width % motion_heads != 0)
    return fmt::format("motion_width {} is not a multiple of motion_heads {}", motion_width, motion_heads);
  if (motion_width % 2 != 0) return fmt::format("motion_width {} must be even (sinusoidal positions)", motion_width);
  if (1.0 / init_temperature > max_logit_scale)
    return fmt::format("1 / init_temperature = {} exceeds max_logit_scale {}", 1.0 / init_temperature,
                       max_logit_scale);
  return "";
}

// ---------------------------------------------------------------- networks

ClipMotionEncoderImpl::ClipMotionEncoderImpl(int num_joints, const TextClipConfig& c)
    : width(c.motion_width), stride(c.motion_stride) {
  input = register_module("input", nn::Linear(num_joints * 9 * c.motion_stride, c.motion_width));
  auto layer = nn::TransformerEncoderLayer(nn::TransformerEncoderLayerOptions(c.motion_width, c.motion_heads)
                                               .dim_feedforward(c.motion_ff)
                                               .dropout(c.motion_dropout)
                                               .activation(torch::kGELU));
  encoder = register_module("encoder", nn::TransformerEncoder(nn::TransformerEncoderOptions(layer, c.motion_layers)));
  norm = register_module("norm", nn::LayerNorm(nn::LayerNormOptions({c.motion_width})));
  out = register_module("out", nn::Linear(c.motion_width, c.text_width));
}

torch::Tensor ClipMotionEncoderImpl::forward(const torch::Tensor& joints, const torch::Tensor& mask) {
  const int64_t B = joints.size(0), T = joints.size(1), J = joints.size(2);
  auto valid = mask.to(joints.device(), torch::kBool);
  auto m = valid.view({B, T, 1, 1}).to(joints.dtype());
  auto x = joints * m;
  // The normalised world joints carry where the body is; the root-relative pose and
  // the per-frame displacement carry what it does, which is what captions describe.
  auto pose = (x - x.narrow(2, 0, 1)) * m;
  auto vel = torch::zeros_like(x);
  if (T > 1) vel.narrow(1, 1, T - 1).copy_((x.narrow(1, 1, T - 1) - x.narrow(1, 0, T - 1)) * m.narrow(1, 1, T - 1) *
                                           m.narrow(1, 0, T - 1));
  auto feats = torch::cat({x, pose, vel}, -1).reshape({B, T, J * 9});
  // Tokens of `stride` frames: pad T up to a multiple (zero features), one token per
  // group, valid when its first frame is (the rest of a clip's last group is zero).
  const int64_t N = (T + stride - 1) / stride, Tp = N * stride;
  auto tok_valid = valid;
  if (Tp > T) {
    feats = torch::cat({feats, torch::zeros({B, Tp - T, J * 9}, feats.options())}, 1);
    tok_valid = torch::cat({valid, torch::zeros({B, Tp - T}, valid.options())}, 1);
  }
  tok_valid = tok_valid.view({B, N, stride}).select(2, 0);
  feats = feats.reshape({B, N, stride * J * 9});
  auto pos = torch::arange(N, torch::TensorOptions().dtype(torch::kFloat32).device(joints.device()));
  auto h = input(feats) + timestep_sinusoid(pos, width).unsqueeze(0);
  h = transformer_encoder_forward(*encoder, h.transpose(0, 1), tok_valid.logical_not()).transpose(0, 1);
  auto w = tok_valid.unsqueeze(-1).to(h.dtype());
  auto pooled = (h * w).sum(1) / w.sum(1).clamp_min(1.0);
  return out(norm(pooled));
}

TextClipNetImpl::TextClipNetImpl(int vocab_size, int num_joints, const TextClipConfig& c)
    : max_logit_scale(c.max_logit_scale) {
  text = register_module("text", TextEncoder(c.text_encoder_options(vocab_size)));
  motion = register_module("motion", ClipMotionEncoder(num_joints, c));
  logit_scale = register_parameter("logit_scale", torch::full({}, std::log(1.0 / c.init_temperature)));
}

torch::Tensor TextClipNetImpl::scale() const { return logit_scale.exp().clamp_max(max_logit_scale); }

// ---------------------------------------------------------------- loss and retrieval

torch::Tensor same_caption_matrix(const std::vector<std::string>& captions) {
  const int64_t B = captions.size();
  auto s = torch::zeros({B, B}, torch::kBool);
  auto a = s.accessor<bool, 2>();
  for (int64_t i = 0; i < B; ++i)
    for (int64_t j = 0; j < B; ++j) a[i][j] = captions[i] == captions[j];
  return s;
}

torch::Tensor clip_infonce(const torch::Tensor& text, const torch::Tensor& motion, const torch::Tensor& scale,
                           const torch::Tensor& same) {
  TORCH_CHECK(text.dim() == 2 && text.sizes() == motion.sizes(), "clip_infonce needs two [B, D] batches, got ",
              text.sizes(), " and ", motion.sizes());
  const int64_t B = text.size(0);
  auto tn = torch::nn::functional::normalize(text, torch::nn::functional::NormalizeFuncOptions().dim(1));
  auto mn = torch::nn::functional::normalize(motion, torch::nn::functional::NormalizeFuncOptions().dim(1));
  auto logits = scale * torch::matmul(tn, mn.t());  // [B texts, B motions]
  auto pos = same.defined() ? same.to(text.device(), torch::kBool)
                            : torch::eye(B, torch::TensorOptions().dtype(torch::kBool).device(text.device()));
  auto target = pos.to(logits.dtype());
  target = target / target.sum(1, true);  // `same` is symmetric: rows serve both directions
  auto t2m = -(target * torch::log_softmax(logits, 1)).sum(1).mean();
  auto m2t = -(target * torch::log_softmax(logits.t(), 1)).sum(1).mean();
  return 0.5 * (t2m + m2t);
}

std::vector<double> clip_retrieval(const torch::Tensor& text, const torch::Tensor& motion, int pool, int top_k) {
  TORCH_CHECK(text.sizes() == motion.sizes(), "clip_retrieval: text ", text.sizes(), " vs motion ", motion.sizes());
  TORCH_CHECK(pool >= 1 && top_k >= 1 && top_k <= pool, "clip_retrieval: bad pool ", pool, " / top_k ", top_k);
  const int64_t pools = text.size(0) / pool;
  std::vector<double> hits(top_k, 0.0);
  if (pools == 0) return hits;
  auto nf = torch::nn::functional::NormalizeFuncOptions().dim(1);
  auto tn = torch::nn::functional::normalize(text.to(torch::kCPU, torch::kFloat64), nf);
  auto mn = torch::nn::functional::normalize(motion.to(torch::kCPU, torch::kFloat64), nf);
  for (int64_t p = 0; p < pools; ++p) {
    auto sim = torch::matmul(tn.narrow(0, p * pool, pool), mn.narrow(0, p * pool, pool).t()).contiguous();
    auto a = sim.accessor<double, 2>();
    for (int i = 0; i < pool; ++i) {
      int rank = 0;
      for (int j = 0; j < pool; ++j)
        if (j != i && (a[i][j] > a[i][i] || (a[i][j] == a[i][i] && j < i))) ++rank;
      for (int k = rank; k < top_k; ++k) hits[k] += 1.0;
    }
  }
  for (double& h : hits) h /= static_cast<double>(pools * pool);
  return hits;
}

// ---------------------------------------------------------------- runs

TextClipRun read_text_clip_run(const std::string& run_dir) {
  TrainedRun run = open_trained_run(
      run_dir, {"contrastive text encoder", {"text_clip"}, {"vocab.txt"},
                "train one with `motionctl train configs/text/text_clip_tiny.yaml` or set model.text_encoder.config "
                "to train it first"});
  TextClipRun r;
  r.run_dir = run_dir;
  r.cfg = run.model.as<TextClipConfig>();
  r.vocab = run.vocab_words();
  TextVocab check(r.vocab, run.output("vocab.txt").string());  // UserError when malformed
  (void)check;
  return r;
}

std::string resolve_text_clip_run(const TextEncoderSourceConfig& src, std::ostream* log) {
  if (!src.run_dir.empty()) {
    if (log) *log << fmt::format("text encoder: the text_clip run {}\n", src.run_dir);
    return src.run_dir;
  }
  if (src.config.empty()) fail("model.text_encoder: set run_dir (a finished text_clip run) or config");
  return trained_run("model.text_encoder", src.run_dir, src.config, src.overrides);
}

void load_text_clip_encoder(const TextClipRun& run, torch::nn::Module& enc, const TextEncoderOptions& want,
                            const std::string& what) {
  const TextEncoderOptions have = run.cfg.text_encoder_options(static_cast<int>(run.vocab.size()));
  auto check = [&](const char* key, int a, int b) {
    if (a != b)
      fail("{}: the text_clip run '{}' has model.{} = {} but this model has {} = {}; give both the same text "
           "encoder sizes (text_width, text_layers, text_heads, text_ff, max_words)",
           what, run.run_dir, key, a, key, b);
  };
  check("text_width", have.width, want.width);
  check("text_layers", have.layers, want.layers);
  check("text_heads", have.heads, want.heads);
  check("text_ff", have.ff, want.ff);
  check("max_words", have.max_words, want.max_words);
  if (have.vocab_size != want.vocab_size)
    fail("{}: the text_clip run '{}' has a vocabulary of {} words but the encoder was built for {}", what,
         run.run_dir, have.vocab_size, want.vocab_size);
  const fs::path final_pt = fs::path(run.run_dir) / "checkpoints" / "final.pt";
  try {
    torch::serialize::InputArchive ar, text_ar;
    ar.load_from(final_pt.string());
    ar.read("text", text_ar);
    read_module_weights(text_ar, enc);
  } catch (const c10::Error& e) {
    fail("{}: cannot read the text encoder from '{}' ({})", what, final_pt.string(),
         std::string(e.what_without_backtrace()).substr(0, 200));
  } catch (const std::exception& e) {  // torch::jit::ErrorReport on a damaged file
    fail("{}: cannot read the text encoder from '{}' ({})", what, final_pt.string(),
         std::string(e.what()).substr(0, 200));
  }
}

// ---------------------------------------------------------------- trainer

namespace {

class TextClipTrainer : public Trainable {
 public:
  TextClipTrainer(const TextClipConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    const MotionSet& set = ctx.data->set();
    // The flow prior's vocabulary rule, so a prior on the same data sees the same ids.
    vocab_ = set.vocab.empty() ? TextVocab::build(set) : TextVocab(set.vocab, ctx.data->source());
    net_ = TextClipNet(vocab_.size(), ctx.data->num_joints(), c);
  }
  nn::Module& module() override { return *net_; }

  // One random caption per clip, each clip once (a batch that wraps an epoch could
  // hold one twice, which would be its own negative). A data-parallel shard embeds
  // its rows of the deduplicated batch, gathers every rank's embeddings and computes
  // the whole batch's InfoNCE (train/batch_shard.h: replicated, the temperature
  // shared), so its gradient is the one-process gradient through its own rows.
  LossOutput loss(const std::vector<int64_t>& idx_in, const BatchShard& shard) override {
    std::vector<int64_t> idx;
    for (int64_t i : idx_in)
      if (std::find(idx.begin(), idx.end(), i) == idx.end()) idx.push_back(i);
    const int64_t n = idx.size();
    std::optional<BatchRowsScope> rows;  // dropout over the deduplicated batch's rows
    if (!shard.whole()) rows.emplace(shard.rows(n));
    MotionBatch b = ctx_.data->batch(idx, ctx_.window, 1, ctx_.device, ctx_.trim_padding, shard);
    const std::vector<std::string> caps = ctx_.data->drawn_captions(idx);
    auto [text, motion] = embed(b, shard.local(caps));
    auto scale = shard.shared(net_->scale());
    auto l = shard.replicated(
        clip_infonce(shard.gather(text, n), shard.gather(motion, n), scale, same_caption_matrix(caps)));
    LossOutput out;
    out.loss = l;
    out.parts = {{"nce", l.detach()}, {"logit_scale", shard.replicated(net_->scale().detach())}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Whole val clips with their first caption, in pools of eval_pool: the InfoNCE
  // loss per pool and text->motion retrieval top-1/top-3 (R-precision's convention;
  // chance is k / pool), plus motion->text top-3.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    net_->eval();
    auto idx = ctx_.data->split("val");
    std::vector<torch::Tensor> ts, ms;
    std::vector<std::string> all_caps;
    for (const auto& chunk : chunked(idx, 64)) {
      MotionBatch b = ctx_.data->batch(chunk, 0, 1, ctx_.device, true);
      const std::vector<std::string> caps = ctx_.data->first_captions(chunk);
      auto [t, m] = embed(b, caps);
      ts.push_back(t.cpu());
      ms.push_back(m.cpu());
      all_caps.insert(all_caps.end(), caps.begin(), caps.end());
    }
    auto text = torch::cat(ts), motion = torch::cat(ms);
    const int pool = cfg_.eval_pool, k = std::min(3, pool);
    std::map<std::string, double> out;
    const int64_t pools = text.size(0) / pool;
    if (pools == 0) {
      out["val_pools"] = 0;
      return out;
    }
    double loss = 0;
    auto scale = net_->scale().cpu();
    for (int64_t p = 0; p < pools; ++p) {
      std::vector<std::string> caps(all_caps.begin() + p * pool, all_caps.begin() + (p + 1) * pool);
      loss += clip_infonce(text.narrow(0, p * pool, pool), motion.narrow(0, p * pool, pool), scale,
                           same_caption_matrix(caps))
                  .item<double>();
    }
    auto t2m = clip_retrieval(text, motion, pool, k);
    auto m2t = clip_retrieval(motion, text, pool, k);
    out["val_nce"] = loss / pools;
    out["val_top1"] = t2m[0];
    out["val_top3"] = t2m[k - 1];
    out["val_m2t_top3"] = m2t[k - 1];
    out["val_pools"] = static_cast<double>(pools);
    out["temperature"] = 1.0 / scale.item<double>();
    return out;
  }

  // Multiply-adds x2 of both encoders over their valid tokens, x3 for forward + backward.
  double flops_per_step(const std::vector<int64_t>& idx) const override {
    const double dt = cfg_.text_width, ft = cfg_.text_ff, w = cfg_.max_words;
    const double dm = cfg_.motion_width, fm = cfg_.motion_ff, in = ctx_.data->num_joints() * 9.0;
    double fwd = 0;
    for (int64_t i : idx) {
      const double L = std::min<int64_t>(ctx_.data->length(i), ctx_.window > 0 ? ctx_.window : INT64_MAX);
      fwd += w * cfg_.text_layers * (8 * dt * dt + 4 * dt * ft + 4 * w * dt) + 2 * dt * dt;
      const double N = std::ceil(L / cfg_.motion_stride);  // motion tokens
      fwd += L * 2 * in * dm + N * cfg_.motion_layers * (8 * dm * dm + 4 * dm * fm + 4 * N * dm) + 2 * dm * dt;
    }
    return 3 * fwd;
  }

  void save_artifacts(const fs::path& outputs) override {
    std::string words;
    for (auto& w : vocab_.words()) words += w + "\n";
    write_file_atomic(outputs / "vocab.txt", words);
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "data" << YAML::Value << ctx_.data->source() << YAML::Key << "num_joints"
      << YAML::Value << ctx_.data->num_joints() << YAML::EndMap;
    write_file_atomic(outputs / "text_clip_meta.yaml", std::string(e.c_str()) + "\n");
  }

 private:
  std::pair<torch::Tensor, torch::Tensor> embed(const MotionBatch& b, const std::vector<std::string>& caps) {
    auto enc = encode_captions(vocab_, caps, cfg_.max_words);
    auto text = net_->text->forward(enc.ids.to(ctx_.device), enc.lengths.to(ctx_.device));
    auto motion = net_->motion->forward(b.joints, b.mask);
    return {text, motion};
  }

  TextClipConfig cfg_;
  TrainContext ctx_;
  TextVocab vocab_{TextVocab::special_tokens()};
  TextClipNet net_{nullptr};
};

}  // namespace

MC_REGISTER_MODEL("text_clip", TextClipConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<TextClipTrainer>(dynamic_cast<const TextClipConfig&>(c), ctx);
                  },
                  "CLIP-style text encoder (the priors' architecture) trained with symmetric InfoNCE against a small "
                  "motion encoder, to be frozen inside a prior (model.text_encoder)");

}  // namespace mc
