// ControlNet branch on the flow prior: the zero-initialised copy, its trainer
// (flow loss + L2 on controlled joints, base frozen), run loading and ACMDM's
// three-pass (text, control) guided velocity.
#include "models/flow_controlnet.h"

#include <ATen/CPUGeneratorImpl.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <iostream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "models/prior_source.h"
#include "models/trainable.h"
#include "models/trained_run.h"

namespace mc {
namespace nn = torch::nn;

// ---------------------------------------------------------------- signal

torch::Tensor control_signal(const torch::Tensor& target, const torch::Tensor& mask) {
  auto m = mask.to(target.dtype());
  return torch::cat({target * m, m}, -1);
}

torch::Tensor random_control_mask(const std::vector<int64_t>& lengths, int64_t T, int64_t J,
                                  const std::vector<int>& joints, int min_frames, at::Generator gen) {
  const int64_t B = lengths.size();
  c10::optional<at::Generator> g;
  if (gen.defined()) g = gen;
  auto mask = torch::zeros({B, T, J, 3});
  for (int64_t b = 0; b < B; ++b) {
    const int64_t L = std::max<int64_t>(1, std::min<int64_t>(lengths[b], T));
    const int64_t pick = torch::randint(0, static_cast<int64_t>(joints.size()), {1}, g).item<int64_t>();
    const int j = joints[pick];
    TORCH_CHECK(j >= 0 && j < J, "control joint ", j, " is outside the skeleton's ", J, " joints");
    const double lo = std::log(static_cast<double>(std::min<int64_t>(min_frames, L)));
    const double hi = std::log(static_cast<double>(L));
    const double u = torch::rand({1}, g).item<double>();
    const int64_t k = std::clamp<int64_t>(std::llround(std::exp(lo + u * (hi - lo))), 1, L);
    auto frames = torch::randperm(L, g, torch::TensorOptions().dtype(torch::kInt64)).narrow(0, 0, k);
    mask[b].select(1, j).index_fill_(0, frames, 1.0);
  }
  return mask;
}

// ---------------------------------------------------------------- branch

FlowControlBranchImpl::FlowControlBranchImpl(const FlowTransformerOptions& o, bool signal_norm, bool residual_head)
    : opt(o) {
  const int64_t d = o.width;
  signal_embed = register_module(
      "signal_embed", nn::Sequential(nn::Linear(o.num_joints * 6, d), nn::SiLU(), nn::Linear(d, d)));
  if (signal_norm) signal_gain = register_parameter("signal_gain", torch::ones({d}));
  if (residual_head) residual_out = register_module("residual_out", nn::Linear(d, o.num_joints * 3));
  signal_zero = register_module("signal_zero", nn::Linear(d, d));
  blocks = register_module("blocks", nn::ModuleList());
  zero_out = register_module("zero_out", nn::ModuleList());
  for (int64_t i = 0; i < o.depth; ++i) {
    blocks->push_back(FlowBlock(o));
    zero_out->push_back(nn::Linear(d, d));
  }
  // Zero-initialised connections: before training the branch adds exactly nothing.
  torch::NoGradGuard ng;
  for (auto& m : signal_embed->modules(false))
    if (auto* lin = m->as<nn::Linear>()) {
      nn::init::xavier_uniform_(lin->weight);
      nn::init::zeros_(lin->bias);
    }
  nn::init::zeros_(signal_zero->weight);
  nn::init::zeros_(signal_zero->bias);
  for (auto& z : *zero_out) {
    auto* lin = z->as<nn::Linear>();
    nn::init::zeros_(lin->weight);
    nn::init::zeros_(lin->bias);
  }
  if (residual_out) {
    nn::init::zeros_(residual_out->weight);
    nn::init::zeros_(residual_out->bias);
  }
}

void FlowControlBranchImpl::copy_blocks_from(FlowTransformerImpl& base) {
  TORCH_CHECK(static_cast<int64_t>(base.blocks->size()) == static_cast<int64_t>(blocks->size()),
              "base has ", base.blocks->size(), " blocks, the branch ", blocks->size());
  torch::NoGradGuard ng;
  for (size_t i = 0; i < blocks->size(); ++i) {
    auto src = base.blocks[i]->named_parameters(true);
    auto dst = blocks[i]->named_parameters(true);
    for (auto& kv : dst) kv.value().copy_(src[kv.key()]);
  }
}

FlowControlBranchImpl::Output FlowControlBranchImpl::forward(FlowTransformerImpl& base, const torch::Tensor& x,
                                                             const torch::Tensor& t, const torch::Tensor& cond,
                                                             const torch::Tensor& mask, const torch::Tensor& signal,
                                                             const torch::Tensor& control_on) {
  const int64_t B = x.size(0), T = x.size(1), J = x.size(2);
  TORCH_CHECK(J == opt.num_joints && x.size(3) == 3, "ControlNet expects [B, T, ", opt.num_joints, ", 3], got ",
              x.sizes());
  TORCH_CHECK(signal.size(0) == B && signal.size(1) == T && signal.size(2) == J && signal.size(3) == 6,
              "control signal must be [", B, ", ", T, ", ", J, ", 6], got ", signal.sizes());
  auto pos = torch::arange(T, torch::TensorOptions().dtype(torch::kFloat32).device(x.device()));
  auto c = base.conditioning(t.to(x.device()).expand({B}), cond);
  auto key_valid = mask.to(x.device(), torch::kBool);
  auto h = base.embed_tokens(x, key_valid);
  auto emb = signal_embed->forward(signal.to(x.dtype()).reshape({B, T, J * 6}));
  if (signal_gain.defined())  // ACMDM's RMSNorm (eps 1e-6) before the zero linear
    emb = emb * torch::rsqrt(emb.pow(2).mean(-1, true) + 1e-6) * signal_gain;
  auto ctrl = signal_zero(emb);
  if (control_on.defined()) {
    TORCH_CHECK(control_on.numel() == B, "control_on needs one entry per sample (", B, "), got ", control_on.numel());
    ctrl = ctrl * control_on.to(x.device(), x.dtype()).view({B, 1, 1});
  }
  auto hc = h + ctrl;
  for (size_t i = 0; i < blocks->size(); ++i) {
    h = base.blocks[i]->as<FlowBlockImpl>()->forward(h, c, key_valid, pos);
    hc = blocks[i]->as<FlowBlockImpl>()->forward(hc, c, key_valid, pos);
    h = h + zero_out[i]->as<nn::Linear>()->forward(hc);
  }
  Output out{base.output(h, c, key_valid), {}};
  if (residual_out) out.residual = residual_out(hc).view({B, T, J, 3});
  return out;
}

// ---------------------------------------------------------------- runtime

FlowControlNet FlowControlNet::around(FlowPrior base, bool signal_norm, bool residual_head) {
  FlowControlNet n;
  n.base_ = std::make_shared<FlowPrior>(std::move(base));
  auto& tr = *n.base_->net()->transformer;
  n.branch_ = std::make_shared<FlowControlBranch>(tr.opt, signal_norm, residual_head);
  (*n.branch_)->copy_blocks_from(tr);
  (*n.branch_)->to(n.base_->device());
  for (auto& p : n.base_->net()->parameters()) p.set_requires_grad(false);
  return n;
}

FlowControlNet FlowControlNet::load(const std::string& run_dir, torch::Device device) {
  TrainedRun run = open_trained_run(
      run_dir, {"ControlNet", {"flow_controlnet"}, {"controlnet_meta.yaml"},
                "train one with `motionctl train configs/prior/flow_controlnet_tiny.yaml`"});
  std::string base_run;
  bool signal_norm = false, residual_head = false;  // absent in runs trained before model.signal
  run.read_meta("controlnet_meta.yaml", [&](const YAML::Node& meta) {
    base_run = run.dependency(meta["base_run"].as<std::string>());
    if (meta["signal_norm"]) signal_norm = meta["signal_norm"].as<bool>();
    if (meta["residual_head"]) residual_head = meta["residual_head"].as<bool>();
  });
  FlowControlNet n = around(FlowPrior::load(base_run, device), signal_norm, residual_head);
  n.run_dir_ = run_dir;
  run.load_weights(**n.branch_, fmt::format("its base prior '{}'", base_run));
  (*n.branch_)->to(device);
  (*n.branch_)->eval();
  return n;
}

torch::Tensor FlowControlNet::raw_velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                           const torch::Tensor& mask, const torch::Tensor& signal,
                                           const torch::Tensor& control_on) const {
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({x.size(0)});
  const auto& net = *base_->net();
  // The branch adds to the base's blocks, so its output is in the base's
  // parametrisation (velocity or clean endpoint): convert like the base does. The
  // residual head adds on the clean estimate (clean base) or the velocity.
  auto o = branch_output(x, tt, text, mask, signal, control_on);
  if (!o.residual.defined()) return net.to_velocity(o.base_out, x, tt, mask);
  if (!net.clean_prediction) return o.base_out + o.residual;
  auto gap = (1 - tt.to(x.device(), x.scalar_type())).clamp_min(1e-6).view({-1, 1, 1, 1});  // as to_velocity
  return (net.to_clean(o.base_out, x, tt, mask) + o.residual - x) / gap;
}

