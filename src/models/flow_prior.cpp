// The flow prior's text encoder, network bundle and trainer (model type
// `flow_prior`): rectified-flow velocity regression with condition dropout; the
// trained prior loaded from its run directory, its guided velocity and normaliser.
#include "models/flow_prior.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <iostream>
#include <optional>

#include "core/atomic_file.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "models/text_clip.h"
#include "models/trained_run.h"
#include "models/trainable.h"

namespace mc {
namespace nn = torch::nn;

// ---------------------------------------------------------------- config

std::string FlowPriorConfig::validate() const {
  int w = width > 0 ? width : 64 * depth, h = heads > 0 ? heads : depth;
  if (w % h != 0) return fmt::format("width {} is not a multiple of heads {}", w, h);
  if ((w / h) % 2 != 0) return fmt::format("head size width/heads = {} must be even for RoPE", w / h);
  if (auto e = text_fields_error(); !e.empty()) return e;
  if (eval_t.empty()) return "eval_t needs at least one flow time";
  if (temporal_kernel % 2 == 0) return fmt::format("temporal_kernel {} must be odd (centred on its frame)", temporal_kernel);
  if (kinematic_head.skip.enabled && !kinematic_head.enabled)
    return "kinematic_head.skip.enabled needs kinematic_head.enabled (the skip acts on the head's channels)";
  if (kinematic_head.skip.enabled && kinematic_head.noise.enabled)
    return "kinematic_head.skip.enabled assumes the papers' N(0, I) source noise: turn kinematic_head.noise off";
  if (kinematic_head.noise.enabled && !kinematic_head.enabled)
    return "kinematic_head.noise.enabled needs kinematic_head.enabled (its channel statistics shape the noise)";
  if (kinematic_head.bones.enabled && !kinematic_head.enabled)
    return "kinematic_head.bones.enabled needs kinematic_head.enabled (bones are the head's pose channels)";
  if (kinematic_head.bones.rigid && !kinematic_head.bones.enabled)
    return "kinematic_head.bones.rigid needs kinematic_head.bones.enabled (it fixes the bone vectors' lengths)";
  if (kinematic_head.bones.enabled && (kinematic_head.noise.enabled || kinematic_head.skip.enabled))
    return "kinematic_head.bones.enabled is not combined with kinematic_head.noise or kinematic_head.skip (both "
           "read the pose channels as root-relative joints): turn those off";
  if (kinematic_head.enabled && prediction != "clean")
    return "kinematic_head.enabled needs prediction: clean (the head states the clean endpoint x1_hat)";
  if (prediction == "velocity" && loss == "clean")
    return "loss: clean needs prediction: clean (a velocity network's clean error is its velocity error times 1 - t)";
  return "";
}

FlowTransformerOptions FlowPriorConfig::transformer_options(int num_joints) const {
  FlowTransformerOptions o;
  o.num_joints = num_joints;
  o.depth = depth;
  o.width = width > 0 ? width : 64 * depth;
  o.heads = heads > 0 ? heads : depth;
  o.mlp_hidden = mlp_hidden;
  o.dropout = dropout;
  o.cond_dim = text_width;
  o.temporal_kernel = temporal_kernel;
  if (kinematic_head.enabled) o.out_channels = kinematic_channel_count(num_joints);
  return o;
}

// ---------------------------------------------------------------- bundle

FlowPriorNetImpl::FlowPriorNetImpl(int vocab_size, int num_joints, const FlowPriorConfig& c) {
  text = register_module("text", TextEncoder(c.text_encoder_options(vocab_size)));
  transformer = register_module("transformer", FlowTransformer(c.transformer_options(num_joints)));
  null_text = register_parameter("null_text", torch::randn({c.text_width}) * 0.02);
  joint_mean = register_buffer("joint_mean", torch::zeros({3}));
  joint_std = register_buffer("joint_std", torch::ones({3}));
  clean_prediction = c.prediction == "clean";
  if (c.text_encoder.enabled()) {
    // Registered last: a prior without the switch draws its initial weights
    // exactly as before. The contrastive vector's scale is arbitrary (only its
    // direction was trained), hence the LayerNorm first.
    const int64_t w = c.text_width;
    text_adapter = register_module(
        "text_adapter", nn::Sequential(nn::LayerNorm(nn::LayerNormOptions({w})), nn::Linear(w, w),
                                       nn::GELU(), nn::Linear(w, w)));
    text_frozen = c.text_encoder.frozen;
  }
  if (c.kinematic_head.enabled) {
    kinematic_head = true;
    const int64_t C = kinematic_channel_count(num_joints);
    kin_mean = register_buffer("kin_mean", torch::zeros({C}));
    kin_std = register_buffer("kin_std", torch::ones({C}));
    kinematic_noise = c.kinematic_head.noise.enabled;
    kinematic_skip = c.kinematic_head.skip.enabled;
    if (c.kinematic_head.bones.enabled) {
      kinematic_bones = true;
      kinematic_rigid = c.kinematic_head.bones.rigid;
      const int64_t n = num_joints - 1;
      kin_from_bones = register_buffer("kin_from_bones", torch::eye(n));
      kin_to_bones = register_buffer("kin_to_bones", torch::eye(n));
      kin_bone_length = register_buffer("kin_bone_length", torch::ones({n}));
    }
  }
}

torch::Tensor FlowPriorNetImpl::head_target_channels(const torch::Tensor& world, const torch::Tensor& mask) const {
  auto ch = kinematic_channels(world, mask);
  return kinematic_bones ? map_pose_block(ch, kin_to_bones) : ch;
}

torch::Tensor FlowPriorNetImpl::head_channels(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                                              const torch::Tensor& mask) const {
  if (!kinematic_skip) return out;
  const auto dev = out.device();
  const auto dt = out.scalar_type();
  const int64_t C = out.size(2);
  auto jstd = joint_std.to(dev, dt), jmean = joint_mean.to(dev, dt);
  auto s = kin_std.to(dev, dt), mu = kin_mean.to(dev, dt);
  // n_c: the std, in channel c's z-units, of N(0, I) source noise in normalised
  // joints. Steps and root-relative joints are differences of two independent
  // draws (sqrt 2); root height and position are one draw.
  const double r2 = std::sqrt(2.0);
  std::vector<torch::Tensor> parts = {r2 * jstd[0].view({1}), r2 * jstd[2].view({1}), jstd[1].view({1}),
                                      jstd[0].view({1}), jstd[2].view({1}), (r2 * jstd).repeat({(C - 5) / 3})};
  auto n = torch::cat(parts) / s;  // [C]
  // The channels of x / t: K is linear in world joints, world(x / t) = x std / t + mean,
  // and K of the constant mean pose is [0, 0, mean_y, mean_x, mean_z, 0, ...].
  auto kmean = torch::zeros({C}, out.options());
  kmean.narrow(0, 2, 3).copy_(torch::stack({jmean[1], jmean[0], jmean[2]}));
  auto lin = kinematic_channels(x * jstd, mask.to(dev));  // K(x std) [B, T, C]
  auto tt = t.to(dev, dt).view({-1, 1, 1});
  auto denom = tt * tt + (1 - tt).pow(2) * n * n;  // t^2 (1 + sigma^2), [B, 1, C]
  // c_skip (K(x std)/t + K(mean) - mu)/s with c_skip = t^2 / denom: no division by t.
  auto skip = (tt * lin + tt * tt * (kmean - mu)) / (s * denom);
  auto c_out = (1 - tt) * n / denom.sqrt();
  return skip + c_out * out;
}

torch::Tensor FlowPriorNetImpl::decode_head(const torch::Tensor& out, const torch::Tensor& mask) const {
  auto ch = out * kin_std.to(out.device(), out.scalar_type()) + kin_mean.to(out.device(), out.scalar_type());
  if (kinematic_bones) {
    if (kinematic_rigid) ch = rigid_pose_block(ch, kin_bone_length);
    ch = map_pose_block(ch, kin_from_bones);
  }
  auto world = joints_from_kinematic(ch, mask.to(out.device()));
  return (world - joint_mean.to(out.device(), out.scalar_type())) / joint_std.to(out.device(), out.scalar_type());
}

torch::Tensor FlowPriorNetImpl::draw_noise(const torch::Tensor& mask, int64_t num_joints,
                                           c10::optional<at::Generator> gen) const {
  const int64_t B = mask.size(0), T = mask.size(1);
  auto opts = torch::TensorOptions();
  if (!kinematic_noise) return torch::randn({B, T, num_joints, 3}, gen, opts);
  const int64_t C = kinematic_channel_count(num_joints);
  auto eps = torch::randn({B, T, C}, gen, opts);
  auto m = mask.to(torch::kCPU, torch::kBool);
  auto scale = kin_std.to(torch::kCPU).view({1, 1, C}).expand({B, 1, C}).clone();
  // The root's offset is the mean of the position channels over valid frames: scaled
  // by sqrt(frames), it keeps the std of one root position.
  auto root_gain = m.sum(1).clamp_min(1).to(torch::kFloat32).sqrt();  // [B]
  scale.narrow(2, 3, 2).mul_(root_gain.view({B, 1, 1}));
  auto world = joints_from_kinematic(eps * scale, m);
  return world / joint_std.to(torch::kCPU);
}

torch::Tensor FlowPriorNetImpl::to_velocity(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                                            const torch::Tensor& mask) const {
  if (!clean_prediction) return out;
  auto gap = (1 - t.to(x.device(), x.scalar_type())).clamp_min(1e-6).view({-1, 1, 1, 1});
  return (to_clean(out, x, t, mask) - x) / gap;
}

torch::Tensor FlowPriorNetImpl::to_clean(const torch::Tensor& out, const torch::Tensor& x, const torch::Tensor& t,
                                         const torch::Tensor& mask) const {
  if (clean_prediction) return kinematic_head ? decode_head(head_channels(out, x, t, mask), mask) : out;
  return x + (1 - t.to(x.device(), x.scalar_type())).view({-1, 1, 1, 1}) * out;
}

torch::Tensor FlowPriorNetImpl::encode_text(const torch::Tensor& ids, const torch::Tensor& lengths) {
  torch::Tensor pooled;
  if (text_frozen) {
    // Frozen: no dropout and no graph through the pretrained encoder.
    torch::NoGradGuard ng;
    text->eval();
    pooled = text->forward(ids, lengths);
  } else {
    pooled = text->forward(ids, lengths);
  }
  return text_adapter ? text_adapter->forward(pooled) : pooled;
}

torch::Tensor FlowPriorNetImpl::null_condition(int64_t B) const { return null_text.unsqueeze(0).expand({B, -1}); }

// ---------------------------------------------------------------- trainer

namespace {
// model.kinematic_head.bones: the pose block's maps for the skeleton's parents.
void set_bone_maps(FlowPriorNetImpl& net, const std::vector<int>& parents) {
  net.kin_to_bones.copy_(relative_to_bones_matrix(parents));
  net.kin_from_bones.copy_(bones_to_relative_matrix(parents));
}
}  // namespace

FlowValidationInputs flow_validation_inputs(const MotionDataset& data, const std::vector<int64_t>& chunk, double t,
                                            at::Generator& gen, torch::Device device, const FlowPriorNetImpl* net) {
  FlowValidationInputs in;
  in.batch = data.batch(chunk, 0, 1, device);
  in.captions = data.first_captions(chunk);
  const int64_t B = chunk.size();
  in.x0 = (net ? net->draw_noise(in.batch.mask, in.batch.joints.size(2), gen)
               : torch::randn(in.batch.joints.sizes(), gen, torch::TensorOptions()))
              .to(device);
  in.t = torch::full({B}, t, torch::TensorOptions().device(device));
  in.drop = torch::zeros({B}, torch::TensorOptions().dtype(torch::kBool).device(device));
  return in;
}

namespace {

class FlowPriorTrainer : public Trainable {
 public:
  FlowPriorTrainer(const FlowPriorConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    const MotionSet& set = ctx.data->set();
    vocab_ = set.vocab.empty() ? TextVocab::build(set) : TextVocab(set.vocab, ctx.data->source());
    std::optional<TextClipRun> clip;
    if (c.text_encoder.enabled()) {
      // The pretrained encoder only knows its own word ids: the prior uses (and
      // saves) that run's vocabulary. Trained on demand first, without disturbing
      // this run's random stream.
      text_run_ = resolve_text_clip_run(c.text_encoder, &std::cerr);
      clip = read_text_clip_run(text_run_);
      TextVocab theirs(clip->vocab, text_run_ + "/outputs/vocab.txt");
      if (theirs.words() != vocab_.words())
        std::cerr << fmt::format("text encoder: the vocabulary of {} ({} words) differs from the one data '{}' "
                                 "gives ({} words); using the text encoder's\n",
                                 text_run_, theirs.size(), ctx.data->source(), vocab_.size());
      vocab_ = theirs;
    }
    net_ = FlowPriorNet(vocab_.size(), ctx.data->num_joints(), c);
    if (clip) {
      load_text_clip_encoder(*clip, *net_->text, c.text_encoder_options(vocab_.size()), "model.text_encoder");
      if (c.text_encoder.frozen)
        for (auto& p : net_->text->parameters()) p.set_requires_grad(false);
    }
    torch::NoGradGuard ng;
    net_->joint_mean.copy_(ctx.data->joint_mean());
    net_->joint_std.copy_(ctx.data->joint_std());
    if (net_->kinematic_head) {
      // The head's channel statistics over the training split's valid frames.
      torch::Tensor to_bones;
      if (net_->kinematic_bones) {
        set_bone_maps(*net_, set.skeleton.parents);
        to_bones = net_->kin_to_bones;
      }
      KinematicStats stats;
      for (const auto& chunk : chunked(ctx.data->split("train"), 256)) {
        MotionBatch b = ctx.data->batch(chunk, 0, 1, torch::kCPU);
        stats.add(ctx.data->denormalize(b.joints), b.mask, to_bones);
      }
      auto [mean, std] = stats.mean_std();
      net_->kin_mean.copy_(mean);
      net_->kin_std.copy_(std);
      if (net_->kinematic_bones) net_->kin_bone_length.copy_(stats.mean_bone_lengths());
    }
  }
  nn::Module& module() override { return *net_; }
  // A frozen text encoder is left out of the optimiser (and so of the EMA): its
  // weights in final.pt are the text_clip run's, bit for bit.
  std::vector<torch::Tensor> trainable_parameters() override {
    std::vector<torch::Tensor> out;
    for (auto& p : net_->parameters())
      if (p.requires_grad()) out.push_back(p);
    return out;
  }

