// The flow prior's kinematic head: the map between absolute joints and its channels
// is exact and linear, the root's shape comes from its steps alone, the statistics
// count what they should, and a prior with the head trains, decodes and stays out of
// the dump when off.
#include <catch2/catch.hpp>

#include <ATen/CPUGeneratorImpl.h>

#include "core/error.h"
#include "data/skeleton.h"
#include "models/flow_prior.h"
#include "models/kinematic_head.h"
#include "trainer_test_util.h"

using namespace mc;

namespace {
// Valid frames a prefix of each row: lengths [B] of T.
torch::Tensor prefix_mask(const std::vector<int64_t>& lengths, int64_t T) {
  auto m = torch::zeros({static_cast<int64_t>(lengths.size()), T}, torch::kBool);
  for (size_t b = 0; b < lengths.size(); ++b) m[b].narrow(0, 0, lengths[b]).fill_(true);
  return m;
}
// Random world clips whose root wanders by metres, like the fixture's.
torch::Tensor wandering_clips(int64_t B, int64_t T, int64_t J) {
  auto root = torch::cumsum(torch::randn({B, T, 1, 3}) * 0.05, 1) + torch::randn({B, 1, 1, 3}) * 3.0;
  return root + torch::randn({B, T, J, 3}) * 0.3;
}
}  // namespace

TEST_CASE("kinematic head: channels decode back to the joints on valid frames", "[flow][kinematic]") {
  const int64_t J = 22, T = 11;
  for (uint64_t seed : {1u, 2u, 3u, 4u}) {
    torch::manual_seed(seed);
    auto world = wandering_clips(3, T, J).to(torch::kFloat64);
    auto mask = prefix_mask({11, 6, 1}, T);
    auto ch = kinematic_channels(world, mask);
    REQUIRE(ch.size(2) == kinematic_channel_count(J));
    auto back = joints_from_kinematic(ch, mask);
    auto vm = mask.view({3, T, 1, 1}).expand_as(world);
    CHECK(torch::allclose(back.masked_select(vm), world.masked_select(vm), 1e-9, 1e-9));
    CHECK(torch::isfinite(back).all().item<bool>());
    // The first frame and padded frames have no step.
    CHECK(ch.select(1, 0).narrow(1, 0, 2).abs().max().item<double>() == 0.0);
    CHECK(ch[1].narrow(0, 6, T - 6).narrow(1, 0, 2).abs().max().item<double>() == 0.0);
  }
}

TEST_CASE("kinematic head: the decode is linear, and the root's shape is the running sum of its steps",
          "[flow][kinematic]") {
  const int64_t J = 5, T = 9, C = kinematic_channel_count(J);
  auto mask = prefix_mask({9, 4}, T);
  torch::manual_seed(7);
  for (int rep = 0; rep < 5; ++rep) {
    auto a = torch::randn({2, T, C}, torch::kFloat64), b = torch::randn({2, T, C}, torch::kFloat64);
    auto lhs = joints_from_kinematic(2.0 * a - 0.5 * b, mask);
    auto rhs = 2.0 * joints_from_kinematic(a, mask) - 0.5 * joints_from_kinematic(b, mask);
    CHECK(torch::allclose(lhs, rhs, 1e-9, 1e-9));
    // Noise in the root-position channels moves the whole root path by their mean
    // over valid frames and nothing else: frame-to-frame moves come from the steps.
    auto noisy = a.clone();
    auto noise = torch::randn({2, T, 2}, torch::kFloat64);
    noisy.narrow(2, 3, 2).add_(noise);
    auto d = joints_from_kinematic(noisy, mask) - joints_from_kinematic(a, mask);  // [2, T, J, 3]
    for (int64_t row = 0; row < 2; ++row) {
      const int64_t L = row == 0 ? 9 : 4;
      auto mean = noise[row].narrow(0, 0, L).mean(0);  // [2]
      for (int64_t f = 0; f < L; ++f) {
        CHECK(d[row][f][J - 1][0].item<double>() == Approx(mean[0].item<double>()).margin(1e-9));
        CHECK(d[row][f][0][2].item<double>() == Approx(mean[1].item<double>()).margin(1e-9));
        CHECK(d[row][f][0][1].item<double>() == Approx(0.0).margin(1e-12));  // height has its own channel
      }
    }
  }
}