torch::Tensor FlowControlNet::raw_clean(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                        const torch::Tensor& mask, const torch::Tensor& signal,
                                        const torch::Tensor& control_on) const {
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({x.size(0)});
  const auto& net = *base_->net();
  auto o = branch_output(x, tt, text, mask, signal, control_on);
  if (!o.residual.defined()) return net.to_clean(o.base_out, x, tt, mask);
  if (net.clean_prediction) return net.to_clean(o.base_out, x, tt, mask) + o.residual;
  return net.to_clean(o.base_out + o.residual, x, tt, mask);  // x + (1 - t) v on the summed velocity
}

FlowControlBranchImpl::Output FlowControlNet::branch_output(const torch::Tensor& x, const torch::Tensor& tt,
                                                            const torch::Tensor& text, const torch::Tensor& mask,
                                                            const torch::Tensor& signal,
                                                            const torch::Tensor& control_on) const {
  return (*branch_)->forward(*base_->net()->transformer, x, tt, text, mask, signal, control_on);
}

torch::Tensor FlowControlNet::velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                                       const torch::Tensor& mask, const torch::Tensor& signal, double text_cfg,
                                       double control_cfg) const {
  torch::NoGradGuard ng;
  const int64_t B = x.size(0);
  auto tt = t.to(x.device(), torch::kFloat32).reshape({-1}).expand({B});
  // The three passes in one batched call: (text, control), (null text, control), (text, no control).
  auto on = torch::cat({torch::ones({2 * B}), torch::zeros({B})}).to(x.device());
  auto v3 = raw_velocity(torch::cat({x, x, x}), torch::cat({tt, tt, tt}), torch::cat({text, base_->null_texts(B), text}),
                         torch::cat({mask, mask, mask}), torch::cat({signal, signal, signal}), on);
  auto v_tc = v3.narrow(0, 0, B), v_nc = v3.narrow(0, B, B), v_t0 = v3.narrow(0, 2 * B, B);
  auto v = v_tc + (text_cfg - 1.0) * (v_tc - v_nc) + (control_cfg - 1.0) * (v_tc - v_t0);
  auto valid = mask.to(torch::kBool).view({B, -1, 1, 1}).expand_as(v);
  if (!torch::isfinite(v.masked_select(valid)).all().item<bool>())
    fail("the ControlNet '{}' produced a non-finite velocity (at t = {}); retrain it (lower optim.lr)", run_dir_,
         tt[0].item<double>());
  return v;
}

