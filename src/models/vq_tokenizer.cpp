// VQ motion tokenizer: EMA quantiser, tokenizer module, its trainer (model type
// `vq_tokenizer`, test-split reconstruction metrics) and the run-directory loader.
#include "models/vq_tokenizer.h"

#include <yaml-cpp/yaml.h>

#include <cmath>

#include <random>

#include "control/anchors.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "data/normalizer.h"
#include "data/joints_view.h"
#include "models/trainable.h"
#include "models/trained_run.h"

namespace mc {
namespace F = torch::nn::functional;

// ---------------------------------------------------------------- quantiser

EmaQuantizerImpl::EmaQuantizerImpl(const EmaQuantizerOptions& o) : opt(o) {
  const int64_t K = o.codebook_size, D = o.code_dim;
  // The initial codebook hardly matters: with counts starting at 1, every code the
  // first batch leaves unused drops below the threshold and is re-drawn from it.
  codebook = register_buffer("codebook", torch::randn({K, D}));
  cluster_size = register_buffer("cluster_size", torch::ones({K}));
  embed_sum = register_buffer("embed_sum", codebook.clone());
}

torch::Tensor EmaQuantizerImpl::assign(const torch::Tensor& z) const {
  auto flat = z.reshape({-1, opt.code_dim});
  auto e = codebook.to(flat.dtype());
  // ||z||^2 is constant per row; argmin of ||e||^2 - 2 z.e picks the nearest code.
  auto d = e.pow(2).sum(1).unsqueeze(0) - 2.0 * torch::matmul(flat, e.t());
  auto sizes = z.sizes().vec();
  sizes.pop_back();
  return d.argmin(1).reshape(sizes);
}

torch::Tensor EmaQuantizerImpl::lookup(const torch::Tensor& ids) const {
  return F::embedding(ids, codebook);
}

torch::Tensor EmaQuantizerImpl::ema_means_(const torch::Tensor& counts, const torch::Tensor& sums) {
  const double d = opt.decay;
  cluster_size.mul_(d).add_(counts, 1.0 - d);
  embed_sum.mul_(d).add_(sums, 1.0 - d);
  // Laplace smoothing keeps the division finite for codes with (almost) no mass
  // while preserving the total count.
  auto n = cluster_size.sum();
  auto smoothed = (cluster_size + opt.epsilon) / (n + opt.codebook_size * opt.epsilon) * n;
  return embed_sum / smoothed.unsqueeze(1);
}

torch::Tensor EmaQuantizerImpl::ema_update(const torch::Tensor& z, const torch::Tensor& ids) {
  torch::NoGradGuard ng;
  const int64_t K = opt.codebook_size, N = z.size(0);
  if (N == 0) return torch::zeros({}, torch::kLong);
  auto zf = z.to(codebook.dtype());
  auto onehot = F::one_hot(ids, K).to(zf.dtype());  // [N, K]
  auto updated = ema_means_(onehot.sum(0), torch::matmul(onehot.t(), zf));
  if (opt.reset_threshold <= 0) {
    codebook.copy_(updated);
    return torch::zeros({}, torch::kLong);
  }
  // Dead codes restart from random vectors of this batch. Indices come from the
  // CPU generator (checkpointed by the trainer) whatever the device, so resume is exact.
  auto pick = torch::randint(0, N, {K}, torch::TensorOptions().dtype(torch::kLong)).to(zf.device());
  auto fresh = zf.index_select(0, pick);
  auto dead = cluster_size < opt.reset_threshold;  // [K]
  auto dead_col = dead.unsqueeze(1);
  codebook.copy_(torch::where(dead_col, fresh, updated));
  // A re-drawn code starts as a code that has just reached the threshold with
  // `fresh` as its mean, so it survives one more step and then needs assignments.
  cluster_size.copy_(torch::where(dead, torch::full_like(cluster_size, opt.reset_threshold), cluster_size));
  embed_sum.copy_(torch::where(dead_col, fresh * opt.reset_threshold, embed_sum));
  return dead.sum();
}

torch::Tensor EmaQuantizerImpl::ema_update_shard(const torch::Tensor& z, const torch::Tensor& counts,
                                                const torch::Tensor& sums, int64_t total, int64_t offset,
                                                const QuantizerSync& sync) {
  torch::NoGradGuard ng;
  const int64_t K = opt.codebook_size, D = opt.code_dim, N = z.size(0);
  if (total == 0) return torch::zeros({}, torch::kLong);
  auto zf = z.to(codebook.dtype());
  auto updated = ema_means_(counts, sums);
  if (opt.reset_threshold <= 0) {
    codebook.copy_(updated);
    return torch::zeros({}, torch::kLong);
  }
  // The picks one process makes over the whole batch (the same draws on every rank);
  // each rank supplies the picked vectors it holds, the sum assembles them all.
  auto pick = torch::randint(0, total, {K}, torch::TensorOptions().dtype(torch::kLong));
  auto fresh = torch::zeros({K, D}, zf.options());
  if (N > 0) {
    auto here = pick - offset;
    auto mine = (here >= 0).logical_and(here < N).to(zf.device());
    auto rows = zf.index_select(0, here.clamp(0, N - 1).to(zf.device()));
    fresh = torch::where(mine.unsqueeze(1), rows, fresh);
  }
  sync.sum(fresh);
  auto dead = cluster_size < opt.reset_threshold;
  auto dead_col = dead.unsqueeze(1);
  codebook.copy_(torch::where(dead_col, fresh, updated));
  cluster_size.copy_(torch::where(dead, torch::full_like(cluster_size, opt.reset_threshold), cluster_size));
  embed_sum.copy_(torch::where(dead_col, fresh * opt.reset_threshold, embed_sum));
  return dead.sum();
}

QuantizerOutput EmaQuantizerImpl::forward(const torch::Tensor& z, const torch::Tensor& valid,
                                          const QuantizerSync& sync) {
  const int64_t K = opt.codebook_size;
  auto ids = assign(z.detach());
  auto e = lookup(ids).to(z.dtype());
  QuantizerOutput out;
  out.ids = ids;
  out.quantized = z + (e - z).detach();  // straight-through estimator
  auto flat_z = z.reshape({-1, opt.code_dim});
  auto flat_e = e.reshape({-1, opt.code_dim});
  auto flat_ids = ids.reshape({-1});
  torch::Tensor sel_z = flat_z, sel_e = flat_e, sel_ids = flat_ids;
  if (valid.defined()) {
    auto v = valid.reshape({-1}).to(torch::kBool);
    sel_z = flat_z.index({v});
    sel_e = flat_e.index({v});
    sel_ids = flat_ids.index({v});
  }
  if (sync.active()) {
    // A shard: the whole batch's vector count (and this rank's offset in it), code
    // counts and vector sums, then the commitment mean, histogram and EMA step over
    // the whole batch (QuantizerSync).
    torch::Tensor counts, sums;
    int64_t total = 0, offset = 0;
    {
      torch::NoGradGuard ng;
      auto ns = torch::zeros({sync.world}, torch::kFloat64);
      ns[sync.rank] = static_cast<double>(sel_z.size(0));
      sync.sum(ns);
      total = static_cast<int64_t>(ns.sum().item<double>());
      offset = static_cast<int64_t>(ns.narrow(0, 0, sync.rank).sum().item<double>());
      auto zf = sel_z.detach().to(codebook.dtype());
      auto onehot = F::one_hot(sel_ids, K).to(zf.dtype());
      auto stats = torch::cat({onehot.sum(0), torch::matmul(onehot.t(), zf).reshape({-1})});
      sync.sum(stats);
      counts = stats.narrow(0, 0, K);
      sums = stats.narrow(0, K, K * opt.code_dim).view({K, opt.code_dim});
      auto p = counts.to(torch::kFloat64) / counts.sum().to(torch::kFloat64).clamp_min(1.0);
      out.perplexity = torch::exp(-(p * torch::log(p + 1e-10)).sum()).to(torch::kFloat32);
    }
    if (total > 0)
      out.commit_loss = opt.commitment * (sel_z - sel_e.detach()).pow(2).sum() / static_cast<double>(total * opt.code_dim);
    else
      out.commit_loss = (z * 0).sum();
    out.resets = is_training() ? ema_update_shard(sel_z.detach(), counts, sums, total, offset, sync)
                               : torch::zeros({}, torch::kLong);
    return out;
  }
  if (sel_z.size(0) > 0)
    out.commit_loss = opt.commitment * (sel_z - sel_e.detach()).pow(2).mean();
  else
    out.commit_loss = (z * 0).sum();  // keeps the graph; no valid vector in the batch
  {
    torch::NoGradGuard ng;
    auto counts = torch::bincount(sel_ids, {}, K).to(torch::kFloat64);
    auto p = counts / counts.sum().clamp_min(1.0);
    out.perplexity = torch::exp(-(p * torch::log(p + 1e-10)).sum()).to(torch::kFloat32);
  }
  out.resets = is_training() ? ema_update(sel_z.detach(), sel_ids) : torch::zeros({}, torch::kLong);
  return out;
}

// ---------------------------------------------------------------- tokenizer

VqTokenizerImpl::VqTokenizerImpl(const VqTokenizerOptions& o) : options(o) {
  if (o.conv.latent != o.quant.code_dim)
    fail("vq tokenizer: encoder latent size {} differs from code_dim {}", o.conv.latent, o.quant.code_dim);
  if (o.representation.invariant()) {
    if (o.num_joints < 2) fail("vq tokenizer: the invariant representation needs num_joints >= 2");
    if (o.skeleton.num_joints() != o.num_joints)
      fail("vq tokenizer: the invariant representation needs the skeleton ({} joints, options say {})",
           o.skeleton.num_joints(), o.num_joints);
    const int F = feature_dim(o.representation.layout, o.skeleton);
    if (o.conv.in_dim != F)
      fail("vq tokenizer: input size {} differs from the {} feature size {}", o.conv.in_dim, o.representation.layout, F);
  } else if (o.representation.type != "absolute_joints") {
    fail("vq tokenizer: unknown representation '{}' (absolute_joints or invariant)", o.representation.type);
  } else if (o.conv.in_dim % 3 != 0) {
    fail("vq tokenizer: input size {} is not J*3", o.conv.in_dim);
  }
  encoder = register_module("encoder", ConvMotionEncoder(o.conv));
  quantizer = register_module("quantizer", EmaQuantizer(o.quant));
  decoder = register_module("decoder", ConvMotionDecoder(o.conv));
  joint_mean = register_buffer("joint_mean", torch::zeros({3}));
  joint_std = register_buffer("joint_std", torch::ones({3}));
  if (o.representation.invariant()) {
    feature_mean = register_buffer("feature_mean", torch::zeros({o.conv.in_dim}));
    feature_std = register_buffer("feature_std", torch::ones({o.conv.in_dim}));
  }
}

namespace {

torch::Tensor masked_input(const torch::Tensor& x, const torch::Tensor& mask, int64_t stride) {
  if (x.dim() != 3) fail("vq tokenizer: expected motion [B, T, C], got {} dimensions", x.dim());
  if (x.size(1) % stride != 0)
    fail("vq tokenizer: {} frames is not a multiple of the token stride {}; pad the clip", x.size(1), stride);
  if (!mask.defined()) return x;
  return x * mask.unsqueeze(-1).to(x.dtype());
}

}  // namespace

torch::Tensor recover_world_from_invariant(const torch::Tensor& f, int64_t J) {
  using torch::indexing::Slice;
  auto heading = f.select(-1, 0).cumsum(-1);  // [..., T]
  auto c = heading.cos(), s = heading.sin();
  auto vx = f.select(-1, 1), vz = f.select(-1, 2);
  // facing frame of t -> world: R_y(theta) (the inverse of to_facing_frame).
  auto root_x = (c * vx + s * vz).cumsum(-1);
  auto root_z = (c * vz - s * vx).cumsum(-1);
  auto sizes = f.sizes().vec();
  sizes.pop_back();
  auto lsizes = sizes;
  lsizes.push_back(J - 1);
  lsizes.push_back(3);
  auto local = f.narrow(-1, 4, 3 * (J - 1)).reshape(lsizes);  // [..., T, J-1, 3]
  auto lx = local.select(-1, 0), ly = local.select(-1, 1), lz = local.select(-1, 2);
  auto cu = c.unsqueeze(-1), su = s.unsqueeze(-1);
  auto wx = cu * lx + su * lz + root_x.unsqueeze(-1);
  auto wz = cu * lz - su * lx + root_z.unsqueeze(-1);
  auto others = torch::stack({wx, ly, wz}, -1);                                 // [..., T, J-1, 3]
  auto root = torch::stack({root_x, f.select(-1, 3), root_z}, -1).unsqueeze(-2);  // [..., T, 1, 3]
  return torch::cat({root, others}, -2);
}

torch::Tensor VqTokenizerImpl::model_input(const torch::Tensor& x, const torch::Tensor& mask) const {
  const int64_t s = stride();
  if (!invariant()) return masked_input(x, mask, s);
  if (x.dim() != 3 || x.size(2) != num_joints() * 3)
    fail("vq tokenizer: expected normalised joints [B, T, {}], got {} dimensions of last size {}", num_joints() * 3,
         x.dim(), x.size(-1));
  if (x.size(1) % s != 0)
    fail("vq tokenizer: {} frames is not a multiple of the token stride {}; pad the clip", x.size(1), s);
  torch::NoGradGuard ng;
  const int64_t B = x.size(0), T = x.size(1), J = num_joints(), F = input_dim();
  auto world = denormalize(x.detach().view({B, T, J, 3})).to(torch::kCPU, torch::kFloat32).contiguous();
  auto lengths = mask.defined() ? mask.to(torch::kCPU).sum(1).to(torch::kLong) : torch::full({B}, T, torch::kLong);
  auto out = torch::zeros({B, T, F});
  auto mean = feature_mean.to(torch::kCPU), sd = feature_std.to(torch::kCPU);
  for (int64_t b = 0; b < B; ++b) {
    const int n = static_cast<int>(lengths[b].item<int64_t>());
    if (n < 1) continue;
    auto f = compute_features(options.representation.layout, world[b].data_ptr<float>(), n, options.skeleton,
                              options.representation.features);
    auto ft = torch::from_blob(f.data(), {n, F}, torch::kFloat32);
    out[b].narrow(0, 0, n).copy_((ft - mean) / sd);
  }
  return out.to(x.device(), x.scalar_type());
}

torch::Tensor VqTokenizerImpl::model_output_to_joints(const torch::Tensor& y) const {
  if (!invariant()) return y;
  auto f = y * feature_std.to(y.device(), y.scalar_type()) + feature_mean.to(y.device(), y.scalar_type());
  auto world = recover_world_from_invariant(f, num_joints());  // [B, T, J, 3]
  return normalize(world).flatten(-2);
}

VqOutput VqTokenizerImpl::forward(const torch::Tensor& x, const torch::Tensor& mask, const QuantizerSync& sync) {
  const int64_t s = stride();
  auto z = encoder(masked_input(x, mask, s));  // [B, L, D]
  // A token is valid when its first frame is: clips are padded at the end only.
  torch::Tensor token_valid;
  if (mask.defined()) token_valid = mask.slice(1, 0, mask.size(1), s);
  auto q = quantizer->forward(z, token_valid, sync);
  VqOutput out;
  out.recon = decoder(q.quantized);
  out.ids = q.ids;
  out.commit_loss = q.commit_loss;
  out.perplexity = q.perplexity;
  out.resets = q.resets;
  return out;
}

torch::Tensor VqTokenizerImpl::encode(const torch::Tensor& x, const torch::Tensor& mask) {
  return quantizer->assign(encoder(model_input(x, mask)));
}

torch::Tensor VqTokenizerImpl::decode(const torch::Tensor& ids) {
  return model_output_to_joints(decoder(quantizer->lookup(ids)));
}

torch::Tensor VqTokenizerImpl::decode_embeddings(const torch::Tensor& u) { return model_output_to_joints(decoder(u)); }

torch::Tensor VqTokenizerImpl::soft_decode(const torch::Tensor& probs) {
  if (probs.size(-1) != codebook_size())
    fail("soft_decode: last dimension {} is not the codebook size {}", probs.size(-1), codebook_size());
  return model_output_to_joints(decoder(torch::matmul(probs, codebook().to(probs.dtype()))));
}

torch::Tensor VqTokenizerImpl::normalized_codebook() const {
  return F::normalize(codebook(), F::NormalizeFuncOptions().p(2).dim(1).eps(1e-8));
}

torch::Tensor VqTokenizerImpl::token_distance_table() const {
  torch::NoGradGuard ng;
  auto n = normalized_codebook();
  auto cos = torch::matmul(n, n.t()).clamp(-1.0, 1.0);
  auto d = (2.0 - 2.0 * cos).pow(2);
  d.fill_diagonal_(0.0);  // exact zero: rounding leaves cos(e_i, e_i) a hair below 1
  return d;
}

torch::Tensor VqTokenizerImpl::normalize(const torch::Tensor& world) const {
  return (world - joint_mean.to(world.device())) / joint_std.to(world.device());
}

torch::Tensor VqTokenizerImpl::denormalize(const torch::Tensor& normed) const {
  return normed * joint_std.to(normed.device()) + joint_mean.to(normed.device());
}

VqTokenizerOptions vq_tokenizer_options(const VqTokenizerConfig& c, const Skeleton& skeleton) {
  VqTokenizerOptions o;
  const int num_joints = skeleton.num_joints();
  o.num_joints = num_joints;
  o.skeleton = skeleton;
  o.representation.type = c.representation.type;
  o.representation.layout = c.representation.layout;
  o.representation.features.facing_smooth_sigma = c.representation.facing_smooth_sigma;
  o.conv.in_dim = o.representation.invariant() ? feature_dim(c.representation.layout, skeleton) : num_joints * 3;
  o.conv.width = c.width;
  o.conv.latent = c.code_dim;
  o.conv.down_stages = c.down_stages;
  o.conv.res_depth = c.res_depth;
  o.conv.dilation_growth = c.dilation_growth;
  o.quant.codebook_size = c.codebook_size;
  o.quant.code_dim = c.code_dim;
  o.quant.decay = c.ema_decay;
  o.quant.commitment = c.commitment;
  o.quant.reset_threshold = c.reset_threshold;
  return o;
}

// ---------------------------------------------------------------- trainer

namespace {

const char* kMetaFile = "tokenizer_meta.yaml";

// The oracle's anchor counts: AnchorRoute's K in {2, 4, 8, 16, 32}, averaged per K then over K.
const int kOracleCounts[] = {2, 4, 8, 16, 32};

class VqTokenizerTrainer : public Trainable {
 public:
  VqTokenizerTrainer(const VqTokenizerConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    const MotionSet& set = ctx.data->set();
    model_ = VqTokenizer(vq_tokenizer_options(c, set.skeleton));
    {
      torch::NoGradGuard ng;
      model_->joint_mean.copy_(ctx.data->joint_mean());
      model_->joint_std.copy_(ctx.data->joint_std());
      if (model_->invariant()) {
        // The same train-split statistics as the dataset's own feature stats (two-pass,
        // population std floored at 1e-4), for this feature layout.
        NormOptions no;
        no.feature_layout = c.representation.layout;
        no.features = model_->options.representation.features;
        NormStats st = compute_norm_stats(set, no);
        model_->feature_mean.copy_(torch::tensor(st.feature_mean));
        model_->feature_std.copy_(torch::tensor(st.feature_std));
      }
    }
    stride_ = static_cast<int>(model_->stride());
    if (ctx.window > 0 && ctx.window % stride_ != 0)
      fail("data.window = {} must be a multiple of {} (2^model.down_stages)", ctx.window, stride_);
    // The codebook is a buffer tracking the live encoder; the trainer's weight EMA
    // would swap in averaged encoder weights at the end that the codebook never saw.
    if (ctx.ema_decay > 0)
      fail("model vq_tokenizer needs optim.ema_decay = 0 (got {}): its EMA codebook follows the live encoder, "
           "so averaged final weights would not match it",
           ctx.ema_decay);
  }
  torch::nn::Module& module() override { return *model_; }