  // Flow-matching loss, eq. (3), masked to valid frames; t, x0, crops, captions
  // and condition dropout all come from torch's generator (exact resume), drawn
  // for the whole batch and cut to the shard's rows (train/batch_shard.h).
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    MotionBatch b = ctx_.data->batch(idx, ctx_.window, 1, ctx_.device, ctx_.trim_padding, shard);
    const std::vector<std::string> caps = ctx_.data->drawn_captions(idx);
    const int64_t B = idx.size();
    auto sizes = b.joints.sizes().vec();
    sizes[0] = B;
    // The whole batch's noise (its mask shapes kinematic noise), cut to the shard's rows.
    auto x0 = shard.local(net_->draw_noise(b.whole_mask, sizes[2], c10::nullopt)).to(ctx_.device);
    auto t = shard.local(torch::rand({B})).to(ctx_.device);
    auto drop = shard.local(torch::rand({B}) < cfg_.cond_drop).to(ctx_.device);
    auto fl = flow_loss(b, shard.local(caps), x0, t, drop, cfg_.loss)[0];
    LossOutput out;
    out.loss = fl;
    out.parts = {{"fm", fl.detach()}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Validation flow loss at fixed t (first caption, whole clips, a constant-seeded
  // local generator for x0): comparable across runs and leaves torch's RNG alone.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    net_->eval();
    auto gen = at::make_generator<at::CPUGeneratorImpl>(20240611);
    // Velocity error (eq. (3)) and clean-endpoint error, weighted by valid frames: the
    // second compares velocity and clean networks on one scale.
    auto chunk_values = [&](double tv, const std::vector<int64_t>& chunk) {
      FlowValidationInputs in = flow_validation_inputs(*ctx_.data, chunk, tv, gen, ctx_.device, &*net_);
      const double w = in.batch.mask.sum().item<double>();
      auto both = flow_loss(in.batch, in.captions, in.x0, in.t, in.drop, "both");
      return ChunkValues{{both[0].item<double>(), both[1].item<double>()}, w};
    };
    const TimedValidation v = validate_at_times(cfg_.eval_t, ctx_.data->split("val"), 32, 2, chunk_values);
    std::map<std::string, double> out;
    for (size_t k = 0; k < cfg_.eval_t.size(); ++k) {
      out[fmt::format("val_fm_t{:.2f}", cfg_.eval_t[k])] = v.at_time[k][0];
      out[fmt::format("val_x1_t{:.2f}", cfg_.eval_t[k])] = v.at_time[k][1];
    }
    out["val_fm"] = v.mean[0];
    out["val_x1"] = v.mean[1];
    return out;
  }

  // Forward multiply-adds x2 on the valid frames of each clip (per token: qkv,
  // projection, SwiGLU and attention over the clip's own frames; embed and head),
  // the text encoder on max_words tokens, then x3 for forward + backward.
  double flops_per_step(const std::vector<int64_t>& idx) const override {
    auto o = cfg_.transformer_options(ctx_.data->num_joints());
    const double d = o.width, h = o.resolved_mlp_hidden(), io = o.num_joints * 3.0;
    const double dt = cfg_.text_width, ff = cfg_.text_ff, w = cfg_.max_words;
    double fwd = 0, text = 0;
    for (int64_t i : idx) {
      const double L = std::min<int64_t>(ctx_.data->length(i), ctx_.window > 0 ? ctx_.window : INT64_MAX);
      const double per_token_block = 8 * d * d + 6 * d * h + 4 * L * d;
      fwd += L * (o.depth * per_token_block + 4 * io * d * o.temporal_kernel);  // blocks, embed + head
      fwd += 2 * d * (o.depth * 6 * d + 2 * d) + 2 * 2 * d * d;           // AdaLN per clip, t_mlp
      // Text encoder: forward only when frozen (no backward through it).
      text += w * cfg_.text_layers * (8 * dt * dt + 4 * dt * ff + 4 * w * dt) + 2 * dt * dt;
    }
    return 3 * fwd + (net_->text_frozen ? 1 : 3) * text;
  }

  void save_artifacts(const fs::path& outputs) override {
    std::string words;
    for (auto& w : vocab_.words()) words += w + "\n";
    write_file_atomic(outputs / "vocab.txt", words);
    const MotionSet& set = ctx_.data->set();
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "fps" << YAML::Value << set.fps << YAML::Key << "t_max" << YAML::Value
      << set.t_max << YAML::Key << "num_joints" << YAML::Value << set.num_joints() << YAML::Key << "data"
      << YAML::Value << ctx_.data->source() << YAML::Key << "skeleton" << YAML::Value << YAML::Literal
      << skeleton_to_yaml(set.skeleton);
    // A key ending in _run: shipping this prior ships the text encoder run too.
    if (!text_run_.empty()) e << YAML::Key << "text_encoder_run" << YAML::Value << text_run_;
    e << YAML::EndMap;
    write_file_atomic(outputs / "prior_meta.yaml", std::string(e.c_str()) + "\n");
  }

 private:
  // Masked MSE between the predicted and the target velocity x1 - x0 on
  // x_t = t x1 + (1 - t) x0, eq. (2)-(3); with model.loss = clean, between the
  // predicted and the true clean endpoint x1.
  // `space` velocity or clean: {that error}; both: {velocity error, clean error}.
  std::vector<torch::Tensor> flow_loss(const MotionBatch& b, const std::vector<std::string>& caps,
                                       const torch::Tensor& x0, const torch::Tensor& t, const torch::Tensor& drop,
                                       const std::string& space) {
    const auto& x1 = b.joints;
    auto tb = t.view({-1, 1, 1, 1});
    auto xt = tb * x1 + (1 - tb) * x0;
    auto enc = encode_captions(vocab_, caps, cfg_.max_words);
    auto cond = net_->encode_text(enc.ids.to(ctx_.device), enc.lengths.to(ctx_.device));
    cond = torch::where(drop.unsqueeze(1), net_->null_condition(cond.size(0)), cond);
    auto out = net_->transformer->forward(xt, t, cond, b.mask).velocity;
    auto m = b.mask.view({b.mask.size(0), b.mask.size(1), 1, 1}).to(out.dtype());
    // Means over the whole batch's valid frames (b.whole_mask): a shard's share.
    auto wm = b.whole_mask.to(out.dtype());
    auto denom = wm.sum() * x1.size(2) * 3 + 1e-8;
    auto mse = [&](const torch::Tensor& err) { return (err.pow(2) * m).sum() / denom; };
    // A clean network's velocity error is its clean error over max(1 - t, eps):
    // exactly the velocity error where 1 - t >= eps, and no target that pushes
    // x1_hat past x1 where the floor bites.
    auto inv_gap = [&] { return 1 / (1 - t).clamp_min(cfg_.clean_eps).view({-1, 1, 1, 1}); };
    auto v_err = [&] {
      if (!net_->clean_prediction) return out - (x1 - x0);
      return (net_->to_clean(out, xt, t, b.mask) - x1) * inv_gap();
    };
    auto x_err = [&] { return net_->to_clean(out, xt, t, b.mask) - x1; };
    if (space == "both") return {mse(v_err()), mse(x_err())};
    auto err = space == "clean" ? x_err() : v_err();
    auto loss = mse(err);
    if (net_->kinematic_head && cfg_.kinematic_head.weight > 0) {
      // The head's channels against the truth's, each z-scored by its own training
      // statistics (the root's step and the root-relative joints get their own unit),
      // with the time weight of the chosen loss.
      auto dev = out.device();
      auto target = (net_->head_target_channels(ctx_.data->denormalize(x1), b.mask) - net_->kin_mean.to(dev)) /
                    net_->kin_std.to(dev);
      auto kerr = net_->head_channels(out, xt, t, b.mask) - target;
      if (space != "clean") kerr = kerr * inv_gap().view({-1, 1, 1});
      auto km = b.mask.unsqueeze(-1).to(out.dtype());
      loss = loss + cfg_.kinematic_head.weight * (kerr.pow(2) * km).sum() / (wm.sum() * out.size(2) + 1e-8);
    }
    if (cfg_.smooth_weight > 0 && err.size(1) > 1) {
      // Frame-to-frame differences of the error on pairs of valid frames: white
      // (jitter) error counts up to 4x, a slow offset hardly at all.
      const int64_t T = err.size(1);
      auto d = err.narrow(1, 1, T - 1) - err.narrow(1, 0, T - 1);
      auto pm = m.narrow(1, 1, T - 1) * m.narrow(1, 0, T - 1);
      auto wpm = wm.narrow(1, 1, T - 1) * wm.narrow(1, 0, T - 1);
      loss = loss + cfg_.smooth_weight * (d.pow(2) * pm).sum() / (wpm.sum() * x1.size(2) * 3 + 1e-8);
    }
    if (cfg_.geometry_loss.enabled()) {
      auto scale = net_->joint_std.to(err.device(), err.scalar_type());
      auto height = x1.select(3, 1) * scale[1] + net_->joint_mean.to(err.device(), err.scalar_type())[1];
      loss = loss + geometry_loss(cfg_.geometry_loss, ctx_.data->set().skeleton, err * scale, height, m, wm);
    }
    return {loss};
  }


  FlowPriorConfig cfg_;
  TrainContext ctx_;
  TextVocab vocab_{TextVocab::special_tokens()};
  FlowPriorNet net_{nullptr};
  std::string text_run_;  // the text_clip run of model.text_encoder ('' when off)
};

}  // namespace

MC_REGISTER_MODEL("flow_prior", FlowPriorConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<FlowPriorTrainer>(dynamic_cast<const FlowPriorConfig&>(c), ctx);
                  },
                  "ACMDM-style text-conditioned flow prior on absolute joints (AdaLN-Zero transformer, RoPE)");

// ---------------------------------------------------------------- the trained prior

FlowPrior FlowPrior::load(const std::string& run_dir, torch::Device device) {
  TrainedRun run = open_trained_run(
      run_dir, {"flow prior", {"flow_prior"}, {"vocab.txt", "prior_meta.yaml"},
                "train one with `motionctl train configs/prior/flow_tiny.yaml` or set prior.config to train it first"});
  FlowPrior p;
  p.run_dir_ = run_dir;
  p.device_ = device;
  p.cfg_ = run.model.as<FlowPriorConfig>();
  p.vocab_ = std::make_shared<TextVocab>(run.vocab_words(), run.output("vocab.txt").string());
  const std::string meta_path = run.output("prior_meta.yaml").string();
  run.read_meta("prior_meta.yaml", [&](const YAML::Node& meta) {
    p.fps_ = meta["fps"].as<double>();
    p.t_max_ = meta["t_max"].as<int>();
    p.data_path_ = meta["data"].as<std::string>("");
    p.skeleton_ = skeleton_from_yaml_text(meta["skeleton"].as<std::string>(), meta_path);
  });
  p.net_ = std::make_shared<FlowPriorNet>(p.vocab_->size(), p.skeleton_.num_joints(), p.cfg_);
  run.load_weights(**p.net_);
  (*p.net_)->to(device);
  (*p.net_)->eval();
  return p;
}

FlowPrior FlowPrior::untrained(const FlowPriorConfig& cfg, const Skeleton& skeleton, int t_max, uint64_t seed,
                               torch::Device device) {
  FlowPrior p;
  p.run_dir_ = "<untrained>";
  p.device_ = device;
  p.cfg_ = cfg;
  p.skeleton_ = skeleton;
  p.t_max_ = t_max;
  std::vector<std::string> words = TextVocab::special_tokens();
  for (const char* w : {"a", "person", "walks", "runs", "jumps", "forward", "waves", "left", "right", "hand"})
    words.push_back(w);
  p.vocab_ = std::make_shared<TextVocab>(words, "untrained prior");
  torch::manual_seed(seed);
  p.net_ = std::make_shared<FlowPriorNet>(p.vocab_->size(), skeleton.num_joints(), cfg);
  {
    torch::NoGradGuard ng;
    // AdaLN-Zero starts at the identity; small random weights everywhere give a
    // network that costs what a trained one costs and returns non-trivial velocities.
    for (auto& w : (*p.net_)->parameters()) w.normal_(0.0, 0.02);
    (*p.net_)->joint_mean.copy_(torch::tensor({0.0f, 0.9f, 0.0f}));
    (*p.net_)->joint_std.copy_(torch::tensor({0.5f, 0.6f, 0.8f}));
    if ((*p.net_)->kinematic_bones) {
      set_bone_maps(**p.net_, skeleton.parents);
      std::vector<float> lengths(skeleton.bone_lengths.begin() + 1, skeleton.bone_lengths.end());
      (*p.net_)->kin_bone_length.copy_(torch::tensor(lengths));
    }
  }
  (*p.net_)->to(device);
  (*p.net_)->eval();
  return p;
}

// ---------------------------------------------------------------- velocity

torch::Tensor FlowPrior::encode_texts(const std::vector<std::string>& captions) const {
  torch::NoGradGuard ng;
  auto enc = encode_captions(*vocab_, captions, cfg_.max_words);
  return (*net_)->encode_text(enc.ids.to(device_), enc.lengths.to(device_));
}

torch::Tensor FlowPrior::null_texts(int64_t B) const { return (*net_)->null_condition(B).detach(); }

torch::Tensor FlowPrior::raw_velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                      const torch::Tensor& mask) const {
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({x.size(0)});
  return (*net_)->to_velocity((*net_)->transformer->forward(x, tt, text, mask).velocity, x, tt, mask);
}