ControlNetLosses controlnet_losses(const FlowControlNet& net, const torch::Tensor& x1, const torch::Tensor& x0,
                                   const torch::Tensor& t, const torch::Tensor& text, const torch::Tensor& mask,
                                   const torch::Tensor& cmask, const torch::Tensor& control_on,
                                   const std::string& weighting) {
  return controlnet_losses(net, x1, x0, t, text, mask, cmask, control_on, weighting, {}, {});
}

ControlNetLosses controlnet_losses(const FlowControlNet& net, const torch::Tensor& x1, const torch::Tensor& x0,
                                   const torch::Tensor& t, const torch::Tensor& text, const torch::Tensor& mask,
                                   const torch::Tensor& cmask, const torch::Tensor& control_on,
                                   const std::string& weighting, const torch::Tensor& fm_count,
                                   const torch::Tensor& ctrl_count) {
  const int64_t B = x1.size(0);
  auto valid = mask.view({B, mask.size(1), 1, 1}).to(x1.dtype());
  auto tb = t.view({-1, 1, 1, 1}).to(x1.dtype());
  auto xt = tb * x1 + (1 - tb) * x0;
  auto cm = cmask.to(x1.dtype()) * valid;
  if (weighting != "none" && weighting != "one_minus_t_sq")
    fail("model.control_loss_weighting '{}' is unknown; use none or one_minus_t_sq", weighting);
  // The velocity error v - (x1 - x0), as the base prior's own training loss forms it.
  // For a velocity network that is the output's error. For a clean-endpoint network
  // (v = (x1_hat - x_t) / (1 - t)) it is (x1_hat - x1) / (1 - t), whose weight is
  // unbounded near t = 1: the base prior floors 1 - t at its clean_eps there
  // (flow_prior.cpp), and so does the branch; without the floor single samples at
  // t ~ 1 carried losses of 10^2-10^3 and dominated the clipped gradient (measured
  // on flow_standard_kin: loss spikes of 62 and 459, dense control error 0.94 m
  // against the unconstrained prior's 1.15 m).
  //
  // ACMDM's clean estimate x0 + v uses the training noise: its error x0 + v - x1 is
  // the velocity error, with the same weight at every t. x_t + (1 - t) v (what a
  // sampler can form) has (1 - t) times that error, so with it the branch gets almost
  // no control supervision near t = 1 (the loss shrinks by (1 - t)^2).
  torch::Tensor v_err, ctrl_err;
  if (net.base().net()->clean_prediction) {
    auto x1_hat = net.raw_clean(xt, t, text, mask, control_signal(x1, cm), control_on);
    v_err = (x1_hat - x1) / (1 - tb).clamp_min(net.base().config().clean_eps);
    ctrl_err = weighting == "none" ? v_err : x1_hat - x1;
  } else {
    auto v = net.raw_velocity(xt, t, text, mask, control_signal(x1, cm), control_on);
    v_err = v - (x1 - x0);
    ctrl_err = weighting == "none" ? x0 + v - x1 : xt + (1 - tb) * v - x1;
  }
  ControlNetLosses out;
  out.fm = (v_err.pow(2) * valid).sum() / ((fm_count.defined() ? fm_count : valid.sum()) * x1.size(2) * 3 + 1e-8);
  out.ctrl_every = (ctrl_err.pow(2) * cm).sum() / (cm.sum() + 1e-8);
  if (control_on.defined()) cm = cm * control_on.to(x1.device(), x1.dtype()).view({B, 1, 1, 1});
  out.ctrl = (ctrl_err.pow(2) * cm).sum() / ((ctrl_count.defined() ? ctrl_count : cm.sum()) + 1e-8);
  return out;
}

