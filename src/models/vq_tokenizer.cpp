// VQ motion tokenizer: EMA quantiser, tokenizer module, its trainer (model type
// `vq_tokenizer`, test-split reconstruction metrics) and the run-directory loader.
#include "models/vq_tokenizer.h"

#include <yaml-cpp/yaml.h>

#include <cmath>

#include "core/atomic_file.h"
#include "core/error.h"
#include "eval/metrics.h"
#include "train/trainer.h"

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

torch::Tensor EmaQuantizerImpl::ema_update(const torch::Tensor& z, const torch::Tensor& ids) {
  torch::NoGradGuard ng;
  const int64_t K = opt.codebook_size, N = z.size(0);
  if (N == 0) return torch::zeros({}, torch::kLong);
  const double d = opt.decay;
  auto zf = z.to(codebook.dtype());
  auto onehot = F::one_hot(ids, K).to(zf.dtype());  // [N, K]
  cluster_size.mul_(d).add_(onehot.sum(0), 1.0 - d);
  embed_sum.mul_(d).add_(torch::matmul(onehot.t(), zf), 1.0 - d);
  // Laplace smoothing keeps the division finite for codes with (almost) no mass
  // while preserving the total count.
  auto n = cluster_size.sum();
  auto smoothed = (cluster_size + opt.epsilon) / (n + K * opt.epsilon) * n;
  auto updated = embed_sum / smoothed.unsqueeze(1);
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

QuantizerOutput EmaQuantizerImpl::forward(const torch::Tensor& z, const torch::Tensor& valid) {
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
  if (o.conv.in_dim % 3 != 0) fail("vq tokenizer: input size {} is not J*3", o.conv.in_dim);
  encoder = register_module("encoder", ConvMotionEncoder(o.conv));
  quantizer = register_module("quantizer", EmaQuantizer(o.quant));
  decoder = register_module("decoder", ConvMotionDecoder(o.conv));
  joint_mean = register_buffer("joint_mean", torch::zeros({3}));
  joint_std = register_buffer("joint_std", torch::ones({3}));
}

namespace {

torch::Tensor masked_input(const torch::Tensor& x, const torch::Tensor& mask, int64_t stride) {
  if (x.dim() != 3) fail("vq tokenizer: expected motion [B, T, J*3], got {} dimensions", x.dim());
  if (x.size(1) % stride != 0)
    fail("vq tokenizer: {} frames is not a multiple of the token stride {}; pad the clip", x.size(1), stride);
  if (!mask.defined()) return x;
  return x * mask.unsqueeze(-1).to(x.dtype());
}

}  // namespace

VqOutput VqTokenizerImpl::forward(const torch::Tensor& x, const torch::Tensor& mask) {
  const int64_t s = stride();
  auto z = encoder(masked_input(x, mask, s));  // [B, L, D]
  // A token is valid when its first frame is: clips are padded at the end only.
  torch::Tensor token_valid;
  if (mask.defined()) token_valid = mask.slice(1, 0, mask.size(1), s);
  auto q = quantizer(z, token_valid);
  VqOutput out;
  out.recon = decoder(q.quantized);
  out.ids = q.ids;
  out.commit_loss = q.commit_loss;
  out.perplexity = q.perplexity;
  out.resets = q.resets;
  return out;
}

torch::Tensor VqTokenizerImpl::encode(const torch::Tensor& x, const torch::Tensor& mask) {
  return quantizer->assign(encoder(masked_input(x, mask, stride())));
}

torch::Tensor VqTokenizerImpl::decode(const torch::Tensor& ids) { return decoder(quantizer->lookup(ids)); }

torch::Tensor VqTokenizerImpl::decode_embeddings(const torch::Tensor& u) { return decoder(u); }

torch::Tensor VqTokenizerImpl::soft_decode(const torch::Tensor& probs) {
  if (probs.size(-1) != codebook_size())
    fail("soft_decode: last dimension {} is not the codebook size {}", probs.size(-1), codebook_size());
  return decoder(torch::matmul(probs, codebook().to(probs.dtype())));
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

VqTokenizerOptions vq_tokenizer_options(const VqTokenizerConfig& c, int num_joints) {
  VqTokenizerOptions o;
  o.conv.in_dim = num_joints * 3;
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

class VqTokenizerTrainer : public Trainable {
 public:
  VqTokenizerTrainer(const VqTokenizerConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    model_ = VqTokenizer(vq_tokenizer_options(c, ctx.data->num_joints()));
    {
      torch::NoGradGuard ng;
      model_->joint_mean.copy_(ctx.data->joint_mean());
      model_->joint_std.copy_(ctx.data->joint_std());
    }
    stride_ = static_cast<int>(model_->stride());
    if (ctx.window > 0 && ctx.window % stride_ != 0)
      fail("data.window = {} must be a multiple of {} (2^model.down_stages)", ctx.window, stride_);
    // The codebook is a buffer tracking the live encoder; the trainer's weight EMA
    // would swap in averaged encoder weights at the end that the codebook never saw.
    if (auto* job = dynamic_cast<const TrainJobConfig*>(ctx.job); job && job->optim.ema_decay > 0)
      fail("model vq_tokenizer needs optim.ema_decay = 0 (got {}): its EMA codebook follows the live encoder, "
           "so averaged final weights would not match it",
           job->optim.ema_decay);
  }
  torch::nn::Module& module() override { return *model_; }

  LossOutput loss(const std::vector<int64_t>& idx) override {
    MotionBatch b = ctx_.data->batch(idx, ctx_.window, stride_, ctx_.device);
    auto x = b.joints.flatten(2);  // [B, T, J*3]
    auto out = model_->forward(x, b.mask);
    auto m = b.mask.unsqueeze(-1).to(x.dtype());
    auto rec = masked_mean(elementwise(out.recon, x), m, x.size(2));
    auto mv = m.slice(1, 1) * m.slice(1, 0, -1);
    auto vel = masked_mean(elementwise(out.recon.diff(1, 1), x.diff(1, 1)), mv, x.size(2));
    LossOutput lo;
    lo.loss = rec + cfg_.velocity_weight * vel + out.commit_loss;
    lo.parts = {{"rec", rec.detach()},
                {"vel", vel.detach()},
                {"commit", out.commit_loss.detach()},
                {"perplexity", out.perplexity},
                {"resets", out.resets.to(torch::kFloat32)}};
    return lo;
  }

  // Whole test clips: reconstruction MPJPE (metres, plain and root-aligned), the
  // mean-training-pose baseline, code perplexity and codes unused on the split.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    const MotionSet& set = ctx_.data->set();
    const int J = set.num_joints();
    auto idx = ctx_.data->split("test");
    std::vector<std::vector<float>> recon_store, gt_store;
    std::vector<int> lengths;
    auto counts = torch::zeros({cfg_.codebook_size}, torch::kLong);
    for (size_t s = 0; s < idx.size(); s += 32) {
      std::vector<int64_t> chunk(idx.begin() + s, idx.begin() + std::min(idx.size(), s + 32));
      MotionBatch b = ctx_.data->batch(chunk, 0, stride_, ctx_.device);
      auto out = model_->forward(b.joints.flatten(2), b.mask);
      auto y = ctx_.data->denormalize(out.recon.view_as(b.joints)).to(torch::kCPU).contiguous();
      auto tv = b.mask.slice(1, 0, b.mask.size(1), stride_).to(torch::kCPU);
      counts += torch::bincount(out.ids.to(torch::kCPU).index({tv}), {}, cfg_.codebook_size);
      const int64_t T = y.size(1);
      for (size_t k = 0; k < chunk.size(); ++k) {
        const float* p = y[k].data_ptr<float>();
        recon_store.emplace_back(p, p + T * J * 3);
        const float* g = set.clip(chunk[k]);
        std::vector<float> gt(T * J * 3, 0.f);
        std::copy(g, g + std::min<int64_t>(T, set.t_max) * J * 3, gt.begin());
        gt_store.push_back(std::move(gt));
        lengths.push_back(set.lengths[chunk[k]]);
      }
    }
    std::vector<JointsView> rec_v, gt_v, mean_v;
    const int T = static_cast<int>(recon_store.front().size() / (J * 3));
    for (size_t i = 0; i < recon_store.size(); ++i) {
      rec_v.push_back(joints_view(recon_store[i], T, J, lengths[i], "reconstruction"));
      gt_v.push_back(joints_view(gt_store[i], T, J, lengths[i], "ground truth"));
    }
    std::vector<float> mean_pose = mean_training_pose(T);
    for (size_t i = 0; i < gt_v.size(); ++i) mean_v.push_back(joints_view(mean_pose, T, J, lengths[i], "mean pose"));

    auto p = counts.to(torch::kFloat64) / counts.sum().clamp_min(1).to(torch::kFloat64);
    double perplexity = torch::exp(-(p * torch::log(p + 1e-10)).sum()).item<double>();
    auto ema_dead = model_->quantizer->cluster_size < cfg_.reset_threshold;
    return {{"test_mpjpe_m", reconstruction_mpjpe(rec_v, gt_v)},
            {"test_mpjpe_root_aligned_m", reconstruction_mpjpe(rec_v, gt_v, true)},
            {"test_mean_pose_mpjpe_m", reconstruction_mpjpe(mean_v, gt_v)},
            {"test_perplexity", perplexity},
            {"test_dead_codes", static_cast<double>((counts == 0).sum().item<int64_t>())},
            {"ema_dead_codes", static_cast<double>(ema_dead.sum().item<int64_t>())}};
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
  torch::Tensor elementwise(const torch::Tensor& y, const torch::Tensor& x) const {
    if (cfg_.recon_loss == "mse") return (y - x).pow(2);
    return F::smooth_l1_loss(y, x, F::SmoothL1LossFuncOptions().reduction(torch::kNone));
  }
  static torch::Tensor masked_mean(const torch::Tensor& v, const torch::Tensor& m, int64_t dim) {
    return (v * m).sum() / (m.sum() * dim + 1e-8);
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
  fs::path dir(run_dir);
  fs::path final_pt = dir / "checkpoints" / "final.pt";
  fs::path meta_file = dir / "outputs" / kMetaFile;
  if (!fs::is_directory(dir)) fail("tokenizer run '{}' does not exist", run_dir);
  for (const fs::path& p : {dir / "config.yaml", final_pt, meta_file})
    if (!fs::exists(p))
      fail("tokenizer run '{}' is incomplete: '{}' is missing; finish it with `motionctl train "
           "configs/tokenizer/vq_tiny.yaml` (or point at a finished vq_tokenizer run)",
           run_dir, p.string());
  TrainJobConfig job;
  parse_config(compose_config((dir / "config.yaml").string()), job);
  if (job.model.type != "vq_tokenizer")
    fail("'{}' is a run of model type '{}', not a tokenizer (vq_tokenizer)", run_dir, job.model.type);
  LoadedVqTokenizer out;
  out.run_dir = run_dir;
  out.cfg = job.model.as<VqTokenizerConfig>();
  int num_joints = 0;
  try {
    YAML::Node meta = YAML::LoadFile(meta_file.string());
    num_joints = meta["num_joints"].as<int>();
    out.fps = meta["fps"].as<double>();
    out.skeleton = skeleton_from_yaml_text(meta["skeleton"].as<std::string>(), meta_file.string());
  } catch (const YAML::Exception& e) {
    fail("'{}' is corrupt: {}", meta_file.string(), e.what());
  }
  if (num_joints != out.skeleton.num_joints())
    fail("'{}' is corrupt: num_joints {} but its skeleton has {}", meta_file.string(), num_joints,
         out.skeleton.num_joints());
  out.model = VqTokenizer(vq_tokenizer_options(out.cfg, num_joints));
  try {
    torch::serialize::InputArchive ar;
    ar.load_from(final_pt.string());
    out.model->load(ar);
  } catch (const c10::Error& e) {
    fail("tokenizer checkpoint '{}' is unreadable or does not match its config.yaml ({})", final_pt.string(),
         std::string(e.what_without_backtrace()).substr(0, 200));
  } catch (const std::exception& e) {  // torch::jit::ErrorReport on a damaged file
    fail("tokenizer checkpoint '{}' is unreadable or does not match its config.yaml ({})", final_pt.string(),
         std::string(e.what()).substr(0, 200));
  }
  out.model->to(device);
  out.model->eval();
  return out;
}

}  // namespace mc