TEST_CASE("kinematic head: statistics over valid frames, steps over valid frame pairs", "[flow][kinematic]") {
  const int64_t J = 3, T = 4;
  // One clip of 3 valid frames whose root moves +1 m in x per frame, joints fixed offsets.
  auto world = torch::zeros({1, T, J, 3});
  for (int64_t f = 0; f < T; ++f) {
    world[0][f][0][0] = static_cast<float>(f);
    world[0][f][0][1] = 0.9f;
    world[0][f][1] = world[0][f][0] + torch::tensor({0.0f, 0.5f, 0.0f});
    world[0][f][2] = world[0][f][0] + torch::tensor({0.2f, -0.5f, 0.1f});
  }
  world[0][3].fill_(100.0f);  // padding: must not count
  KinematicStats stats;
  stats.add(world, prefix_mask({3}, T));
  auto [mean, std] = stats.mean_std();
  CHECK(stats.count[0].item<double>() == 2.0);  // steps: frame pairs (1,0), (2,1)
  CHECK(stats.count[2].item<double>() == 3.0);
  CHECK(mean[0].item<double>() == Approx(1.0));  // step x
  CHECK(std[0].item<double>() == Approx(1e-3));   // constant: floored at 1 mm
  CHECK(mean[2].item<double>() == Approx(0.9));  // root height
  CHECK(mean[3].item<double>() == Approx(1.0));  // root x over frames 0, 1, 2
  CHECK(std[3].item<double>() == Approx(std::sqrt(2.0 / 3.0)));
  CHECK(mean[5 + 3 + 1].item<double>() == Approx(-0.5));  // joint 2's relative height
}

namespace {
std::unique_ptr<Trainable> kin_trainer(TrainJobConfig& job, const std::string& extra) {
  return test::trainer_on_random_clips(job,
                                       "model:\n  type: flow_prior\n  depth: 2\n  width: 32\n  heads: 2\n"
                                       "  text_width: 16\n  text_heads: 2\n  text_ff: 32\n  text_layers: 1\n"
                                       "  prediction: clean\n" +
                                           extra,
                                       {12, 30, 17, 9}, true);
}
// Sum of squared gradients over a trainer's parameters after backward().
double grad_sq(Trainable& tr) {
  double gsq = 0;
  for (auto& p : tr.trainable_parameters())
    if (p.grad().defined()) gsq += p.grad().pow(2).sum().item<double>();
  return gsq;
}
}  // namespace