  // A data-parallel shard (train/batch_shard.h) computes its rows: crops drawn for
  // the whole batch, means over the whole batch's valid frames, and the quantiser's
  // statistics summed over the ranks (QuantizerSync). Perplexity and resets are the
  // whole batch's on every rank: their shares are value / ranks.
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    torch::Tensor x, mask, whole_mask;
    if (model_->invariant()) {
      std::tie(x, mask, whole_mask) = feature_batch(idx, shard, ctx_.window);
    } else {
      MotionBatch b = ctx_.data->batch(idx, ctx_.window, stride_, ctx_.device, false, shard);
      x = b.joints.flatten(2);  // [B, T, J*3]
      mask = b.mask;
      whole_mask = b.whole_mask;
    }
    QuantizerSync sync;
    if (!shard.whole()) {
      sync.rank = shard.rank();
      sync.world = shard.world();
      sync.sum = [&shard](torch::Tensor& t) { shard.sum_(t); };
    }
    auto out = model_->forward(x, mask, sync);
    auto m = mask.unsqueeze(-1).to(x.dtype());
    auto wm = whole_mask.unsqueeze(-1).to(x.dtype());
    if (model_->invariant() && cfg_.representation.root_weight != 1.0) {
      // Per-channel weights (root channels root_weight, the rest 1), normalised to mean 1.
      auto w = torch::ones({x.size(2)}, x.options());
      w.narrow(0, 0, 4).fill_(cfg_.representation.root_weight);
      m = m * (w / w.mean());
      wm = wm * (w / w.mean());
    }
    auto rec = masked_mean(elementwise(out.recon, x), m, wm, x.size(2));
    auto mv = m.slice(1, 1) * mask.slice(1, 0, -1).unsqueeze(-1).to(x.dtype());
    auto wmv = wm.slice(1, 1) * whole_mask.slice(1, 0, -1).unsqueeze(-1).to(x.dtype());
    auto vel = masked_mean(elementwise(out.recon.diff(1, 1), x.diff(1, 1)), mv, wmv, x.size(2));
    LossOutput lo;
    lo.loss = rec + cfg_.velocity_weight * vel + out.commit_loss;
    lo.parts = {{"rec", rec.detach()},
                {"vel", vel.detach()},
                {"commit", out.commit_loss.detach()},
                {"perplexity", shard.replicated(out.perplexity)},
                {"resets", shard.replicated(out.resets.to(torch::kFloat32))}};
    const bool world_loss = model_->invariant() && cfg_.representation.world_weight > 0;
    if (world_loss || cfg_.geometry_loss.enabled()) {
      // World joints (metres) of prediction and target: for the invariant
      // representation recovered by integration over the window (from the frame
      // before it), so root drift inside the window counts.
      const int64_t J = model_->num_joints();
      torch::Tensor wy, wx;
      if (model_->invariant()) {
        auto fm = model_->feature_mean, fs = model_->feature_std;
        wy = recover_world_from_invariant(out.recon * fs + fm, J);
        wx = recover_world_from_invariant(x * fs + fm, J);
      } else {
        wy = model_->denormalize(out.recon.view({x.size(0), x.size(1), J, 3}));
        wx = model_->denormalize(x.view({x.size(0), x.size(1), J, 3}));
      }
      if (world_loss) {
        auto world = world_mpjpe(wy, wx, mask, whole_mask);
        lo.loss = lo.loss + cfg_.representation.world_weight * world;
        lo.parts.emplace_back("world", world.detach());
      }
      if (cfg_.geometry_loss.enabled()) {
        auto valid = mask.to(x.dtype()).view({x.size(0), x.size(1), 1, 1});
        auto geo = geometry_loss(cfg_.geometry_loss, ctx_.data->set().skeleton, wy - wx, wx.select(3, 1), valid,
                                 whole_mask.to(x.dtype()));
        lo.loss = lo.loss + geo;
        lo.parts.emplace_back("geometry", geo.detach());
      }
    }
    if (cfg_.clip_world_loss.enabled()) {
      auto cw = clip_world_loss(idx, shard);
      lo.loss = lo.loss + cfg_.clip_world_loss.weight * cw;
      lo.parts.emplace_back("clip_world", cw.detach());
    }
    return lo;
  }

