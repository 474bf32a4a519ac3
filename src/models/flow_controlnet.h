// ACMDM+ControlNet baseline (model type `flow_controlnet`, reference-facts §2): a
// trainable copy of a frozen flow prior's blocks fed with joint targets, whose
// zero-initialised outputs are added after the matching base blocks.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "models/flow_prior.h"
#include "models/flow_transformer.h"
#include "models/prior_source.h"

namespace mc {

// How the control signal enters the copy (`model.signal`). Off by default and then
// absent from the dump, so ControlNets trained before it keep their names.
struct ControlSignalConfig : Config {
  // ACMDM's c_control_embedder ends in an RMSNorm before its zero linear: every
  // controlled frame's embedding has unit RMS however few of its entries are set.
  bool norm = false;
  // Ours: a zero-initialised Linear from the copy's last hidden state straight to a
  // per-frame residual on the normalised absolute joints of the clean estimate (on the
  // velocity for a velocity base). A kinematic-head base states the root as a running
  // sum of per-frame steps, so moving one frame's pelvis through the hidden stream needs
  // every earlier frame's step to change; this path reaches frame f's joints from frame f.
  bool residual_head = false;
  void visit(FieldVisitor& v) override {
    v("norm", norm,
      "RMS-normalise the signal embedding (learned gain) before its zero-initialised Linear, as ACMDM's "
      "control embedder");
    v("residual_head", residual_head,
      "add a zero-initialised per-frame residual on the absolute joints of the output, read from the copy's "
      "last hidden state (ours; ACMDM adds to the hidden stream only)");
  }
  bool omitted_from_dump() const override { return !norm && !residual_head; }
};

struct FlowControlNetConfig : Config {
  PriorSourceConfig base;  // the finished flow prior it controls (frozen)
  std::vector<int> control_joints = {0, 10, 11, 15, 20, 21};
  double control_loss_weight = 1.0;  // weight of the L2 on controlled entries of the clean estimate
  // none: ||x0 + v - x1||^2 (ACMDM); one_minus_t_sq: (1-t)^2 times it, which on a clean-endpoint base is the
  // clean error x1_hat - x1 itself (the standard ControlNets: the velocity error's 1/(1-t) weight left the
  // branch almost no supervision where the signal matters, docs/choices.md)
  std::string control_loss_weighting = "none";
  double cond_drop = 0.1;            // text dropout (the copy sees the null text at CFG's unconditional side)
  double control_drop = 0.1;         // control dropout: teaches the branch the "no control" pass of the CFG
  int min_controlled_frames = 1;     // controlled frames per sample: log-uniform in [this, clip length]
  std::vector<double> eval_t = {0.1, 0.5, 0.9};
  ControlSignalConfig signal;
  void visit(FieldVisitor& v) override {
    v("base", base, "the frozen base flow prior (run_dir, or its training config trained on demand)");
    v("control_joints", control_joints, "each training sample controls one joint drawn from this list",
      each(at_least(0)));
    v("control_loss_weight", control_loss_weight,
      "weight of the extra L2 loss on the controlled entries of the clean estimate", at_least(0.0));
    v("control_loss_weighting", control_loss_weighting,
      "clean estimate of the control loss: none = x0 + v with the training noise x0 (ACMDM; the error is "
      "v - (x1 - x0), equally weighted at every t), one_minus_t_sq = x_t + (1 - t) v (the error is (1 - t) times "
      "that: on a clean-endpoint base the clean error x1_hat - x1, every t alike; on a velocity base it vanishes "
      "near t = 1)",
      one_of({"none", "one_minus_t_sq"}));
    v("cond_drop", cond_drop, "probability of replacing the text by the base's null text", in_range(0.0, 1.0));
    v("control_drop", control_drop,
      "probability of switching a sample's control signal off (ACMDM: the CFG's 'text, no control' pass)",
      in_range(0.0, 1.0));
    v("min_controlled_frames", min_controlled_frames,
      "fewest controlled frames per sample; the count is log-uniform between this and the clip length",
      at_least(1));
    v("eval_t", eval_t, "flow times of the validation losses", each(in_range(0.0, 1.0)));
    v("signal", signal, "how the control signal enters the copy (off: ours, no normalisation)");
  }
  std::string validate() const override {
    if (control_joints.empty()) return "control_joints needs at least one joint";
    if (eval_t.empty()) return "eval_t needs at least one flow time";
    return "";
  }
};

// The control signal the branch reads, [B, T, J, 6]: normalised targets x mask
// (3 channels) and the per-entry mask itself (3 channels), so a target of 0 and
// "no target" differ. target [B, T, J, 3] normalised, mask [B, T, J, 3] in {0, 1}.
torch::Tensor control_signal(const torch::Tensor& target, const torch::Tensor& mask);

// Training-time control masks [B, T, J, 3] float: per sample one joint of `joints`,
// k frames without replacement among its valid ones, k log-uniform in
// [min_frames, length] (so single keyframes and whole trajectories are both
// common), all three axes.
torch::Tensor random_control_mask(const std::vector<int64_t>& lengths, int64_t T, int64_t J,
                                  const std::vector<int>& joints, int min_frames, at::Generator gen = {});

// The trainable side: copies of the base blocks, a zero-initialised Linear after
// each, and the signal embedding that enters the copy's input tokens through a
// zero-initialised Linear. The base itself is not a submodule (it stays frozen
// and is not saved with the branch).
struct FlowControlBranchImpl : torch::nn::Module {
  // signal_norm / residual_head: ControlSignalConfig (they add the `signal_gain` and
  // `residual_out` parameters).
  explicit FlowControlBranchImpl(const FlowTransformerOptions& o, bool signal_norm = false,
                                 bool residual_head = false);
  // Initialises the copied blocks from the base's (the zero linears stay zero).
  void copy_blocks_from(FlowTransformerImpl& base);
  // Velocity of base + branch: h_i = base_i(h_{i-1}) + zero_i(copy_i(hc_{i-1})),
  // hc_0 = embed(x) + on * signal_zero(signal_embed(signal)); the base's embedding,
  // conditioning and head are used as they are. Arguments as FlowTransformer::forward,
  // signal [B, T, J, 6] from control_signal(); control_on [B] (1 = control, 0 = the
  // branch runs without it, ACMDM's "no control"; undefined = all 1).
  struct Output {
    torch::Tensor base_out;  // the base's raw output (its parametrisation) with the branch's additions
    torch::Tensor residual;  // residual_head: [B, T, J, 3] on normalised absolute joints; else undefined
  };
  Output forward(FlowTransformerImpl& base, const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& cond,
                 const torch::Tensor& mask, const torch::Tensor& signal, const torch::Tensor& control_on = {});

