// Differentiable anchor losses on world joints (AnchorRoute eqs. (3), (10), (11)),
// batched over samples whose anchor sets differ in size (padded + masked).
#pragma once
#include <vector>

#include <torch/torch.h>

#include "control/anchors.h"

namespace mc {

// Anchor sets of B samples padded to the largest N: padding rows have valid = 0
// and point at frame 0, joint 0 with zero axes and target.
struct AnchorBatch {
  torch::Tensor frame;   // [B, N] int64
  torch::Tensor joint;   // [B, N] int64
  torch::Tensor axes;    // [B, N, 3] float, 1 on controlled axes (Pi_{m_n})
  torch::Tensor target;  // [B, N, 3] float, y_n (0 on uncontrolled axes)
  torch::Tensor valid;   // [B, N] float
  int64_t batch() const { return frame.size(0); }
  int64_t max_anchors() const { return frame.size(1); }
};

AnchorBatch make_anchor_batch(const std::vector<AnchorSet>& sets, torch::Device device = torch::kCPU);
// Eqs. (7)-(9): the support entries of every set with targets read from the
// ground-truth world motions gt [B, T, J, 3] (so eq. (10) is anchor_loss on it).
AnchorBatch make_support_batch(const std::vector<AnchorSet>& sets, int delta, const torch::Tensor& gt_world);

// Eq. (11): r_n = Pi_{m_n}(x[tau_n]) - y_n for world [B, T, J, 3] -> [B, N, 3]
// (zero on uncontrolled axes and padding).
torch::Tensor anchor_residuals(const torch::Tensor& world, const AnchorBatch& a);
// Eq. (3) per sample: sum_n ||r_n||^2 -> [B]. Eq. (10) with a support batch.
torch::Tensor anchor_loss(const torch::Tensor& world, const AnchorBatch& a);
// ||r_n|| -> [B, N] (0 on padding): the AnchorRoute control error of each anchor.
torch::Tensor anchor_errors(const torch::Tensor& world, const AnchorBatch& a);
// The control error of the batch: mean ||r_n|| over all valid anchors (scalar;
// 0 without anchors). Matches eval's control_metrics(...).control_error.
torch::Tensor mean_control_error(const torch::Tensor& world, const AnchorBatch& a);

}  // namespace mc