  // model.clip_world_loss: the MPJPE (m) of the joints integrated over whole clips,
  // the first `clips` of the batch (the same ones on every data-parallel rank), padded
  // to the longest of them. The quantiser runs in eval mode for this pass: the
  // straight-through gradient still reaches the encoder, but the codebook's EMA
  // statistics and dead-code resets stay the window pass's alone (one step per batch).
  torch::Tensor clip_world_loss(const std::vector<int64_t>& idx, const BatchShard& shard) {
    const int64_t n = std::min<int64_t>(cfg_.clip_world_loss.clips, static_cast<int64_t>(idx.size()));
    const std::vector<int64_t> sub(idx.begin(), idx.begin() + n);
    auto [x, mask, whole_mask] = feature_batch(sub, shard, 0, true);
    const bool was_training = model_->quantizer->is_training();
    model_->quantizer->eval();
    VqOutput out;
    try {
      out = model_->forward(x, mask);
    } catch (...) {
      model_->quantizer->train(was_training);
      throw;
    }
    model_->quantizer->train(was_training);
    const int64_t J = model_->num_joints();
    auto fm = model_->feature_mean, fs = model_->feature_std;
    return world_mpjpe(recover_world_from_invariant(out.recon * fs + fm, J),
                       recover_world_from_invariant(x * fs + fm, J), mask, whole_mask);
  }

