// The batched anchor losses (control/anchor_loss.h, eqs. (3), (10), (11)) against
// their per-set Eigen counterparts, eval's pooled control error, and their gradients.
#include <catch2/catch.hpp>

#include <random>

#include "control/anchor_loss.h"
#include "control/anchors.h"
#include "eval/metrics.h"

using namespace mc;

TEST_CASE("batched anchor losses match the per-set Eigen ones and are differentiable", "[routesolver][anchor_loss]") {
  std::mt19937_64 rng(3);
  const int T = 16, J = 22;
  auto world = torch::randn({2, T, J, 3});
  auto gt = torch::randn({2, T, J, 3});
  std::vector<AnchorSet> sets = {draw_anchor_set(AnchorFamily::planar_root, 3, gt[0].data_ptr<float>(), T, J, rng),
                                 draw_anchor_set(AnchorFamily::body_point, 5, gt[1].data_ptr<float>(), T, J, rng)};
  auto batch = make_anchor_batch(sets);
  CHECK(batch.max_anchors() == 5);
  auto loss = anchor_loss(world, batch);
  auto err = anchor_errors(world, batch);
  auto wc = world.contiguous();
  for (int b = 0; b < 2; ++b) {
    CHECK(loss[b].item<double>() == Approx(mc::anchor_loss(sets[b], wc[b].data_ptr<float>(), J)).epsilon(1e-5));
    auto e = mc::anchor_errors(sets[b], wc[b].data_ptr<float>(), J);
    for (size_t n = 0; n < e.size(); ++n) CHECK(err[b][n].item<double>() == Approx(e[n]).epsilon(1e-5));
  }
  CHECK(err[0][4].item<double>() == 0.0);  // padding
  CHECK(mean_control_error(gt, batch).item<double>() < 1e-6);
  // The AnchorRoute control error is eval's pooled control_error over the same entries.
  std::vector<std::vector<double>> per;
  for (int b = 0; b < 2; ++b) per.push_back(mc::anchor_errors(sets[b], wc[b].data_ptr<float>(), J));
  CHECK(mean_control_error(world, batch).item<double>() ==
        Approx(control_metrics_from_errors(per).control_error).epsilon(1e-5));
  // Gradient: only anchored entries receive it, planar anchors never on y.
  auto x = world.clone().set_requires_grad(true);
  anchor_loss(x, batch).sum().backward();
  const auto& a0 = sets[0].anchors[0];
  CHECK(x.grad()[0][a0.frame][0][1].item<double>() == 0.0);
  CHECK(x.grad()[0][a0.frame][0][0].item<double>() != 0.0);
  CHECK(x.grad().abs().sum().item<double>() > 0);
  // Eq. (10): support targets from the ground truth make the loss vanish on it.
  auto sup = make_support_batch(sets, 2, gt);
  CHECK(anchor_loss(gt, sup).abs().max().item<double>() < 1e-10);
  CHECK(anchor_loss(world, sup).min().item<double>() > 0);
}
