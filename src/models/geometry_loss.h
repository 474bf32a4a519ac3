// Geometric terms a motion network's reconstruction or regression loss can add
// (issue 13; MDM trains its prior with such losses): bone-vector error and toe slip
// on ground-truth contact frames, both in world metres. Used by the flow prior
// (`model.geometry_loss` of flow_prior: on the flow-matching error) and the VQ
// tokenizer (`model.geometry_loss` of vq_tokenizer: on the error of the joints its
// decoder's features integrate to).
#pragma once
#include <torch/torch.h>

#include "core/config.h"
#include "data/skeleton.h"

namespace mc {

// floor (ours, 2026-11-28): the squared height error of the toes on frames where the
// ground-truth toe is in contact (below contact_height). Built because the adopted flow
// prior's planted toes sit ±2 cm around the floor (below y = 0 on half the frames).
// Measured at 1,000 on that prior: penetration 3.5 -> 0.6 cm, but foot skating doubles
// and FID rises (docs/choices.md): its feet slide, they were not merely sunk. Off in
// every config. Its own section, absent from the dump when off.
struct GeometryFloorConfig : Config {
  double weight = 0.0;
  void visit(FieldVisitor& v) override {
    v("weight", weight, "weight of the squared toe height error (m) on ground-truth contact frames (0 = off)",
      in_range(0.0, 1e6));
  }
  bool omitted_from_dump() const override { return weight == 0.0; }
};

// The terms are squared errors of the caller's error, measured in world metres per
// axis. For the flow prior that error is the flow-matching one times the per-axis
// std: a positive-definite reweighting, so the loss still has its minimiser at the
// conditional expectation (the flow on absolute joints is unchanged); it only decides
// where a finite network spends its precision. For an autoencoder it is the
// reconstruction error, whose minimiser (the input) is unchanged too. Off by default
// and then left out of the dumped config (every earlier run keeps its name).
//   bone_weight: error of every bone vector (joint minus parent), i.e. of the
//     skeleton Laplacian's edges, the terms ProjFlow's kinematic metric (eq. (11))
//     weighs by w_kin; a z-scored loss weighs a 1 cm pose error on metres of root
//     travel almost not at all.
//   contact_weight: the frame-to-frame difference of the toes' horizontal error on
//     pairs of frames where the ground-truth toe is below contact_height at both
//     frames (MDM's foot-contact loss, on the error so a moving ground-truth toe is
//     not pulled to rest).
//   floor.weight: the toes' squared height error on ground-truth contact frames
//     (GeometryFloorConfig above).
struct GeometryLossConfig : Config {
  double bone_weight = 0.0;
  double contact_weight = 0.0;
  double contact_height = 0.05;  // the foot-skating metric's contact height (reference-facts)
  void visit(FieldVisitor& v) override {
    v("bone_weight", bone_weight, "weight of the squared bone-vector error in metres (0 = off)",
      in_range(0.0, 1e6));
    v("contact_weight", contact_weight,
      "weight of the squared frame-to-frame toe error (horizontal, metres) on ground-truth contact frames (0 = off)",
      in_range(0.0, 1e6));
    v("contact_height", contact_height, "a ground-truth toe below this height (m) at both frames is in contact",
      in_range(0.0, 1.0));
    v("floor", floor, "toe height error on ground-truth contact frames (ours; off by default)");
  }
  GeometryFloorConfig floor;
  bool enabled() const { return bone_weight > 0 || contact_weight > 0 || floor.weight > 0; }
  bool omitted_from_dump() const override { return !enabled() && contact_height == 0.05; }
};

// The geometry terms on one batch: err_m [B, T, J, 3] the error in metres,
// gt_height [B, T, J] the ground truth's joint heights (m), valid [B, T, 1, 1] this
// shard's valid frames, whole_valid [B', T'] the whole batch's (the means are over
// it, so data-parallel shares add up). Zero when both weights are 0.
torch::Tensor geometry_loss(const GeometryLossConfig& g, const Skeleton& sk, const torch::Tensor& err_m,
                            const torch::Tensor& gt_height, const torch::Tensor& valid,
                            const torch::Tensor& whole_valid);

}  // namespace mc
