// Bone-vector and toe-slip loss terms in world metres (see geometry_loss.h).
#include "models/geometry_loss.h"

#include <vector>

namespace mc {

torch::Tensor geometry_loss(const GeometryLossConfig& g, const Skeleton& sk, const torch::Tensor& err_m,
                            const torch::Tensor& gt_height, const torch::Tensor& valid,
                            const torch::Tensor& whole_valid) {
  const auto dev = err_m.device();
  auto total = torch::zeros({}, err_m.options());
  if (g.bone_weight > 0) {
    std::vector<int64_t> child, parent;
    for (int j = 0; j < sk.num_joints(); ++j)
      if (sk.parents[j] >= 0) child.push_back(j), parent.push_back(sk.parents[j]);
    auto ci = torch::tensor(child, torch::kLong).to(dev), pi = torch::tensor(parent, torch::kLong).to(dev);
    auto be = err_m.index_select(2, ci) - err_m.index_select(2, pi);  // bone-vector errors
    total = total + g.bone_weight * (be.pow(2) * valid).sum() / (whole_valid.sum() * double(child.size()) * 3 + 1e-8);
  }
  const int64_t T = err_m.size(1);
  if (g.contact_weight > 0 && T > 1) {
    const auto& toes = sk.role("toes");
    auto ti = torch::tensor(std::vector<int64_t>(toes.begin(), toes.end()), torch::kLong).to(dev);
    auto low = (gt_height.index_select(2, ti) < g.contact_height).to(err_m.scalar_type());  // [B, T, toes]
    auto contact = low.narrow(1, 1, T - 1) * low.narrow(1, 0, T - 1);
    auto v = valid.view({valid.size(0), T, 1});
    auto pairs = v.narrow(1, 1, T - 1) * v.narrow(1, 0, T - 1);
    auto wv = whole_valid.view({whole_valid.size(0), -1});
    const int64_t Tw = wv.size(1);
    auto whole_pairs = (wv.narrow(1, 1, Tw - 1) * wv.narrow(1, 0, Tw - 1)).sum();
    auto et = err_m.index_select(2, ti);
    auto d = et.narrow(1, 1, T - 1) - et.narrow(1, 0, T - 1);        // [B, T-1, toes, 3]
    auto horiz = d.select(3, 0).pow(2) + d.select(3, 2).pow(2);       // squared horizontal slip error
    total = total + g.contact_weight * (horiz * contact * pairs).sum() / (whole_pairs * double(toes.size()) + 1e-8);
  }
  if (g.floor.weight > 0) {
    const auto& toes = sk.role("toes");
    auto ti = torch::tensor(std::vector<int64_t>(toes.begin(), toes.end()), torch::kLong).to(dev);
    // Per frame, not per frame pair as the slip term: a height error is one frame's.
    auto contact = (gt_height.index_select(2, ti) < g.contact_height).to(err_m.scalar_type());  // [B, T, toes]
    auto v = valid.view({valid.size(0), T, 1});
    auto ey = err_m.index_select(2, ti).select(3, 1);  // toes' height error [B, T, toes]
    total = total + g.floor.weight * (ey.pow(2) * contact * v).sum() / (whole_valid.sum() * double(toes.size()) + 1e-8);
  }
  return total;
}

}  // namespace mc