TEST_CASE("kinematic head: a flow prior with it decodes, trains, and is absent from the dump when off",
          "[flow][kinematic]") {
  TrainJobConfig off_job, on_job, zero_job;
  auto off = kin_trainer(off_job, "");
  auto on = kin_trainer(on_job, "  kinematic_head:\n    enabled: true\n");
  auto zero = kin_trainer(zero_job, "  kinematic_head:\n    enabled: true\n    weight: 0\n");
  CHECK(dump_config(off_job).find("kinematic_head") == std::string::npos);
  CHECK(dump_config(on_job).find("kinematic_head") != std::string::npos);

  auto& net = dynamic_cast<FlowPriorNetImpl&>(on->module());
  REQUIRE(net.kinematic_head);
  const int64_t J = 22, C = kinematic_channel_count(J);
  CHECK(net.kin_mean.size(0) == C);
  CHECK((net.kin_std > 0).all().item<bool>());
  // The head writes C channels; x + (1 - t) v lands on the joints they decode to.
  auto x = torch::randn({2, 6, J, 3});
  auto out = torch::randn({2, 6, C});
  auto mask = prefix_mask({6, 4}, 6);
  auto t = torch::tensor({0.2f, 0.95f});
  auto x1_hat = net.decode_head(out, mask);
  REQUIRE(x1_hat.sizes() == x.sizes());
  auto v = net.to_velocity(out, x, t, mask);
  CHECK(torch::allclose(x[0] + 0.8 * v[0], x1_hat[0], 1e-5, 1e-5));
  CHECK(torch::allclose(x[1] + 0.05 * v[1], x1_hat[1], 1e-4, 1e-4));
  CHECK(torch::allclose(net.to_clean(out, x, t, mask), x1_hat));
  // The head's channels of the data decode back to the data in normalised units.
  auto world = wandering_clips(2, 6, J);
  auto norm = (world - net.joint_mean) / net.joint_std;
  auto z = (kinematic_channels(world, mask) - net.kin_mean) / net.kin_std;
  auto vm = mask.view({2, 6, 1, 1}).expand_as(norm);
  CHECK(torch::allclose(net.decode_head(z, mask).masked_select(vm), norm.masked_select(vm), 1e-4, 1e-4));

  // Same weights and draws: the channel loss adds to the flow loss; both train.
  test::same_random_weights({on.get(), zero.get()});
  torch::manual_seed(9);
  auto lo = on->loss({0, 1}).loss;
  torch::manual_seed(9);
  auto lz = zero->loss({0, 1}).loss;
  CHECK(lo.item<double>() > lz.item<double>());
  lo.backward();
  const double gsq = grad_sq(*on);
  CHECK(std::isfinite(gsq));
  CHECK(gsq > 0);
  on->module().eval();
  auto e = on->evaluate();
  CHECK(std::isfinite(e.at("val_x1")));

  // The head states x1_hat: a velocity network cannot have it.
  TrainJobConfig bad;
  CHECK_THROWS_AS(test::trainer_on_random_clips(bad,
                                                "model:\n  type: flow_prior\n  depth: 2\n  width: 32\n  heads: 2\n"
                                                "  text_width: 16\n  text_heads: 2\n  text_ff: 32\n"
                                                "  kinematic_head:\n    enabled: true\n",
                                                {12, 30, 17, 9}, true),
                  mc::UserError);
}

TEST_CASE("kinematic head: source noise is the papers' N(0, I) unless asked, else Gaussian at the channels' scale",
          "[flow][kinematic]") {
  TrainJobConfig abs_job, kin_job;
  auto abs = kin_trainer(abs_job, "  kinematic_head:\n    enabled: true\n");
  auto kin = kin_trainer(kin_job, "  kinematic_head:\n    enabled: true\n    noise:\n      enabled: true\n");
  CHECK(dump_config(abs_job).find("noise") == std::string::npos);
  CHECK(dump_config(kin_job).find("noise") != std::string::npos);
  auto& an = dynamic_cast<FlowPriorNetImpl&>(abs->module());
  auto& kn = dynamic_cast<FlowPriorNetImpl&>(kin->module());
  const int64_t J = 22, T = 40, B = 400;
  auto mask = prefix_mask(std::vector<int64_t>(B, T), T);
  // Absolute: bit for bit the draw every sampler made before the option existed.
  auto g1 = at::make_generator<at::CPUGeneratorImpl>(5), g2 = at::make_generator<at::CPUGeneratorImpl>(5);
  CHECK(torch::equal(an.draw_noise(mask, J, g1), torch::randn({B, T, J, 3}, g2, torch::TensorOptions())));
  // Kinematic: root-relative offsets carry each channel's std, the root's steps the
  // steps' std, in world metres.
  auto g3 = at::make_generator<at::CPUGeneratorImpl>(6);
  auto x0 = kn.draw_noise(mask, J, g3);
  REQUIRE(x0.sizes() == torch::IntArrayRef({B, T, J, 3}));
  auto world = x0 * kn.joint_std;
  auto ch = kinematic_channels(world, mask);
  const std::vector<int64_t> bt = {0, 1};
  auto rel_std = ch.narrow(2, 5, (J - 1) * 3).std(bt);
  auto want = kn.kin_std.narrow(0, 5, (J - 1) * 3);
  CHECK(((rel_std / want) - 1).abs().max().item<double>() < 0.05);
  auto step_std = ch.narrow(1, 1, T - 1).narrow(2, 0, 2).std(bt);
  CHECK(((step_std / kn.kin_std.narrow(0, 0, 2)) - 1).abs().max().item<double>() < 0.05);
  // The root's mean position keeps one position's std.
  auto offset_std = world.select(2, 0).mean(1).std(std::vector<int64_t>{0});  // [3]
  CHECK(offset_std[0].item<double>() == Approx(kn.kin_std[3].item<double>()).epsilon(0.15));
  // Training and validation draw it too.
  torch::manual_seed(3);
  auto out = kin->loss({0, 1});
  CHECK(std::isfinite(out.loss.item<double>()));
  kin->module().eval();
  CHECK(std::isfinite(kin->evaluate().at("val_x1")));
  // It needs the head (its statistics shape the noise).
  TrainJobConfig bad;
  CHECK_THROWS_AS(kin_trainer(bad, "  kinematic_head:\n    noise:\n      enabled: true\n"), mc::UserError);
}

