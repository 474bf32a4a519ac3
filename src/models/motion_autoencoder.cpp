// A continuous motion autoencoder on normalised joints (the conv encoder/decoder
// of the tokenizer without quantisation): the foundation's proof that the
// training loop trains a real model; also a useful smoothness/compression probe.
#include "core/error.h"
#include "models/conv_motion.h"
#include "models/trainable.h"

namespace mc {
namespace {

struct MotionAutoencoderConfig : Config {
  int width = 128;
  int latent = 64;
  int down_stages = 2;
  int res_depth = 2;
  double velocity_weight = 0.5;
  void visit(FieldVisitor& v) override {
    v("width", width, "conv channels", at_least(8));
    v("latent", latent, "code dimension per downsampled frame", at_least(1));
    v("down_stages", down_stages, "stride-2 stages (2 = x4 in time)", in_range(0, 4));
    v("res_depth", res_depth, "dilated residual blocks per stage", in_range(0, 6));
    v("velocity_weight", velocity_weight, "weight of the frame-difference reconstruction loss", at_least(0.0));
  }
};

struct MotionAutoencoderImpl : torch::nn::Module {
  MotionAutoencoderImpl(const ConvMotionOptions& o) {
    encoder = register_module("encoder", ConvMotionEncoder(o));
    decoder = register_module("decoder", ConvMotionDecoder(o));
  }
  torch::Tensor forward(const torch::Tensor& x) { return decoder(encoder(x)); }  // [B, T, D]
  ConvMotionEncoder encoder{nullptr};
  ConvMotionDecoder decoder{nullptr};
};
TORCH_MODULE(MotionAutoencoder);

class MotionAutoencoderTrainer : public Trainable {
 public:
  MotionAutoencoderTrainer(const MotionAutoencoderConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    ConvMotionOptions o;
    o.in_dim = ctx.data->num_joints() * 3;
    o.width = c.width;
    o.latent = c.latent;
    o.down_stages = c.down_stages;
    o.res_depth = c.res_depth;
    model_ = MotionAutoencoder(o);
    stride_ = 1 << c.down_stages;
    if (ctx.window > 0 && ctx.window % stride_ != 0)
      fail("data.window = {} must be a multiple of {} (2^model.down_stages)", ctx.window, stride_);
  }
  torch::nn::Module& module() override { return *model_; }

  // Shard rows (train/batch_shard.h): crops drawn for the whole batch, means over
  // the whole batch's valid frames.
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    MotionBatch b = ctx_.data->batch(idx, ctx_.window, stride_, ctx_.device, false, shard);
    auto x = b.joints.flatten(2);  // [B, T, J*3]
    auto m = b.mask.unsqueeze(-1).to(x.dtype());
    auto wm = b.whole_mask.unsqueeze(-1).to(x.dtype());
    auto y = model_->forward(x);
    auto denom = wm.sum() * x.size(2) + 1e-8;
    auto rec = ((y - x).pow(2) * m).sum() / denom;
    auto mv = m.slice(1, 1) * m.slice(1, 0, -1);
    auto wmv = wm.slice(1, 1) * wm.slice(1, 0, -1);
    auto dv = (y.diff(1, 1) - x.diff(1, 1)).pow(2);
    auto vel = (dv * mv).sum() / (wmv.sum() * x.size(2) + 1e-8);
    LossOutput out;
    out.loss = rec + cfg_.velocity_weight * vel;
    out.parts = {{"rec", rec.detach()}, {"vel", vel.detach()}};
    return out;
  }
  bool shards_batches() const override { return true; }

  // Validation reconstruction MPJPE in metres, whole clips.
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    auto idx = ctx_.data->split("val");
    double err = 0, frames = 0;
    for (const auto& chunk : chunked(idx, 32)) {
      MotionBatch b = ctx_.data->batch(chunk, 0, stride_, ctx_.device);
      auto x = b.joints;
      auto y = model_->forward(x.flatten(2)).view_as(x);
      auto d = (ctx_.data->denormalize(y) - ctx_.data->denormalize(x)).norm(2, -1).mean(-1);  // [B, T]
      auto m = b.mask.to(d.dtype());
      err += (d * m).sum().item<double>();
      frames += m.sum().item<double>();
    }
    return {{"val_mpjpe_m", err / std::max(1.0, frames)}};
  }

 private:
  MotionAutoencoderConfig cfg_;
  TrainContext ctx_;
  MotionAutoencoder model_{nullptr};
  int stride_ = 4;
};

}  // namespace

MC_REGISTER_MODEL("motion_autoencoder", MotionAutoencoderConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<MotionAutoencoderTrainer>(
                        dynamic_cast<const MotionAutoencoderConfig&>(c), ctx);
                  },
                  "conv autoencoder on normalised joints (x4 temporal compression)");

}  // namespace mc
