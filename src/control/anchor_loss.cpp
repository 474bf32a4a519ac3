// Batched anchor residuals and losses (eqs. (3), (10), (11)) by one gather over
// the flattened (frame, joint) axis.
#include "control/anchor_loss.h"

#include "core/error.h"

namespace mc {

namespace {

std::string shape_text(const torch::Tensor& t) {
  std::string s = "[";
  for (int64_t i = 0; i < t.dim(); ++i) s += (i ? ", " : "") + std::to_string(t.size(i));
  return s + "]";
}

AnchorBatch pack(const std::vector<std::vector<Anchor>>& per_sample, torch::Device device) {
  const int64_t B = static_cast<int64_t>(per_sample.size());
  int64_t N = 0;
  for (const auto& s : per_sample) N = std::max<int64_t>(N, static_cast<int64_t>(s.size()));
  auto frame = torch::zeros({B, N}, torch::kLong), joint = torch::zeros({B, N}, torch::kLong);
  auto axes = torch::zeros({B, N, 3}), target = torch::zeros({B, N, 3}), valid = torch::zeros({B, N});
  auto fa = frame.accessor<int64_t, 2>(), ja = joint.accessor<int64_t, 2>();
  auto aa = axes.accessor<float, 3>(), ta = target.accessor<float, 3>();
  auto va = valid.accessor<float, 2>();
  for (int64_t b = 0; b < B; ++b)
    for (size_t n = 0; n < per_sample[b].size(); ++n) {
      const Anchor& a = per_sample[b][n];
      fa[b][n] = a.frame;
      ja[b][n] = a.joint;
      va[b][n] = 1.f;
      for (int c = 0; c < 3; ++c)
        if (a.axes[c]) {
          aa[b][n][c] = 1.f;
          ta[b][n][c] = static_cast<float>(a.value[c]);
        }
    }
  return {frame.to(device), joint.to(device), axes.to(device), target.to(device), valid.to(device)};
}

}  // namespace

AnchorBatch make_anchor_batch(const std::vector<AnchorSet>& sets, torch::Device device) {
  std::vector<std::vector<Anchor>> per;
  for (const auto& s : sets) per.push_back(s.anchors);
  return pack(per, device);
}

AnchorBatch make_support_batch(const std::vector<AnchorSet>& sets, int delta, const torch::Tensor& gt_world) {
  if (gt_world.dim() != 4 || gt_world.size(0) != static_cast<int64_t>(sets.size()) || gt_world.size(3) != 3)
    fail("support batch: ground truth must be [B = {}, T, J, 3], got {}", sets.size(), shape_text(gt_world));
  auto gt = gt_world.to(torch::kCPU, torch::kFloat).contiguous();
  const int T = static_cast<int>(gt.size(1)), J = static_cast<int>(gt.size(2));
  std::vector<std::vector<Anchor>> per;
  for (size_t b = 0; b < sets.size(); ++b) {
    if (sets[b].frames > T) fail("support batch: sample {} has {} frames but the ground truth only {}", b, sets[b].frames, T);
    per.push_back(support_targets(sets[b], delta, gt[b].data_ptr<float>(), J).anchors);
  }
  return pack(per, gt_world.device());
}

torch::Tensor anchor_residuals(const torch::Tensor& world, const AnchorBatch& a) {  // eq. (11)
  if (world.dim() != 4 || world.size(0) != a.batch() || world.size(3) != 3)
    fail("anchor residuals: motion must be [B = {}, T, J, 3], got {}", a.batch(), shape_text(world));
  const int64_t B = world.size(0), J = world.size(2);
  if (a.max_anchors() == 0) return torch::zeros({B, 0, 3}, world.options());
  auto flat = world.reshape({B, -1, 3});
  auto idx = (a.frame * J + a.joint).unsqueeze(-1).expand({B, a.max_anchors(), 3});
  auto obs = torch::gather(flat, 1, idx);
  return (obs - a.target) * a.axes * a.valid.unsqueeze(-1);
}

torch::Tensor anchor_loss(const torch::Tensor& world, const AnchorBatch& a) {  // eq. (3) / eq. (10)
  return anchor_residuals(world, a).pow(2).sum({1, 2});
}

torch::Tensor anchor_errors(const torch::Tensor& world, const AnchorBatch& a) {
  // sqrt has an infinite derivative at 0: add a tiny floor inside for the gradient's sake.
  auto sq = anchor_residuals(world, a).pow(2).sum(-1);
  return (sq + 1e-24).sqrt() * a.valid;
}

torch::Tensor mean_control_error(const torch::Tensor& world, const AnchorBatch& a) {
  auto n = a.valid.sum();
  if (n.item<double>() == 0) return torch::zeros({}, world.options());
  return anchor_errors(world, a).sum() / n;
}

}  // namespace mc
