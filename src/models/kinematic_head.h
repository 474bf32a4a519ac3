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

// The head's pose block as bone vectors (ours, `model.kinematic_head.bones`, issue
// 13): the (J-1)*3 channels after the root's five are each joint's offset from its
// parent instead of from the root, and the root-relative joints are their running
// sum down the skeleton's chains (a fixed linear map, `bones_to_relative_matrix`).
// Why: the adopted head writes every joint's offset from the root anew on every
// frame, so a bone's length is the difference of two independently erring channels
// (part of the measured 9.5 mm bone-length std; the rest is CFG's, docs/choices.md);
// here each bone's length is what one channel triple says. `rigid` then writes only
// the bone's direction: the vector is normalised and scaled by the bone's mean
// length over the training split, so the decoded skeleton has the data's bone
// lengths on every frame (a parametrisation of the network's output, like a
// rotation-based head with forward kinematics; the flow's state, noise and samplers
// stay on absolute joints, and CFG and ProjFlow's projection act on the decoded
// joints as before). Its own section, absent from the dump when off, so runs
// without it keep their names.
struct KinematicBonesConfig : Config {
  bool enabled = false;
  bool rigid = false;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled,
      "the head's pose channels are bone vectors (joint minus parent), summed down the chains to root-relative "
      "joints (off: root-relative joints)");
    v("rigid", rigid,
      "normalise each bone vector and scale it by the bone's mean length over the training split (needs enabled)");
  }
  bool omitted_from_dump() const override { return !enabled && !rigid; }
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
  KinematicBonesConfig bones;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled,
      "the network writes x1_hat as root steps, root height, root position and root-relative joints "
      "(needs prediction: clean)");
    v("weight", weight, "weight of the z-scored loss on those channels beside the flow loss", in_range(0.0, 1e4));
    v("skip", skip, "EDM-style per-channel skip from x_t (off by default)");
    v("noise", noise, "source noise in the head's channels (off by default)");
    v("bones", bones, "pose channels as bone vectors, optionally rigid (off by default)");
  }
  bool omitted_from_dump() const override {
    return !enabled && weight == 1.0 && !noise.enabled && !skip.enabled && bones.omitted_from_dump();
  }
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

// Bone-vector pose block (KinematicBonesConfig). For a skeleton's parents (J, -1 for
// the root, parents before children) the [J-1, J-1] matrices between the pose block
// as root-relative joints and as bone vectors (joint minus parent), indexed by joint
// - 1: relative = A bones (A[j][k] = 1 when joint k+1 is joint j+1 or one of its
// ancestors below the root), bones = D relative (D = A^-1: 1 on the diagonal, -1 at
// the parent's column).
torch::Tensor bones_to_relative_matrix(const std::vector<int>& parents);
torch::Tensor relative_to_bones_matrix(const std::vector<int>& parents);
// Applies such a matrix M to the pose block of channels [B, T, C]: block joint j
// becomes sum_k M[j][k] block joint k; the root's five channels pass unchanged.
torch::Tensor map_pose_block(const torch::Tensor& channels, const torch::Tensor& M);
// Each bone vector of the pose block scaled to `lengths` [J-1] metres (its direction
// kept; a vector shorter than 1e-6 m is taken as it is, scaled by length / 1e-6).
torch::Tensor rigid_pose_block(const torch::Tensor& channels, const torch::Tensor& lengths);

// Per-channel mean and std (each [C], std floored at 1 mm) over the valid frames of
// world clips, accumulated chunk by chunk.
struct KinematicStats {
  torch::Tensor sum, sum_sq;  // [C] double
  torch::Tensor count;        // [C] double: frames (steps count frame pairs)
  torch::Tensor bone_length_sum;  // [J-1] double, with to_bones only
  double bone_frames = 0;
  // to_bones (relative_to_bones_matrix), when given, turns the pose block into bone
  // vectors before counting, and the bones' lengths are averaged too.
  void add(const torch::Tensor& world, const torch::Tensor& valid, const torch::Tensor& to_bones = {});
  std::pair<torch::Tensor, torch::Tensor> mean_std() const;  // float [C]
  torch::Tensor mean_bone_lengths() const;                    // float [J-1] metres
};

}  // namespace mc