  // The mean per-joint Euclidean error in metres (MPJPE; its gradient does not fade
  // as the drift gets small, as a squared one would) of wy against wx [b, T, J, 3]
  // over this shard's valid frames `mask` [b, T], divided by the whole batch's
  // (`whole_mask`), so data-parallel shares add up.
  static torch::Tensor world_mpjpe(const torch::Tensor& wy, const torch::Tensor& wx, const torch::Tensor& mask,
                                   const torch::Tensor& whole_mask) {
    auto err = ((wy - wx).pow(2).sum(-1) + 1e-12).sqrt();  // [b, T, J]
    auto mw = mask.unsqueeze(-1).to(wy.dtype());
    return (err * mw).sum() / (whole_mask.to(wy.dtype()).sum() * wy.size(2) + 1e-8);
  }
  bool shards_batches() const override { return true; }

  // The final evaluation needs the test split (reconstructions); the oracle on val is
  // skipped when val is empty.
  std::vector<std::string> evaluation_splits() const override { return {"test"}; }

  // Whole clips through encode -> decode (world metres): test-split reconstruction
  // MPJPE (plain and root-aligned), the mean-training-pose baseline, code perplexity,
  // codes unused on the split; and the oracle control error on the val split.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    const MotionSet& set = ctx_.data->set();
    const int J = set.num_joints();
    Reconstructed test = reconstruct(ctx_.data->split("test"));
    std::vector<JointsView> rec_v, gt_v, mean_v;
    const int T = test.frames;
    for (size_t i = 0; i < test.recon.size(); ++i) {
      rec_v.push_back(joints_view(test.recon[i], T, J, test.lengths[i], "reconstruction"));
      gt_v.push_back(joints_view(test.gt[i], T, J, test.lengths[i], "ground truth"));
    }
    std::vector<float> mean_pose = mean_training_pose(T);
    for (size_t i = 0; i < gt_v.size(); ++i)
      mean_v.push_back(joints_view(mean_pose, T, J, test.lengths[i], "mean pose"));

