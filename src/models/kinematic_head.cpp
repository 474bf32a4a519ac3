// The kinematic head's linear map between absolute joints and its channels (root
// steps, root height, root position, root-relative joints) and their statistics.
#include "models/kinematic_head.h"

#include <vector>

namespace mc {

int64_t kinematic_channel_count(int64_t num_joints) { return 5 + (num_joints - 1) * 3; }

namespace {
// Frames whose step is defined: valid and preceded by a valid frame. [B, T] bool.
torch::Tensor step_valid(const torch::Tensor& valid) {
  auto v = valid.to(torch::kBool);
  auto prev = torch::zeros_like(v);
  if (v.size(1) > 1) prev.narrow(1, 1, v.size(1) - 1).copy_(v.narrow(1, 0, v.size(1) - 1));
  return v & prev;
}
}  // namespace

torch::Tensor kinematic_channels(const torch::Tensor& world, const torch::Tensor& valid) {
  const int64_t B = world.size(0), T = world.size(1), J = world.size(2);
  auto root = world.select(2, 0);                                    // [B, T, 3]
  auto rxz = torch::stack({root.select(2, 0), root.select(2, 2)}, -1);  // [B, T, 2]
  auto step = torch::zeros_like(rxz);
  if (T > 1) step.narrow(1, 1, T - 1).copy_(rxz.narrow(1, 1, T - 1) - rxz.narrow(1, 0, T - 1));
  step = step * step_valid(valid).unsqueeze(-1).to(step.dtype());
  auto rel = (world.narrow(2, 1, J - 1) - world.narrow(2, 0, 1)).reshape({B, T, (J - 1) * 3});
  return torch::cat({step, root.narrow(2, 1, 1), rxz, rel}, -1);
}

torch::Tensor joints_from_kinematic(const torch::Tensor& ch, const torch::Tensor& valid) {
  const int64_t B = ch.size(0), T = ch.size(1), J = (ch.size(2) - 5) / 3 + 1;
  auto sv = step_valid(valid).unsqueeze(-1).to(ch.dtype());
  auto path = torch::cumsum(ch.narrow(2, 0, 2) * sv, 1);  // [B, T, 2], 0 on frame 0
  auto vm = valid.to(ch.dtype()).unsqueeze(-1);            // [B, T, 1]
  auto n = vm.sum(1, true).clamp_min(1.0);
  auto offset = ((ch.narrow(2, 3, 2) - path) * vm).sum(1, true) / n;  // [B, 1, 2]
  auto rxz = path + offset;
  auto root = torch::stack({rxz.select(2, 0), ch.select(2, 2), rxz.select(2, 1)}, -1).unsqueeze(2);  // [B,T,1,3]
  auto rel = ch.narrow(2, 5, (J - 1) * 3).reshape({B, T, J - 1, 3});
  return torch::cat({root, root + rel}, 2);
}

torch::Tensor bones_to_relative_matrix(const std::vector<int>& parents) {
  const int64_t n = static_cast<int64_t>(parents.size()) - 1;
  auto A = torch::zeros({n, n});
  auto a = A.accessor<float, 2>();
  for (int64_t j = 1; j <= n; ++j)
    for (int k = static_cast<int>(j); k > 0; k = parents[k]) a[j - 1][k - 1] = 1.0f;
  return A;
}

torch::Tensor relative_to_bones_matrix(const std::vector<int>& parents) {
  const int64_t n = static_cast<int64_t>(parents.size()) - 1;
  auto D = torch::eye(n);
  auto d = D.accessor<float, 2>();
  for (int64_t j = 1; j <= n; ++j)
    if (parents[j] > 0) d[j - 1][parents[j] - 1] = -1.0f;
  return D;
}

torch::Tensor map_pose_block(const torch::Tensor& ch, const torch::Tensor& M) {
  const int64_t B = ch.size(0), T = ch.size(1), n = (ch.size(2) - 5) / 3;
  auto block = ch.narrow(2, 5, n * 3).reshape({B, T, n, 3});
  auto mapped = torch::einsum("jk,btkc->btjc", {M.to(ch.device(), ch.scalar_type()), block});
  return torch::cat({ch.narrow(2, 0, 5), mapped.reshape({B, T, n * 3})}, 2);
}

torch::Tensor rigid_pose_block(const torch::Tensor& ch, const torch::Tensor& lengths) {
  const int64_t B = ch.size(0), T = ch.size(1), n = (ch.size(2) - 5) / 3;
  auto block = ch.narrow(2, 5, n * 3).reshape({B, T, n, 3});
  auto norm = block.norm(2, -1, true).clamp_min(1e-6);
  auto scaled = block / norm * lengths.to(ch.device(), ch.scalar_type()).view({1, 1, n, 1});
  return torch::cat({ch.narrow(2, 0, 5), scaled.reshape({B, T, n * 3})}, 2);
}

void KinematicStats::add(const torch::Tensor& world, const torch::Tensor& valid, const torch::Tensor& to_bones) {
  auto ch = kinematic_channels(world, valid).to(torch::kFloat64);  // [B, T, C]
  const int64_t C = ch.size(2);
  if (to_bones.defined()) {
    ch = map_pose_block(ch, to_bones);
    const int64_t n = (C - 5) / 3;
    auto vf = valid.to(torch::kFloat64);  // [B, T]
    auto len = ch.narrow(2, 5, n * 3).reshape({ch.size(0), ch.size(1), n, 3}).norm(2, -1);  // [B, T, n]
    auto s = (len * vf.unsqueeze(-1)).sum(std::vector<int64_t>{0, 1});
    bone_length_sum = bone_length_sum.defined() ? bone_length_sum + s : s;
    bone_frames += vf.sum().item<double>();
  }
  auto w = valid.to(torch::kFloat64).unsqueeze(-1).expand({-1, -1, C}).clone();
  w.narrow(2, 0, 2).copy_(step_valid(valid).to(torch::kFloat64).unsqueeze(-1).expand({-1, -1, 2}));
  const std::vector<int64_t> dims = {0, 1};
  auto s = (ch * w).sum(dims), s2 = (ch * ch * w).sum(dims), c = w.sum(dims);
  if (!sum.defined()) {
    sum = s, sum_sq = s2, count = c;
  } else {
    sum += s, sum_sq += s2, count += c;
  }
}

torch::Tensor KinematicStats::mean_bone_lengths() const {
  return (bone_length_sum / std::max(bone_frames, 1.0)).to(torch::kFloat32);
}

std::pair<torch::Tensor, torch::Tensor> KinematicStats::mean_std() const {
  auto n = count.clamp_min(1.0);
  auto mean = sum / n;
  auto var = (sum_sq / n - mean * mean).clamp_min(0.0);
  return {mean.to(torch::kFloat32), var.sqrt().clamp_min(1e-3).to(torch::kFloat32)};
}

}  // namespace mc