TEST_CASE("kinematic head skip: the clean head at t = 0, x itself as t -> 1, the noise's own scale per channel between",
          "[flow][kinematic]") {
  TrainJobConfig plain_job, skip_job;
  auto plain = kin_trainer(plain_job, "  kinematic_head:\n    enabled: true\n");
  auto skip = kin_trainer(skip_job, "  kinematic_head:\n    enabled: true\n    skip:\n      enabled: true\n");
  CHECK(dump_config(plain_job).find("skip") == std::string::npos);
  CHECK(dump_config(skip_job).find("skip") != std::string::npos);
  auto& pn = dynamic_cast<FlowPriorNetImpl&>(plain->module());
  auto& sn = dynamic_cast<FlowPriorNetImpl&>(skip->module());
  REQUIRE(sn.kinematic_skip);
  REQUIRE_FALSE(pn.kinematic_skip);
  const int64_t J = 22, C = kinematic_channel_count(J), T = 8;
  auto mask = prefix_mask({8, 5}, T);
  auto vm = mask.view({2, T, 1, 1}).expand({2, T, J, 3});
  for (uint64_t seed : {1u, 2u, 3u}) {
    torch::manual_seed(seed);
    auto world = wandering_clips(2, T, J);
    auto x1 = (world - sn.joint_mean) / sn.joint_std;
    auto x0 = torch::randn({2, T, J, 3});
    auto out = torch::randn({2, T, C});
    // t = 0: exactly the plain head (c_skip = 0, c_out = 1).
    auto t0 = torch::zeros({2});
    CHECK(torch::allclose(sn.head_channels(out, x0, t0, mask), out, 0, 0));
    CHECK(torch::allclose(sn.to_clean(out, x0, t0, mask), pn.decode_head(out, mask), 1e-5, 1e-5));
    // t -> 1: x1_hat is x_t itself whatever the output (c_out -> 0).
    auto t1 = torch::full({2}, 1.0 - 1e-6);
    auto xt = 0.999999 * x1 + 1e-6 * x0;
    CHECK(torch::allclose(sn.to_clean(out, xt, t1, mask).masked_select(vm), xt.masked_select(vm), 1e-3, 1e-3));
    // The plain head ignores x: the same output gives the same x1_hat at any t.
    CHECK(torch::allclose(pn.to_clean(out, xt, t1, mask), pn.decode_head(out, mask)));
    // Between: affine in the output with slope c_out in (0, 1), and the skip part is
    // c_skip times the channels of x / t (here x = t x1 exactly, no noise).
    auto tm = torch::full({2}, 0.6);
    auto zero = torch::zeros_like(out);
    auto base = sn.head_channels(zero, 0.6 * x1, tm, mask);
    auto slope = sn.head_channels(torch::ones_like(out), 0.6 * x1, tm, mask) - base;
    CHECK((slope > 0).all().item<bool>());
    CHECK((slope < 1).all().item<bool>());
    auto z1 = (kinematic_channels(world, mask) - sn.kin_mean) / sn.kin_std;
    auto c_skip = 1 - slope.pow(2);  // c_skip = 1 / (1 + s^2), c_out = s / sqrt(1 + s^2)
    auto cm = mask.unsqueeze(-1).expand({2, T, C});
    CHECK(torch::allclose(base.masked_select(cm), (c_skip * z1).masked_select(cm), 1e-4, 1e-4));
  }
  // The skip needs the head, and the papers' noise.
  TrainJobConfig bad1, bad2;
  CHECK_THROWS_AS(kin_trainer(bad1, "  kinematic_head:\n    skip:\n      enabled: true\n"), mc::UserError);
  CHECK_THROWS_AS(kin_trainer(bad2, "  kinematic_head:\n    enabled: true\n    skip:\n      enabled: true\n"
                                    "    noise:\n      enabled: true\n"),
                  mc::UserError);
  // Same weights and draws as the plain head: the loss trains (finite, non-zero gradient).
  test::same_random_weights({plain.get(), skip.get()});
  torch::manual_seed(4);
  auto l = skip->loss({0, 1}).loss;
  l.backward();
  CHECK(std::isfinite(l.item<double>()));
  CHECK(grad_sq(*skip) > 0);
}