  FlowTransformerOptions opt;
  torch::nn::Sequential signal_embed{nullptr};  // J*6 -> d -> SiLU -> d
  torch::nn::Linear signal_zero{nullptr};       // d -> d, zero-init
  torch::Tensor signal_gain;                    // [d] RMSNorm gain (signal_norm only)
  torch::nn::Linear residual_out{nullptr};      // d -> J*3, zero-init (residual_head only)
  torch::nn::ModuleList blocks{nullptr};        // copies of the base blocks
  torch::nn::ModuleList zero_out{nullptr};      // one d -> d zero-init Linear per block
};
TORCH_MODULE(FlowControlBranch);

// A finished `flow_controlnet` run with its base prior: config.yaml,
// checkpoints/final.pt (branch weights), outputs/controlnet_meta.yaml (base run).
class FlowControlNet {
 public:
  static FlowControlNet load(const std::string& run_dir, torch::Device device = torch::kCPU);
  // Builds base + freshly initialised branch (zero linears) around a loaded base.
  static FlowControlNet around(FlowPrior base, bool signal_norm = false, bool residual_head = false);

  // One network call of base + branch (text or null text), no guidance; control_on
  // as FlowControlBranchImpl::forward.
  torch::Tensor raw_velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                             const torch::Tensor& mask, const torch::Tensor& signal,
                             const torch::Tensor& control_on = {}) const;
  // The same call as the clean endpoint x1_hat (the base's to_clean): exact at every t
  // for a clean-endpoint base, x + (1 - t) v for a velocity one.
  torch::Tensor raw_clean(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                          const torch::Tensor& mask, const torch::Tensor& signal,
                          const torch::Tensor& control_on = {}) const;
  // ACMDM's three-pass guidance (models/ACMDM_ControlNet.py, forward_with_control):
  // passes (text, control), (null text, control) and (text, no control), all through
  // base + branch, combined as
  //   v = v_tc + (s_text - 1)(v_tc - v_nc) + (s_ctrl - 1)(v_tc - v_t0).
  // s_text = s_ctrl = 1 gives the plain controlled velocity. UserError when not finite.
  torch::Tensor velocity(const torch::Tensor& x, const torch::Tensor& t, const torch::Tensor& text,
                         const torch::Tensor& mask, const torch::Tensor& signal, double text_cfg,
                         double control_cfg) const;

