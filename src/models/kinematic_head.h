// The flow prior's kinematic head (`model.kinematic_head`, ours, issue 13): the
// network states its clean endpoint x1_hat in kinematic channels per frame (root
// step, root height, root position, root-relative joints) that a fixed linear map
// turns back into absolute joints. The flow's state, noise, velocity and every
// sampler stay the papers' absolute joints (ProjFlow's linear observations and
// projection are untouched); only what the head writes and where the loss spends
// its precision change.
//
// Why: the prior is z-scored per axis over all joints, so on the standard fixture
// (roots travel up to 20 m, x/z std ~3 m) a 1 cm pose error is 0.003 normalised
// units, and the per-axis head must reach that on every frame independently: the
// measured priors shake common-mode (foot skating 40x ground truth, bone drift
// 30 mm). Here the root's frame-to-frame step (std ~3 cm) and the root-relative
// joints (std ~0.1-0.4 m) each have their own unit, and the root's trajectory is
// the running sum of its steps, so per-frame noise in the head cannot make it jitter.
#pragma once
#include <torch/torch.h>

#include "core/config.h"

namespace mc {

// The flow's source noise x0 with the head: off, the papers' N(0, I) in the
// normalised absolute joints; on, i.i.d. draws in the head's channels, each scaled
// by its training std (the root-position channels by sqrt(valid frames), so the
// root's offset keeps its std), decoded to joints by the same linear map. Still a
// Gaussian on absolute joints, but one whose pose and root-path directions carry
// noise on their own scale: pose and gait phase become visible at mid t instead of
// in the last few steps (a shared per-axis std of ~3 m buries a 0.3 m stride until
// t > 0.9). Its own section, absent from the dump when off, so runs with the head
// keep their names.
struct KinematicNoiseConfig : Config {
  bool enabled = false;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled,
      "draw the source noise i.i.d. in the head's channels at their std and decode it to joints "
      "(off: N(0, I) on the normalised joints, the papers')");
  }
  bool omitted_from_dump() const override { return !enabled; }
};

// EDM-style skip per channel (ours, `model.kinematic_head.skip.enabled`): x1_hat's
// channels = c_skip(t) * the channels of x_t / t + c_out(t) * the network's output,
// with c_skip = 1 / (1 + sigma_c^2), c_out = sigma_c / sqrt(1 + sigma_c^2),
// sigma_c = (1 - t) / t * n_c and n_c the std of the source noise in channel c in
// the channel's own z-units (Karras et al.'s preconditioning with unit data std, the
// channels being z-scored). A pure clean network must rewrite every detail of x_t at
// t -> 1 with its finite precision (the measured bone drift and sinking feet); with
// the skip, a channel whose noise has fallen below its data scale is carried over
// from x_t and the network writes only a correction. At t = 0 it is the clean head
// (c_skip = 0, c_out = 1). Measured worse on every health figure at the adopted
// prior's recipe (docs/choices.md): off everywhere. Its own section, absent from the
// dump when off.
struct KinematicSkipConfig : Config {
  bool enabled = false;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled,
      "x1_hat's channels = c_skip(t) x_t's channels + c_out(t) the network's output, per channel (ours; off: "
      "the network writes x1_hat)");
  }
  bool omitted_from_dump() const override { return !enabled; }
};

struct KinematicHeadConfig : Config {
  bool enabled = false;
  // Weight of the loss on the head's own channels (each z-scored by its training
  // statistics) beside the flow loss on the absolute joints it decodes to. Both are
  // positive-definite weightings of the same clean-endpoint error, so the minimiser
  // (the conditional expectation) is unchanged.
  double weight = 1.0;
  KinematicNoiseConfig noise;
  KinematicSkipConfig skip;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled,
      "the network writes x1_hat as root steps, root height, root position and root-relative joints "
      "(needs prediction: clean)");
    v("weight", weight, "weight of the z-scored loss on those channels beside the flow loss", in_range(0.0, 1e4));
    v("skip", skip, "EDM-style per-channel skip from x_t (off by default)");
    v("noise", noise, "source noise in the head's channels (off by default)");
  }
  bool omitted_from_dump() const override { return !enabled && weight == 1.0 && !noise.enabled && !skip.enabled; }
};

// Channels per frame for J joints: [step_x, step_z, root_y, root_x, root_z, (J-1)*3
// root-relative joints].
int64_t kinematic_channel_count(int64_t num_joints);

// World joints [B, T, J, 3] and valid [B, T] bool (valid frames a prefix) to
// channels [B, T, C] in metres. A frame's step is the root's horizontal move from
// the previous frame (0 on the first frame and wherever either frame is padding).
torch::Tensor kinematic_channels(const torch::Tensor& world, const torch::Tensor& valid);

// The inverse: channels [B, T, C] (metres) and valid [B, T] to world joints
// [B, T, J, 3]. The horizontal root is the running sum of the steps, shifted by the
// mean over valid frames of (root position channel - running sum): the steps give
// its shape, the position channels only its offset. Exact on kinematic_channels'
// output; finite (and meaningless) on padded frames.
torch::Tensor joints_from_kinematic(const torch::Tensor& channels, const torch::Tensor& valid);

// Per-channel mean and std (each [C], std floored at 1 mm) over the valid frames of
// world clips, accumulated chunk by chunk.
struct KinematicStats {
  torch::Tensor sum, sum_sq;  // [C] double
  torch::Tensor count;        // [C] double: frames (steps count frame pairs)
  void add(const torch::Tensor& world, const torch::Tensor& valid);
  std::pair<torch::Tensor, torch::Tensor> mean_std() const;  // float [C]
};

}  // namespace mc