TEST_CASE("kinematic head bones: the pose block as bone vectors is exact and linear, and rigid bones keep the "
          "training split's lengths on every frame",
          "[flow][kinematic]") {
  const Skeleton sk = humanml3d_skeleton();
  const int64_t J = sk.num_joints(), n = J - 1, T = 7;
  auto A = bones_to_relative_matrix(sk.parents), D = relative_to_bones_matrix(sk.parents);
  CHECK(torch::allclose(torch::matmul(A, D), torch::eye(n), 0, 1e-6));
  auto mask = prefix_mask({7, 3}, T);
  torch::manual_seed(11);
  auto world = wandering_clips(2, T, J).to(torch::kFloat64);
  auto rel_ch = kinematic_channels(world, mask);
  auto bone_ch = map_pose_block(rel_ch, D);
  // A bone channel triple is the joint minus its parent, for every joint off the root.
  for (int64_t j = 1; j < J; ++j) {
    auto want = world.select(2, j) - world.select(2, sk.parents[j]);  // [2, T, 3]
    CHECK(torch::allclose(bone_ch.narrow(2, 5 + (j - 1) * 3, 3), want, 1e-9, 1e-9));
  }
  CHECK(torch::allclose(map_pose_block(bone_ch, A), rel_ch, 1e-9, 1e-9));
  // Rigid: every bone vector gets the given length, its direction kept.
  auto lengths = torch::rand({n}, torch::kFloat64) + 0.05;
  auto rigid = rigid_pose_block(bone_ch, lengths);
  auto rb = rigid.narrow(2, 5, n * 3).reshape({2, T, n, 3}), ob = bone_ch.narrow(2, 5, n * 3).reshape({2, T, n, 3});
  CHECK(torch::allclose(rb.norm(2, -1), lengths.view({1, 1, n}).expand({2, T, n}), 1e-9, 1e-9));
  CHECK(torch::allclose((rb * ob).sum(-1), rb.norm(2, -1) * ob.norm(2, -1), 1e-9, 1e-9));
  CHECK(torch::equal(rigid.narrow(2, 0, 5), bone_ch.narrow(2, 0, 5)));

  // In a prior: off, absent from the dump; bones decode the data's channels back to
  // the data; rigid decodes any output to the training split's bone lengths.
  TrainJobConfig head_job, bones_job, rigid_job;
  auto head = kin_trainer(head_job, "  kinematic_head:\n    enabled: true\n");
  auto bones = kin_trainer(bones_job, "  kinematic_head:\n    enabled: true\n    bones:\n      enabled: true\n");
  std::shared_ptr<MotionDataset> data;
  auto rigid_tr = test::trainer_on_random_clips(rigid_job,
                                                "model:\n  type: flow_prior\n  depth: 2\n  width: 32\n  heads: 2\n"
                                                "  text_width: 16\n  text_heads: 2\n  text_ff: 32\n  text_layers: 1\n"
                                                "  prediction: clean\n  kinematic_head:\n    enabled: true\n"
                                                "    bones:\n      enabled: true\n      rigid: true\n",
                                                {12, 30, 17, 9}, true, &data);
  CHECK(dump_config(head_job).find("bones") == std::string::npos);
  CHECK(dump_config(bones_job).find("bones") != std::string::npos);
  auto& bn = dynamic_cast<FlowPriorNetImpl&>(bones->module());
  auto& rn = dynamic_cast<FlowPriorNetImpl&>(rigid_tr->module());
  REQUIRE(bn.kinematic_bones);
  REQUIRE_FALSE(bn.kinematic_rigid);
  REQUIRE(rn.kinematic_rigid);
  CHECK(torch::allclose(bn.kin_to_bones, D.to(torch::kFloat32)));
  CHECK(torch::allclose(bn.kin_from_bones, A.to(torch::kFloat32)));
  auto wf = world.to(torch::kFloat32);
  auto norm = (wf - bn.joint_mean) / bn.joint_std;
  auto z = (bn.head_target_channels(wf, mask) - bn.kin_mean) / bn.kin_std;
  auto vm = mask.view({2, T, 1, 1}).expand_as(norm);
  CHECK(torch::allclose(bn.decode_head(z, mask).masked_select(vm), norm.masked_select(vm), 1e-4, 1e-4));
  // The rigid lengths are the mean bone lengths over the training split's valid frames.
  MotionBatch b = data->batch(data->split("train"), 0, 1, torch::kCPU);
  auto tw = data->denormalize(b.joints);
  auto tb = map_pose_block(kinematic_channels(tw, b.mask), D.to(torch::kFloat32));
  auto tl = tb.narrow(2, 5, n * 3).reshape({tb.size(0), tb.size(1), n, 3}).norm(2, -1);  // [B, T, n]
  auto mf = b.mask.to(torch::kFloat32).unsqueeze(-1);
  auto want_len = (tl * mf).sum(std::vector<int64_t>{0, 1}) / mf.sum(std::vector<int64_t>{0, 1});
  CHECK(torch::allclose(rn.kin_bone_length, want_len, 1e-4, 1e-5));
  auto out = torch::randn({2, T, kinematic_channel_count(J)});
  auto decoded = rn.decode_head(out, mask) * rn.joint_std + rn.joint_mean;  // world [2, T, J, 3]
  for (int64_t j = 1; j < J; ++j) {
    auto len = (decoded.select(2, j) - decoded.select(2, sk.parents[j])).norm(2, -1);  // [2, T]
    CHECK(torch::allclose(len.masked_select(mask), rn.kin_bone_length[j - 1].expand({mask.sum().item<int64_t>()}),
                          1e-4, 1e-4));
  }
  // Both train: finite loss, non-zero gradient.
  for (auto* tr : {bones.get(), rigid_tr.get()}) {
    test::same_random_weights({tr});
    torch::manual_seed(9);
    auto l = tr->loss({0, 1}).loss;
    l.backward();
    CHECK(std::isfinite(l.item<double>()));
    CHECK(grad_sq(*tr) > 0);
  }
  // Refused: bones without the head, rigid without bones, bones with the noise or the skip.
  for (const char* bad : {"  kinematic_head:\n    bones:\n      enabled: true\n",
                          "  kinematic_head:\n    enabled: true\n    bones:\n      rigid: true\n",
                          "  kinematic_head:\n    enabled: true\n    bones:\n      enabled: true\n    noise:\n"
                          "      enabled: true\n",
                          "  kinematic_head:\n    enabled: true\n    bones:\n      enabled: true\n    skip:\n"
                          "      enabled: true\n"}) {
    INFO(bad);
    TrainJobConfig job;
    CHECK_THROWS_AS(kin_trainer(job, bad), mc::UserError);
  }
}