// ---------------------------------------------------------------- trainer

namespace {

class FlowControlNetTrainer : public Trainable {
 public:
  FlowControlNetTrainer(const FlowControlNetConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {
    base_run_ = c.base.run();  // trained first by the job when named by its config
    net_ = FlowControlNet::around(FlowPrior::load(base_run_, ctx.device), c.signal.norm, c.signal.residual_head);
    const FlowPrior& base = net_.base();
    if (base.num_joints() != ctx.data->num_joints())
      fail("model.base '{}' has {} joints but data '{}' has {}; train the ControlNet on the base's skeleton",
           base_run_, base.num_joints(), ctx.data->source(), ctx.data->num_joints());
    for (int j : c.control_joints)
      if (j >= base.num_joints())
        fail("model.control_joints: joint {} is outside the skeleton's {} joints", j, base.num_joints());
  }
  nn::Module& module() override { return *net_.branch(); }

  // Every draw (crops, captions, x0, t, drops, control masks) is made for the whole
  // batch and cut to the shard's rows; the means divide by the whole batch's counts.
  LossOutput loss(const std::vector<int64_t>& idx, const BatchShard& shard) override {
    MotionBatch b = ctx_.data->batch(idx, ctx_.window, 1, ctx_.device, ctx_.trim_padding, shard);
    const std::vector<std::string> caps = ctx_.data->drawn_captions(idx);
    const int64_t B = idx.size(), T = b.joints.size(1), J = b.joints.size(2);
    auto x0 = shard.local(net_.base().net()->draw_noise(b.whole_mask, J, c10::nullopt)).to(ctx_.device);
    auto t = shard.local(torch::rand({B})).to(ctx_.device);
    auto drop = shard.local(torch::rand({B}) < cfg_.cond_drop).to(ctx_.device);
    auto control_on_all = (torch::rand({B}) >= cfg_.control_drop).to(ctx_.device, torch::kFloat32);
    auto wlen = b.whole_mask.sum(1).to(torch::kCPU).contiguous();
    std::vector<int64_t> whole_lengths(wlen.data_ptr<int64_t>(), wlen.data_ptr<int64_t>() + wlen.numel());
    auto cmask_all = random_control_mask(whole_lengths, T, J, cfg_.control_joints, cfg_.min_controlled_frames, {})
                         .to(ctx_.device);
    // The whole batch's counts: valid frames, and controlled entries of valid
    // frames of the samples whose control is on (as controlnet_losses counts them).
    auto wvalid = b.whole_mask.view({B, T, 1, 1}).to(torch::kFloat32);
    auto fm_count = wvalid.sum();
    auto ctrl_count = (cmask_all * wvalid * control_on_all.view({B, 1, 1, 1})).sum();
    auto parts = losses(b, shard.local(caps), x0, t, drop, shard.local(cmask_all), shard.local(control_on_all),
                        fm_count, ctrl_count);
    LossOutput out;
    out.loss = parts.fm + cfg_.control_loss_weight * parts.ctrl;
    out.parts = {{"fm", parts.fm.detach()}, {"ctrl", parts.ctrl.detach()}};
    return out;
  }

  // Validation flow and control losses at fixed t with noise and control masks from a
  // constant-seeded local generator (first caption, whole clips).
  std::map<std::string, double> evaluate() override {
    torch::NoGradGuard ng;
    net_.branch()->eval();
    auto gen = at::make_generator<at::CPUGeneratorImpl>(20240612);
    // Weighted by clips: each loss is already a mean over its chunk.
    // Each chunk runs twice on the same draws: with the control, and with the branch's
    // control off (ACMDM's "no control" pass). val_ctrl below val_ctrl_off is the branch
    // using its signal; equal, it has learned nothing from it (as AnchorKV's
    // zeroed-feature twin tells for the adapters).
    auto chunk_values = [&](double tv, const std::vector<int64_t>& chunk) {
      FlowValidationInputs in = flow_validation_inputs(*ctx_.data, chunk, tv, gen, ctx_.device, &*net_.base().net());
      auto cmask = control_mask(in.batch, gen);
      auto p = losses(in.batch, in.captions, in.x0, in.t, in.drop, cmask, {}, {}, {});
      auto off = torch::zeros({in.batch.mask.size(0)}, torch::TensorOptions().device(ctx_.device));
      auto p_off = losses(in.batch, in.captions, in.x0, in.t, in.drop, cmask, off, {}, {});
      return ChunkValues{{p.fm.item<double>(), p.ctrl.item<double>(), p_off.ctrl_every.item<double>()},
                         static_cast<double>(chunk.size())};
    };
    const TimedValidation v = validate_at_times(cfg_.eval_t, ctx_.data->split("val"), 32, 3, chunk_values);
    std::map<std::string, double> out;
    for (size_t k = 0; k < cfg_.eval_t.size(); ++k) {
      out[fmt::format("val_fm_t{:.2f}", cfg_.eval_t[k])] = v.at_time[k][0];
      out[fmt::format("val_ctrl_t{:.2f}", cfg_.eval_t[k])] = v.at_time[k][1];
      out[fmt::format("val_ctrl_off_t{:.2f}", cfg_.eval_t[k])] = v.at_time[k][2];
    }
    out["val_fm"] = v.mean[0];
    out["val_ctrl"] = v.mean[1];
    out["val_ctrl_off"] = v.mean[2];
    return out;
  }

  void save_artifacts(const fs::path& outputs) override {
    YAML::Emitter e;
    e << YAML::BeginMap << YAML::Key << "base_run" << YAML::Value << base_run_;
    if (cfg_.signal.norm) e << YAML::Key << "signal_norm" << YAML::Value << true;  // absent: off
    if (cfg_.signal.residual_head) e << YAML::Key << "residual_head" << YAML::Value << true;
    e << YAML::EndMap;
    write_file_atomic(outputs / "controlnet_meta.yaml", std::string(e.c_str()) + "\n");
  }

  const FlowControlNet& net() const { return net_; }

 private:
  torch::Tensor control_mask(const MotionBatch& b, at::Generator gen) {
    auto len = b.lengths.to(torch::kCPU).contiguous();
    std::vector<int64_t> lengths(len.data_ptr<int64_t>(), len.data_ptr<int64_t>() + len.numel());
    return random_control_mask(lengths, b.joints.size(1), b.joints.size(2), cfg_.control_joints,
                               cfg_.min_controlled_frames, gen)
        .to(ctx_.device);
  }

  // controlnet_losses on a data batch: targets use the base's normaliser (the
  // data's may differ), dropped texts become the base's null vector.
  ControlNetLosses losses(const MotionBatch& b, const std::vector<std::string>& caps, const torch::Tensor& x0,
                          const torch::Tensor& t, const torch::Tensor& drop, const torch::Tensor& cmask,
                          const torch::Tensor& control_on, const torch::Tensor& fm_count,
                          const torch::Tensor& ctrl_count) {
    const FlowPrior& base = net_.base();
    auto valid = b.mask.view({b.mask.size(0), b.mask.size(1), 1, 1}).to(torch::kFloat32);
    auto x1 = base.normalize(ctx_.data->denormalize(b.joints)) * valid;
    auto cond = base.encode_texts(caps);
    cond = torch::where(drop.unsqueeze(1), base.null_texts(cond.size(0)), cond);
    return controlnet_losses(net_, x1, x0, t, cond, b.mask, cmask, control_on, cfg_.control_loss_weighting, fm_count,
                             ctrl_count);
  }

  FlowControlNetConfig cfg_;
  TrainContext ctx_;
  std::string base_run_;
  FlowControlNet net_;
};

}  // namespace

const FlowControlNet* controlnet_of(const Trainable& t) {
  auto* c = dynamic_cast<const FlowControlNetTrainer*>(&t);
  return c ? &c->net() : nullptr;
}

MC_REGISTER_MODEL("flow_controlnet", FlowControlNetConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<FlowControlNetTrainer>(dynamic_cast<const FlowControlNetConfig&>(c), ctx);
                  },
                  "ACMDM+ControlNet: trainable zero-connected copy of a frozen flow prior's blocks fed joint targets");

}  // namespace mc