torch::Tensor FlowPrior::velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                  const torch::Tensor& mask, double cfg_scale) const {
  torch::NoGradGuard ng;
  const int64_t B = x.size(0);
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({B});
  torch::Tensor v;
  if (cfg_scale == 1.0) {
    // s = 1 is the conditional velocity: skip the null-text half of the batch (the
    // steps outside a CFG interval, FlowSamplerConfig::cfg_interval, cost half).
    v = raw_velocity(x, tt, text, mask);
  } else {
    auto v2 = raw_velocity(torch::cat({x, x}), torch::cat({tt, tt}), torch::cat({text, null_texts(B)}),
                           torch::cat({mask, mask}));
    auto vc = v2.narrow(0, 0, B), vu = v2.narrow(0, B, B);
    v = vu + cfg_scale * (vc - vu);
  }
  // Only valid frames matter; padded rows are garbage by design but must not poison the check.
  auto valid = mask.to(torch::kBool).view({B, -1, 1, 1}).expand_as(v);
  if (!torch::isfinite(v.masked_select(valid)).all().item<bool>())
    fail("the flow prior '{}' produced a non-finite velocity (at t = {}); the checkpoint is broken or diverged — "
         "retrain it (lower optim.lr) before sampling",
         run_dir_, tt[0].item<double>());
  return v;
}

torch::Tensor FlowPrior::draw_noise(const std::vector<int64_t>& lengths, int64_t T, at::Generator& gen) const {
  auto mask = torch::zeros({static_cast<int64_t>(lengths.size()), T}, torch::kBool);
  for (size_t i = 0; i < lengths.size(); ++i) mask[i].narrow(0, 0, std::min<int64_t>(lengths[i], T)).fill_(true);
  return (*net_)->draw_noise(mask, num_joints(), gen);
}

torch::Tensor FlowPrior::normalize(const torch::Tensor& world) const {
  auto& n = *net_;
  return (world - n->joint_mean.to(world.device())) / n->joint_std.to(world.device());
}

torch::Tensor FlowPrior::denormalize(const torch::Tensor& normed) const {
  auto& n = *net_;
  return normed * n->joint_std.to(normed.device()) + n->joint_mean.to(normed.device());
}

}  // namespace mc