    auto p = test.counts.to(torch::kFloat64) / test.counts.sum().clamp_min(1).to(torch::kFloat64);
    double perplexity = torch::exp(-(p * torch::log(p + 1e-10)).sum()).item<double>();
    auto ema_dead = model_->quantizer->cluster_size < cfg_.reset_threshold;
    std::map<std::string, double> out = {
        {"test_mpjpe_m", reconstruction_mpjpe(rec_v, gt_v)},
        {"test_mpjpe_root_aligned_m", reconstruction_mpjpe(rec_v, gt_v, true)},
        {"test_mean_pose_mpjpe_m", reconstruction_mpjpe(mean_v, gt_v)},
        {"test_perplexity", perplexity},
        {"test_dead_codes", static_cast<double>((test.counts == 0).sum().item<int64_t>())},
        {"ema_dead_codes", static_cast<double>(ema_dead.sum().item<int64_t>())}};
    for (auto& [k, v] : oracle_control_error()) out[k] = v;
    return out;
  }

  void save_artifacts(const fs::path& outputs) override {
    const MotionSet& set = ctx_.data->set();
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "num_joints" << YAML::Value << set.num_joints() << YAML::Key << "fps"
      << YAML::Value << set.fps << YAML::Key << "stride" << YAML::Value << stride_ << YAML::Key << "data"
      << YAML::Value << ctx_.data->source() << YAML::Key << "skeleton" << YAML::Value << YAML::Literal
      << skeleton_to_yaml(set.skeleton) << YAML::EndMap;
    write_file_atomic(outputs / kMetaFile, std::string(e.c_str()) + "\n");
  }

