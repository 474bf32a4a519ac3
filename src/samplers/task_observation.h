// Control tasks -> linear observations in the flow prior's model units (one per
// task), and their batched torch form: A x for a whole batch through index tensors.
#pragma once
#include <array>
#include <vector>

#include <torch/torch.h>

#include "control/control_task.h"
#include "control/linear_observation.h"

namespace mc {

class FlowPrior;
struct Skeleton;

// compile(task.spec, task.length, skeleton, task.source) -> affine_to_model with the
// normaliser's per-axis map (x_world = scale * x_model + offset), so A_m x_model = y_m
// with y_m in world units (metres). UserError naming the task when its source clip has
// the wrong size; compile's own errors are prefixed with the task id.
std::vector<LinearObservation> model_observations(const std::vector<ControlTask>& tasks, const Skeleton& skeleton,
                                                  const std::array<double, 3>& axis_scale,
                                                  const std::array<double, 3>& axis_offset);
// The same with the prior's skeleton, joint_std (scale) and joint_mean (offset).
std::vector<LinearObservation> model_observations(const FlowPrior& prior, const std::vector<ControlTask>& tasks);

// The rows of several observations stacked for a batch x [B, T, J, 3] (row-major,
// so the flat index of (b, t, j, c) is b*T*J*3 + (t*J + j)*3 + c, i.e. each
// observation's own column index shifted by b*T*J*3). No dense d x d anywhere.
struct BatchedObservation {
  torch::Tensor row;      // [nnz] int64: stacked row of each non-zero
  torch::Tensor col;      // [nnz] int64: flat index into x.reshape(-1)
  torch::Tensor val;      // [nnz] float: the entry of A
  torch::Tensor y;        // [R] float targets
  torch::Tensor sample;   // [R] int64: batch row of each stacked row
  torch::Tensor hard;     // [R] bool: variance 0
  torch::Tensor row_count;  // [B] float: rows per batch row
  int64_t batch = 0, frames = 0, joints = 0;

  int64_t rows() const { return y.defined() ? y.size(0) : 0; }
  // A x: [R] (differentiable in x).
  torch::Tensor apply(const torch::Tensor& x) const;
  torch::Tensor residual(const torch::Tensor& x) const { return apply(x) - y; }
  // Per batch row mean |A x - y| over its rows, [B] (0 for a row without constraints).
  torch::Tensor mean_abs_residual(const torch::Tensor& x) const;
};

// obs[b] constrains batch row b; every obs must have `joints` joints and at most
// `frames` frames (shorter clips are zero padded at the end).
BatchedObservation batch_observations(const std::vector<const LinearObservation*>& obs, int64_t frames,
                                      int64_t joints, torch::Device device = torch::kCPU);

}  // namespace mc