  const FlowPrior& base() const { return *base_; }
  FlowControlBranch& branch() const { return *branch_; }
  const std::string& run_dir() const { return run_dir_; }

 private:
  // One base + branch call at per-sample times tt [B]: the base's raw output
  // (velocity or clean endpoint, in the base's parametrisation) and the residual head's.
  FlowControlBranchImpl::Output branch_output(const torch::Tensor& x, const torch::Tensor& tt,
                                              const torch::Tensor& text, const torch::Tensor& mask,
                                              const torch::Tensor& signal, const torch::Tensor& control_on) const;
  std::shared_ptr<FlowPrior> base_;
  std::shared_ptr<FlowControlBranch> branch_;
  std::string run_dir_;
};

// The two training losses of a ControlNet on one batch, masked means in the base's
// normalised units. x1 [B, T, J, 3] normalised data (zero past each length), x0 the
// noise, t [B], text [B, C] conditioning (dropout already applied), mask [B, T]
// valid frames, cmask [B, T, J, 3] controlled entries (the signal is x1 there),
// control_on [B] as FlowControlBranchImpl::forward (samples with the control off do
// not count in ctrl). weighting as FlowControlNetConfig::control_loss_weighting.
struct ControlNetLosses {
  torch::Tensor fm;    // flow matching: mean ||v - (x1 - x0)||^2 over valid entries
  torch::Tensor ctrl;  // mean ||x1_hat - x1||^2 over the controlled entries
  // The same mean over the controlled entries of every sample, its control on or off
  // (ctrl leaves out samples whose control is off): the validation's "signal off" error.
  torch::Tensor ctrl_every;
};
ControlNetLosses controlnet_losses(const FlowControlNet& net, const torch::Tensor& x1, const torch::Tensor& x0,
                                   const torch::Tensor& t, const torch::Tensor& text, const torch::Tensor& mask,
                                   const torch::Tensor& cmask, const torch::Tensor& control_on,
                                   const std::string& weighting);
// The same for a data-parallel shard's rows (train/batch_shard.h): each mean is
// divided by the whole batch's count of valid entries (`fm_count`) and of controlled
// entries (`ctrl_count`), so the shards' losses sum to the whole batch's.
ControlNetLosses controlnet_losses(const FlowControlNet& net, const torch::Tensor& x1, const torch::Tensor& x0,
                                   const torch::Tensor& t, const torch::Tensor& text, const torch::Tensor& mask,
                                   const torch::Tensor& cmask, const torch::Tensor& control_on,
                                   const std::string& weighting, const torch::Tensor& fm_count,
                                   const torch::Tensor& ctrl_count);

class Trainable;
// The ControlNet inside a `flow_controlnet` trainer (nullptr for other models): tests
// use it to check that training leaves the base untouched.
const FlowControlNet* controlnet_of(const Trainable& t);

}  // namespace mc