 private:
  struct Reconstructed {
    int frames = 0;                              // padded length (a multiple of the stride)
    std::vector<std::vector<float>> recon, gt;   // [T, J, 3] world metres each
    std::vector<int> lengths;
    torch::Tensor counts;                        // [K] code histogram over the valid tokens
  };

  // Whole clips of `idx`: tokens of the ground truth decoded back to world joints.
  Reconstructed reconstruct(const std::vector<int64_t>& idx) {
    const MotionSet& set = ctx_.data->set();
    const int J = set.num_joints();
    Reconstructed r;
    r.counts = torch::zeros({cfg_.codebook_size}, torch::kLong);
    for (const auto& chunk : chunked(idx, 32)) {
      MotionBatch b = ctx_.data->batch(chunk, 0, stride_, ctx_.device);
      auto ids = model_->encode(b.joints.flatten(2), b.mask);
      auto y = ctx_.data->denormalize(model_->decode(ids).view_as(b.joints)).to(torch::kCPU).contiguous();
      auto tv = b.mask.slice(1, 0, b.mask.size(1), stride_).to(torch::kCPU);
      r.counts += torch::bincount(ids.to(torch::kCPU).index({tv}), {}, cfg_.codebook_size);
      const int64_t T = y.size(1);
      r.frames = static_cast<int>(T);
      for (size_t k = 0; k < chunk.size(); ++k) {
        const float* p = y[k].data_ptr<float>();
        r.recon.emplace_back(p, p + T * J * 3);
        const float* g = set.clip(chunk[k]);
        std::vector<float> gt(T * J * 3, 0.f);
        std::copy(g, g + std::min<int64_t>(T, set.t_max) * J * 3, gt.begin());
        r.gt.push_back(std::move(gt));
        r.lengths.push_back(set.lengths[chunk[k]]);
      }
    }
    return r;
  }

  // The oracle control error (issue 15): ground-truth tokens -> decoder -> AnchorRoute
  // anchor error (mean Euclidean, xz for planar root), per family, on the val split;
  // per clip one anchor set per K in {2, 4, 8, 16, 32} (draw_anchor_set, seeded by
  // (clip, K, family)), averaged per K then over K as the AnchorRoute tables are.
  std::map<std::string, double> oracle_control_error() {
    const MotionSet& set = ctx_.data->set();
    const int J = set.num_joints();
    std::vector<int64_t> idx;
    for (size_t i : set.indices_of_split("val")) idx.push_back(static_cast<int64_t>(i));
    if (idx.empty()) return {};
    Reconstructed r = reconstruct(idx);
    std::map<std::string, double> out;
    double all = 0;
    int families = 0;
    for (AnchorFamily fam : {AnchorFamily::root_3d, AnchorFamily::planar_root, AnchorFamily::body_point}) {
      double sum_k = 0;
      int n_k = 0;
      for (int K : kOracleCounts) {
        double sum = 0;
        size_t n = 0;
        for (size_t i = 0; i < idx.size(); ++i) {
          if (r.lengths[i] < K) continue;
          std::seed_seq seq{20250115u, static_cast<unsigned>(idx[i]), static_cast<unsigned>(K),
                            static_cast<unsigned>(fam)};
          std::mt19937_64 rng(seq);
          AnchorSet a = draw_anchor_set(fam, K, r.gt[i].data(), r.lengths[i], J, rng);
          for (double e : anchor_errors(a, r.recon[i].data(), J)) sum += e, ++n;
        }
        if (n == 0) continue;
        sum_k += sum / n;
        ++n_k;
      }
      if (n_k == 0) continue;
      out["val_oracle_" + family_name(fam) + "_m"] = sum_k / n_k;
      all += sum_k / n_k;
      ++families;
    }
    if (families > 0) out["val_oracle_control_error_m"] = all / families;
    return out;
  }

  // Invariant training batch: each clip's features over the whole clip (so a window's
  // first row holds the real step from the frame before it), normalised, cropped to
  // `window` frames like MotionDataset::batch (same random draws, every clip's; window
  // 0 = whole clips, padded to t_max, or with `fit` to the longest of `idx`, with no
  // draw), padded to a multiple of the stride: the shard's rows, their mask and the
  // whole batch's mask.
  std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> feature_batch(const std::vector<int64_t>& idx,
                                                                        const BatchShard& shard, int64_t window,
                                                                        bool fit = false) {
    const MotionSet& set = ctx_.data->set();
    const int64_t Bw = idx.size(), F = model_->input_dim();
    int64_t T = window > 0 ? window : set.t_max;
    if (window <= 0 && fit) {
      T = 1;
      for (int64_t i : idx) T = std::max<int64_t>(T, set.lengths[i]);
    }
    if (stride_ > 1) T = (T + stride_ - 1) / stride_ * stride_;
    std::vector<int64_t> starts(Bw, 0), takes(Bw);
    auto whole_mask = torch::zeros({Bw, T}, torch::kBool);
    for (int64_t b = 0; b < Bw; ++b) {
      const int64_t len = set.lengths[idx[b]];
      takes[b] = std::min(len, T);
      if (window > 0 && len > T) starts[b] = torch::randint(0, len - T + 1, {1}).item<int64_t>();
      whole_mask[b].narrow(0, 0, takes[b]).fill_(true);
    }
    const BatchRows rows = shard.rows(Bw);
    auto x = torch::zeros({rows.size(), T, F});
    auto mean = model_->feature_mean.to(torch::kCPU), sd = model_->feature_std.to(torch::kCPU);
    for (int64_t b = 0; b < rows.size(); ++b) {
      const int64_t w = rows.begin + b, len = set.lengths[idx[w]];
      auto f = compute_features(cfg_.representation.layout, set.clip(idx[w]), static_cast<int>(len), set.skeleton,
                                model_->options.representation.features);
      auto ft = torch::from_blob(f.data(), {len, F}, torch::kFloat32).narrow(0, starts[w], takes[w]);
      x[b].narrow(0, 0, takes[w]).copy_((ft - mean) / sd);
    }
    auto mask = shard.local(whole_mask).clone();
    return {x.to(ctx_.device), mask.to(ctx_.device), whole_mask.to(ctx_.device)};
  }

  torch::Tensor elementwise(const torch::Tensor& y, const torch::Tensor& x) const {
    if (cfg_.recon_loss == "mse") return (y - x).pow(2);
    return F::smooth_l1_loss(y, x, F::SmoothL1LossFuncOptions().reduction(torch::kNone));
  }
  // m [B, T, 1] (a frame mask: the mean over frames and `dim` channels) or [B, T, C]
  // (per-channel weights times the mask: the weighted mean); the denominator from
  // the whole batch's `whole` (m itself in one process).
  static torch::Tensor masked_mean(const torch::Tensor& v, const torch::Tensor& m, const torch::Tensor& whole,
                                   int64_t dim) {
    if (m.size(-1) > 1) return (v * m).sum() / (whole.sum() + 1e-8);
    return (v * m).sum() / (whole.sum() * dim + 1e-8);
  }
  // Per-joint mean world position over the valid training frames, repeated over T.
  std::vector<float> mean_training_pose(int T) const {
    const MotionSet& set = ctx_.data->set();
    const int J = set.num_joints();
    std::vector<double> acc(J * 3, 0.0);
    double frames = 0;
    for (int64_t i : ctx_.data->split("train")) {
      for (int t = 0; t < set.lengths[i]; ++t)
        for (int j = 0; j < J; ++j)
          for (int c = 0; c < 3; ++c) acc[j * 3 + c] += set.at(i, t, j)[c];
      frames += set.lengths[i];
    }
    std::vector<float> out(static_cast<size_t>(T) * J * 3);
    for (int t = 0; t < T; ++t)
      for (int k = 0; k < J * 3; ++k) out[t * J * 3 + k] = static_cast<float>(acc[k] / std::max(1.0, frames));
    return out;
  }

  VqTokenizerConfig cfg_;
  TrainContext ctx_;
  VqTokenizer model_{nullptr};
  int stride_ = 4;
};

}  // namespace

MC_REGISTER_MODEL("vq_tokenizer", VqTokenizerConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<VqTokenizerTrainer>(dynamic_cast<const VqTokenizerConfig&>(c), ctx);
                  },
                  "VQ motion tokenizer: conv encoder, EMA codebook with dead-code reset, conv decoder (x4)");

// ---------------------------------------------------------------- loading

void LoadedVqTokenizer::check_compatible(const MotionSet& m, const std::string& source) const {
  if (m.num_joints() != skeleton.num_joints())
    fail("{}: {} joints per frame, but the tokenizer {} was trained on {} ({})", source, m.num_joints(), run_dir,
         skeleton.num_joints(), skeleton.name);
  if (!(m.skeleton == skeleton))
    fail("{}: skeleton '{}' differs from the tokenizer's '{}' ({}); use motions of the skeleton it was trained on",
         source, m.skeleton.name, skeleton.name, run_dir);
  if (std::abs(m.fps - fps) > 1e-9)
    fail("{}: fps {} differs from the tokenizer's {} ({}); resample the motions", source, m.fps, fps, run_dir);
}

LoadedVqTokenizer load_vq_tokenizer(const std::string& run_dir, torch::Device device) {
  TrainedRun run = open_trained_run(run_dir, {"tokenizer", {"vq_tokenizer"}, {kMetaFile},
                                              "train one with `motionctl train configs/tokenizer/vq_tiny.yaml`"});
  LoadedVqTokenizer out;
  out.run_dir = run_dir;
  out.cfg = run.model.as<VqTokenizerConfig>();
  int num_joints = 0;
  const std::string meta_file = run.output(kMetaFile).string();
  run.read_meta(kMetaFile, [&](const YAML::Node& meta) {
    num_joints = meta["num_joints"].as<int>();
    out.fps = meta["fps"].as<double>();
    out.skeleton = skeleton_from_yaml_text(meta["skeleton"].as<std::string>(), meta_file);
  });
  if (num_joints != out.skeleton.num_joints())
    fail("'{}' is corrupt: num_joints {} but its skeleton has {}", meta_file, num_joints, out.skeleton.num_joints());
  out.model = VqTokenizer(vq_tokenizer_options(out.cfg, out.skeleton));
  run.load_weights(*out.model);
  out.model->to(device);
  out.model->eval();
  return out;
}

}  // namespace mc
