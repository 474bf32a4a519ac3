// ACMDM+ControlNet: zero-init equivalence with the base, copied blocks, frozen base
// under training steps, the three-pass guidance, the unweighted control loss,
// training control masks (also pelvis-only), a short real training that lowers the
// control loss, tasks -> control signal (and the error for non-joint constraints),
// and an end-to-end train + sample.
#include <catch2/catch.hpp>

#include <ATen/CPUGeneratorImpl.h>

#include <yaml-cpp/yaml.h>

#include <random>
#include <set>

#include "core/error.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "models/flow_controlnet.h"
#include "samplers/controlnet_generator.h"
#include "models/flow_prior_test_util.h"
#include "samplers/motion_generator.h"
#include "test_util.h"
#include "train/dependencies.h"
#include "models/motion_dataset.h"
#include "train/train_job.h"
#include "models/trainable.h"
#include "samplers/generator_test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

// Random clips of the given lengths on the HumanML3D skeleton (world metres).
MotionSet random_set(const std::vector<int>& lengths, unsigned seed) {
  MotionSet m;
  m.skeleton = humanml3d_skeleton();
  m.fps = 20;
  m.t_max = 40;
  m.lengths = lengths;
  m.joints.assign(lengths.size() * m.clip_stride(), 0.0f);
  std::mt19937 rng(seed);
  std::normal_distribution<float> n(0.0f, 0.5f);
  for (size_t i = 0; i < lengths.size(); ++i) {
    for (int t = 0; t < lengths[i]; ++t)
      for (int j = 0; j < 22; ++j)
        for (int a = 0; a < 3; ++a) m.at(i, t, j)[a] = n(rng) + (a == 1 ? 0.9f : 0.0f);
    m.ids.push_back("clip" + std::to_string(i));
    m.splits.push_back(i % 4 == 3 ? "val" : "train");
    m.captions.push_back({"a person walks number " + std::to_string(i % 4), "a person jumps"});
  }
  NormStats st;
  st.joint_mean = {0.0f, 0.9f, 0.0f};
  st.joint_std = {0.5f, 0.5f, 0.5f};
  m.stats = st;
  return m;
}

}  // namespace

TEST_CASE("ControlNet: zero-initialised branch gives exactly the base's velocity", "[controlnet]") {
  TempDir dir("cn_zero");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers);
  // Ours; with ACMDM's RMS-normalised signal embedding (model.signal.norm); with the
  // zero-initialised residual head on the output joints (model.signal.residual_head).
  const int variant = GENERATE(0, 1, 2);
  const bool signal_norm = variant == 1, residual_head = variant == 2;
  FlowControlNet net = FlowControlNet::around(FlowPrior::load(dir.path.string()), signal_norm, residual_head);
  CHECK(net.branch()->signal_gain.defined() == signal_norm);
  CHECK(!net.branch()->residual_out.is_empty() == residual_head);
  const FlowPrior& base = net.base();
  torch::manual_seed(2);
  const int64_t B = 3, T = 30;
  auto x = torch::randn({B, T, 22, 3});
  auto t = torch::rand({B});
  auto mask = torch::ones({B, T}, torch::kBool);
  mask[2].narrow(0, 20, 10).fill_(false);
  auto cmask = (torch::rand({B, T, 22, 3}) < 0.2).to(torch::kFloat32);
  auto signal = control_signal(torch::randn({B, T, 22, 3}), cmask);
  auto text = base.encode_texts({"a person walks", "a person jumps", "forward"});
  torch::NoGradGuard ng;
  auto vb = base.raw_velocity(x, t, text, mask);
  auto vc = net.raw_velocity(x, t, text, mask, signal);
  REQUIRE(vb.abs().max().item<double>() > 1e-3);  // a real (non-zero) base velocity
  auto valid = mask.view({B, T, 1, 1}).expand_as(vb);
  CHECK(torch::equal(vb.masked_select(valid), vc.masked_select(valid)));
  // Guided: with v_ctrl = v_text the control term vanishes and text CFG is the base's.
  auto g = net.velocity(x, t, text, mask, signal, 2.5, 1.75);
  auto gb = base.velocity(x, t, text, mask, 2.5);
  INFO("max |guided - base guided| " << (g - gb).masked_select(valid).abs().max().item<double>() << ", max |v| "
                                      << gb.abs().max().item<double>());
  CHECK(torch::allclose(g.masked_select(valid), gb.masked_select(valid), 1e-4, 1e-5));
  // The copied blocks start as the base's.
  auto& tr = *base.net()->transformer;
  for (size_t i = 0; i < tr.blocks->size(); ++i) {
    auto src = tr.blocks[i]->named_parameters(true);
    for (auto& kv : net.branch()->blocks[i]->named_parameters(true)) CHECK(torch::equal(kv.value(), src[kv.key()]));
  }
  // Control signal layout: targets x mask, then the mask.
  auto tgt = torch::full({1, 1, 22, 3}, 2.0f);
  auto m = torch::zeros({1, 1, 22, 3});
  m[0][0][5][1] = 1;
  auto s = control_signal(tgt, m);
  REQUIRE(s.size(3) == 6);
  CHECK(s.sum().item<double>() == Approx(3.0));
  CHECK(s[0][0][5][1].item<double>() == 2.0);
  CHECK(s[0][0][5][4].item<double>() == 1.0);
}

TEST_CASE("ControlNet training masks: one listed joint, 1..length frames, valid frames only", "[controlnet]") {
  auto gen = at::make_generator<at::CPUGeneratorImpl>(9);
  std::vector<int64_t> lengths = {40, 12, 1, 25, 33, 7, 40, 40};
  std::vector<int> joints = {0, 10, 11, 15, 20, 21};
  std::set<int64_t> counts;
  for (int rep = 0; rep < 20; ++rep) {
    auto m = random_control_mask(lengths, 40, 22, joints, 1, gen);
    for (size_t b = 0; b < lengths.size(); ++b) {
      torch::Tensor per_joint = m[static_cast<int64_t>(b)].sum(std::vector<int64_t>{0, 2});  // [J]
      auto nz = per_joint.nonzero();
      REQUIRE(nz.size(0) == 1);
      const int j = static_cast<int>(nz[0][0].item().toLong());
      CHECK(std::find(joints.begin(), joints.end(), j) != joints.end());
      auto frames = m[b].select(1, j).sum(1);  // [T] in {0, 3}
      int64_t k = (frames > 0).sum().item<int64_t>();
      CHECK(k >= 1);
      CHECK(k <= lengths[b]);
      CHECK(frames.narrow(0, lengths[b], 40 - lengths[b]).sum().item<double>() == 0.0);
      CHECK(((frames == 0) | (frames == 3)).all().item<bool>());
      if (lengths[b] == 40) counts.insert(k);
    }
  }
  // Densities vary: sparse keyframes and dense trajectories both occur.
  CHECK(*counts.begin() <= 3);
  CHECK(*counts.rbegin() >= 20);
  // Same generator seed, same masks.
  auto g1 = at::make_generator<at::CPUGeneratorImpl>(4), g2 = at::make_generator<at::CPUGeneratorImpl>(4);
  CHECK(torch::equal(random_control_mask(lengths, 40, 22, joints, 1, g1),
                     random_control_mask(lengths, 40, 22, joints, 1, g2)));
}

TEST_CASE("ControlNet trainer: base frozen, branch learns, losses finite", "[controlnet]") {
  TempDir dir("cn_train");
  write_random_prior_run(dir.path / "base", 40, "flow_prior", kPriorWordsWithNumbers);
  auto data = std::make_shared<MotionDataset>(random_set({40, 30, 36, 40, 22, 40, 28, 35}, 3), "random");
  TrainJobConfig job;
  parse_config(config_from_string(fmt::format("model:\n  type: flow_controlnet\n  base:\n    run_dir: {}\n",
                                              (dir.path / "base").string())),
               job);
  TrainContext ctx{data, torch::kCPU, &job, 0};
  auto tr = make_trainable(job.model, ctx);
  FlowPrior base_copy = FlowPrior::load((dir.path / "base").string());
  const FlowControlNet* cn = controlnet_of(*tr);
  REQUIRE(cn != nullptr);
  auto base_params = cn->base().net()->parameters();
  std::vector<torch::Tensor> before;
  for (auto& p : base_params) before.push_back(p.detach().clone());
  auto params = tr->trainable_parameters();
  // Only the branch is optimised (copied blocks + zero linears + signal embedding).
  REQUIRE(params.size() == cn->branch()->parameters().size());
  for (auto& p : params)
    for (auto& q : base_params) CHECK_FALSE(p.is_same(q));
  for (auto& p : base_params) CHECK_FALSE(p.requires_grad());
  torch::optim::AdamW opt(params, torch::optim::AdamWOptions(1e-2));
  torch::manual_seed(1);
  for (int s = 0; s < 4; ++s) {
    LossOutput out = tr->loss({0, 1, 2, 4, 5, 6});
    REQUIRE(std::isfinite(out.loss.item<double>()));
    REQUIRE(out.parts.size() == 2);
    opt.zero_grad();
    out.loss.backward();
    opt.step();
  }
  // The branch can fit: on one fixed batch (same noise, t and control masks) the
  // control loss falls well below the zero-initialised branch's.
  auto fixed_loss = [&] {
    torch::manual_seed(77);
    return tr->loss({0, 1, 2, 4});
  };
  double ctrl0 = 0;
  for (auto& [k, v] : fixed_loss().parts)
    if (k == "ctrl") ctrl0 = v.item<double>();
  double ctrl1 = 0;
  for (int s = 0; s < 25; ++s) {
    LossOutput out = fixed_loss();
    for (auto& [k, v] : out.parts)
      if (k == "ctrl") ctrl1 = v.item<double>();
    opt.zero_grad();
    out.loss.backward();
    opt.step();
  }
  INFO("control loss on a fixed batch: " << ctrl0 << " -> " << ctrl1);
  CHECK(ctrl1 < 0.5 * ctrl0);
  for (size_t i = 0; i < base_params.size(); ++i) CHECK(torch::equal(base_params[i], before[i]));
  auto& bz = cn->branch()->zero_out;
  double moved = 0;
  for (auto& z : *bz) moved += z->as<torch::nn::Linear>()->weight.abs().sum().item<double>();
  CHECK(moved > 0);
  // After training steps the control signal changes the velocity.
  torch::NoGradGuard ng;
  auto x = torch::randn({1, 40, 22, 3});
  auto t = torch::full({1}, 0.5);
  auto mask = torch::ones({1, 40}, torch::kBool);
  auto text = base_copy.encode_texts({"a person walks"});
  auto sig = control_signal(torch::randn({1, 40, 22, 3}), torch::ones({1, 40, 22, 3}));
  auto v_ctrl = cn->raw_velocity(x, t, text, mask, sig);
  auto v_base = base_copy.raw_velocity(x, t, text, mask);
  CHECK((v_ctrl - v_base).abs().max().item<double>() > 1e-6);
  // ACMDM's three passes, all through base + branch: "no control" is the branch
  // with its signal switched off, which after training differs from the base.
  auto null_text = base_copy.null_texts(1);
  auto v_nc = cn->raw_velocity(x, t, null_text, mask, sig);
  auto v_t0 = cn->raw_velocity(x, t, text, mask, sig, torch::zeros({1}));
  CHECK((v_t0 - v_base).abs().max().item<double>() > 1e-6);
  auto guided = cn->velocity(x, t, text, mask, sig, 2.5, 1.75);
  auto expected = v_ctrl + 1.5 * (v_ctrl - v_nc) + 0.75 * (v_ctrl - v_t0);
  INFO("max |guided - expected| " << (guided - expected).abs().max().item<double>());
  CHECK(torch::allclose(guided, expected, 1e-4, 1e-5));
  CHECK(torch::allclose(cn->velocity(x, t, text, mask, sig, 1.0, 1.0), v_ctrl, 1e-4, 1e-5));
  auto ev = tr->evaluate();
  CHECK(std::isfinite(ev["val_fm"]));
  CHECK(std::isfinite(ev["val_ctrl"]));
}

TEST_CASE("ControlNet control loss: on the clean estimate x0 + v, it does not vanish near t = 1", "[controlnet]") {
  TempDir dir("cn_loss_t");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers);
  FlowControlNet net = FlowControlNet::around(FlowPrior::load(dir.path.string()));
  torch::manual_seed(3);
  const int64_t B = 4, T = 30;
  auto x1 = torch::randn({B, T, 22, 3});
  auto x0 = torch::randn({B, T, 22, 3});
  auto mask = torch::ones({B, T}, torch::kBool);
  mask[1].narrow(0, 24, 6).fill_(false);
  x1 = x1 * mask.view({B, T, 1, 1}).to(torch::kFloat32);
  auto cmask = (torch::rand({B, T, 22, 3}) < 0.1).to(torch::kFloat32);
  auto text = net.base().encode_texts({"a person walks", "a person jumps", "forward", "a person walks forward"});
  torch::NoGradGuard ng;
  auto ctrl = [&](double tv, const std::string& weighting) {
    auto t = torch::full({B}, tv);
    return controlnet_losses(net, x1, x0, t, text, mask, cmask, {}, weighting).ctrl.item<double>();
  };
  const double new_99 = ctrl(0.99, "none"), new_50 = ctrl(0.5, "none");
  const double old_99 = ctrl(0.99, "one_minus_t_sq"), old_50 = ctrl(0.5, "one_minus_t_sq");
  INFO("unweighted " << new_50 << " -> " << new_99 << ", (1-t)^2-weighted " << old_50 << " -> " << old_99);
  CHECK(old_99 < old_50 / 1000);  // the old loss shrinks ~2500x from t = 0.5 to 0.99
  CHECK(new_99 > 0.2 * new_50);   // the new one keeps its scale
  // Same velocity, so the two differ by exactly (1 - t)^2.
  CHECK(old_99 == Approx(0.01 * 0.01 * new_99).epsilon(1e-3));
  CHECK(old_50 == Approx(0.25 * new_50).epsilon(1e-4));
  // The unweighted loss is the mean of (x0 + v - x1)^2 over the controlled valid entries.
  auto t = torch::full({B}, 0.99);
  auto cm = cmask * mask.view({B, T, 1, 1}).to(torch::kFloat32);
  auto xt = 0.99 * x1 + 0.01 * x0;
  auto v = net.raw_velocity(xt, t, text, mask, control_signal(x1, cm));
  CHECK(new_99 == Approx(((x0 + v - x1).pow(2) * cm).sum().item<double>() / cm.sum().item<double>()).epsilon(1e-4));
  // Samples whose control is switched off do not count.
  auto on = torch::tensor({1.0f, 0.0f, 1.0f, 1.0f});
  auto part = controlnet_losses(net, x1, x0, t, text, mask, cmask, on, "none").ctrl.item<double>();
  auto cm_on = cm * on.view({B, 1, 1, 1});
  auto v_on = net.raw_velocity(xt, t, text, mask, control_signal(x1, cm), on);
  CHECK(part ==
        Approx(((x0 + v_on - x1).pow(2) * cm_on).sum().item<double>() / cm_on.sum().item<double>()).epsilon(1e-4));
  // ctrl_every counts them (the validation's "control off" error), from the same call.
  auto every = controlnet_losses(net, x1, x0, t, text, mask, cmask, on, "none").ctrl_every.item<double>();
  CHECK(every == Approx(((x0 + v_on - x1).pow(2) * cm).sum().item<double>() / cm.sum().item<double>()).epsilon(1e-4));
}

TEST_CASE("ControlNet losses on a clean-endpoint base: the base's velocity error with its clean_eps floor",
          "[controlnet][kinematic]") {
  // With the kinematic head and without: both state the clean endpoint.
  for (const std::string extra : {std::string("  prediction: clean\n"),
                                  std::string("  prediction: clean\n  kinematic_head:\n    enabled: true\n")}) {
    INFO(extra);
    TempDir dir("cn_loss_clean");
    write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers, extra);
    FlowControlNet net = FlowControlNet::around(FlowPrior::load(dir.path.string()));
    const double eps = net.base().config().clean_eps;
    REQUIRE(eps == 0.05);
    torch::manual_seed(4);
    const int64_t B = 3, T = 24;
    auto x1 = torch::randn({B, T, 22, 3});
    auto x0 = torch::randn({B, T, 22, 3});
    auto mask = torch::ones({B, T}, torch::kBool);
    mask[2].narrow(0, 18, 6).fill_(false);
    x1 = x1 * mask.view({B, T, 1, 1}).to(torch::kFloat32);
    auto cmask = (torch::rand({B, T, 22, 3}) < 0.2).to(torch::kFloat32);
    auto text = net.base().encode_texts({"a person walks", "a person jumps", "forward"});
    auto valid = mask.view({B, T, 1, 1}).to(torch::kFloat32);
    auto cm = cmask * valid;
    torch::NoGradGuard ng;
    for (const double tv : {0.3, 0.97, 1.0 - 1e-7}) {
      INFO("t = " << tv);
      auto t = torch::full({B}, tv);
      auto xt = tv * x1 + (1 - tv) * x0;
      // The branch's clean endpoint, and the same read off its velocity where 1 - t >= 1e-6.
      auto x1_hat = net.raw_clean(xt, t, text, mask, control_signal(x1, cm));
      if (1 - tv >= 1e-6)
        CHECK(torch::allclose(xt + (1 - tv) * net.raw_velocity(xt, t, text, mask, control_signal(x1, cm)), x1_hat,
                              1e-3, 1e-4));
      auto v_err = (x1_hat - x1) / std::max(1 - tv, eps);
      const double fm = (v_err.pow(2) * valid).sum().item<double>() / (valid.sum().item<double>() * 66);
      const double ctrl = (v_err.pow(2) * cm).sum().item<double>() / cm.sum().item<double>();
      auto l = controlnet_losses(net, x1, x0, t, text, mask, cmask, {}, "none");
      CHECK(l.fm.item<double>() == Approx(fm).epsilon(1e-3));
      CHECK(l.ctrl.item<double>() == Approx(ctrl).epsilon(1e-3));
      // (1 - t)^2 weighting: the clean endpoint's own error.
      const double ctrl_sq = ((x1_hat - x1).pow(2) * cm).sum().item<double>() / cm.sum().item<double>();
      CHECK(controlnet_losses(net, x1, x0, t, text, mask, cmask, {}, "one_minus_t_sq").ctrl.item<double>() ==
            Approx(ctrl_sq).epsilon(1e-3));
    }
    // Bounded at t -> 1: at most 1 / eps^2 = 400 times the clean error, where the raw
    // velocity error (x0 + v - x1, no floor) would be 10^14 times it.
    auto t1 = torch::full({B}, 1.0 - 1e-7);
    const double near_one = controlnet_losses(net, x1, x0, t1, text, mask, cmask, {}, "none").fm.item<double>();
    const double mid = controlnet_losses(net, x1, x0, torch::full({B}, 1.0 - eps), text, mask, cmask, {}, "none")
                           .fm.item<double>();
    CHECK(std::isfinite(near_one));
    CHECK(near_one < 10 * mid);
  }
}

TEST_CASE("ControlNet residual head: adds on the velocity of a velocity base, on the clean estimate of a clean one",
          "[controlnet]") {
  for (const std::string extra : {std::string(), std::string("  prediction: clean\n")}) {
    INFO("base: " << (extra.empty() ? "velocity" : "clean"));
    TempDir dir("cn_residual");
    write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers, extra);
    FlowControlNet net = FlowControlNet::around(FlowPrior::load(dir.path.string()), false, true);
    const bool clean = net.base().net()->clean_prediction;
    REQUIRE(clean == !extra.empty());
    torch::manual_seed(5);
    const int64_t B = 2, T = 20;
    auto x = torch::randn({B, T, 22, 3});
    auto t = torch::tensor({0.3f, 0.8f});
    auto mask = torch::ones({B, T}, torch::kBool);
    auto signal = control_signal(torch::randn({B, T, 22, 3}), (torch::rand({B, T, 22, 3}) < 0.2).to(torch::kFloat32));
    auto text = net.base().encode_texts({"a person walks", "a person jumps"});
    torch::NoGradGuard ng;
    auto v0 = net.raw_velocity(x, t, text, mask, signal), c0 = net.raw_clean(x, t, text, mask, signal);
    // A residual that is the same r on every frame: its weight zero, its bias r.
    auto r = torch::randn({22 * 3});
    net.branch()->residual_out->bias.copy_(r);
    auto v1 = net.raw_velocity(x, t, text, mask, signal), c1 = net.raw_clean(x, t, text, mask, signal);
    auto rr = r.view({1, 1, 22, 3});
    auto gap = (1 - t).view({B, 1, 1, 1});
    if (clean) {
      CHECK(torch::allclose(c1 - c0, rr.expand_as(c0), 1e-4, 1e-5));
      CHECK(torch::allclose(v1 - v0, (rr / gap).expand_as(v0), 1e-3, 1e-4));
    } else {
      CHECK(torch::allclose(v1 - v0, rr.expand_as(v0), 1e-4, 1e-5));
      CHECK(torch::allclose(c1 - c0, (rr * gap).expand_as(c0), 1e-4, 1e-5));
    }
  }
}

TEST_CASE("ControlNet model.signal switches: saved with the run and rebuilt by load", "[controlnet]") {
  TempDir t("cn_signal_meta");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40 "
                                    "fixture.max_frames=48 fixture.t_max=48",
                                    data))
              .exit_code == 0);
  const std::string base_ov =
      fmt::format("[optim.steps=4, optim.batch_size=8, optim.warmup=1, data.path={}, run.root={}, run.name=base, "
                  "run.threads=1, run.log_every=4, run.checkpoint_every=4]",
                  data, t.path.string());
  TrainResult r = run_train("configs/prior/flow_controlnet_tiny.yaml",
                            {"model.base.overrides=" + base_ov, "optim.steps=4", "optim.batch_size=8",
                             "optim.warmup=1", "data.path=" + data, "run.root=" + t.path.string(), "run.name=cn",
                             "run.threads=1", "run.log_every=4", "run.checkpoint_every=4",
                             "model.signal.norm=true", "model.signal.residual_head=true"});
  const std::string meta = slurp(r.run_dir / "outputs" / "controlnet_meta.yaml");
  CHECK(meta.find("signal_norm: true") != std::string::npos);
  CHECK(meta.find("residual_head: true") != std::string::npos);
  FlowControlNet net = FlowControlNet::load(r.run_dir.string());
  REQUIRE(net.branch()->signal_gain.defined());
  REQUIRE(!net.branch()->residual_out.is_empty());
  // Trained: the residual head moved off zero and came back from final.pt.
  CHECK(net.branch()->residual_out->weight.abs().max().item<double>() > 0);
}

TEST_CASE("ControlNet pelvis-only model: configs and training masks control joint 0 alone", "[controlnet]") {
  for (const char* f : {"configs/prior/flow_controlnet_pelvis_tiny.yaml",
                        "configs/prior/flow_controlnet_pelvis_standard.yaml",
                        "configs/prior/flow_controlnet_pelvis_paper.yaml"}) {
    INFO(f);
    auto job = load_job<TrainJobConfig>(f, {});
    REQUIRE(job.model.type == "flow_controlnet");
    CHECK(job.model.as<FlowControlNetConfig>().control_joints == std::vector<int>{0});
  }
  // Table 1's pelvis row uses the pelvis model; the all-joints and editing rows do not.
  YAML::Node gen = YAML::LoadFile(resolve_data_path("experiments/generators/flow_controlnet_pelvis.yaml"));
  CHECK(gen["generator"]["controlnet"]["config"].as<std::string>() ==
        "configs/prior/flow_controlnet_pelvis_tiny.yaml");
  YAML::Node table = YAML::LoadFile(resolve_data_path("experiments/projflow/table1.yaml"));
  int rows = 0;
  for (const auto& row : table["rows"]) {
    const std::string id = row["id"].as<std::string>(), g = row["generator"].as<std::string>();
    if (id.find("controlnet") == std::string::npos) continue;
    ++rows;
    INFO(id);
    CHECK((g == "experiments/generators/flow_controlnet_pelvis.yaml") == (id.rfind("pelvis/", 0) == 0));
  }
  CHECK(rows == 3);

  auto gen_rng = at::make_generator<at::CPUGeneratorImpl>(21);
  std::vector<int64_t> lengths = {40, 9, 1, 33, 40};
  for (int rep = 0; rep < 10; ++rep) {
    auto m = random_control_mask(lengths, 40, 22, {0}, 1, gen_rng);
    CHECK(m.narrow(2, 1, 21).sum().item<double>() == 0.0);  // no other joint
    for (size_t b = 0; b < lengths.size(); ++b) {
      auto pelvis = m[static_cast<int64_t>(b)].select(1, 0);  // [T, 3]
      auto frames = pelvis.sum(1);
      CHECK((frames > 0).sum().item<int64_t>() >= 1);
      CHECK(((frames == 0) | (frames == 3)).all().item<bool>());  // all three axes
      CHECK(frames.narrow(0, lengths[b], 40 - lengths[b]).sum().item<double>() == 0.0);
    }
  }
}

TEST_CASE("ControlNet training: a short real run lowers the validation control loss below step 0's",
          "[controlnet]") {
  // The tiny config as the table replay trains it (EMA, schedule, control dropout) on a
  // fixture of short clips, against the same job's zero-initialised branch: evaluate()
  // draws noise, t and control masks from a constant seed, so the two are paired.
  TempDir t("cn_learns");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=80 "
                                    "fixture.max_frames=48 fixture.t_max=48",
                                    data))
              .exit_code == 0);
  const std::string base_ov =
      fmt::format("[optim.steps=60, optim.batch_size=16, optim.warmup=10, data.path={}, run.root={}, run.name=base, "
                  "run.threads=1, run.log_every=20, run.checkpoint_every=60]",
                  data, t.path.string());
  const std::vector<std::string> ov = {"model.base.overrides=" + base_ov, "optim.steps=120", "data.path=" + data,
                                       "run.root=" + t.path.string(), "run.name=cn", "run.threads=1",
                                       "run.log_every=20", "run.checkpoint_every=120"};
  TrainResult r = run_train("configs/prior/flow_controlnet_tiny.yaml", ov);
  auto job = load_job<TrainJobConfig>("configs/prior/flow_controlnet_tiny.yaml", ov);
  TrainContext ctx{MotionDataset::load(data), torch::kCPU, &job, 0};
  resolve_dependencies(job.model, nullptr);  // as train() does: the base, found
  auto step0 = make_trainable(job.model, ctx)->evaluate();
  INFO("val_ctrl " << step0["val_ctrl"] << " -> " << r.summary["val_ctrl"] << "; val_fm " << step0["val_fm"] << " -> "
                   << r.summary["val_fm"]);
  CHECK(r.summary["val_ctrl"] < 0.9 * step0["val_ctrl"]);
  // The zero-initialised branch is the base with the control on or off; the trained one
  // is closer to the targets with its signal than without it.
  CHECK(step0["val_ctrl_off"] == Approx(step0["val_ctrl"]).epsilon(1e-5));
  INFO("trained: val_ctrl " << r.summary["val_ctrl"] << ", with the control off " << r.summary["val_ctrl_off"]);
  CHECK(r.summary["val_ctrl"] < r.summary["val_ctrl_off"]);
  // It falls faster than the flow loss: the branch uses the signal, not just its extra capacity.
  CHECK(r.summary["val_ctrl"] / step0["val_ctrl"] < r.summary["val_fm"] / step0["val_fm"]);
}

TEST_CASE("ControlNet control targets: joint-position selections only (keyframe, trajectory, upper-body edit)", "[controlnet]") {
  TempDir dir("cn_targets");
  write_random_prior_run(dir.path, 40, "flow_prior", kPriorWordsWithNumbers);
  FlowPrior base = FlowPrior::load(dir.path.string());
  std::vector<ControlTask> tasks = {
      make_task("k", 20, "- {type: keyframe, joints: [0, l_wrist], frames: [3, 9], axes: xz, from_source: true}\n", 1),
      make_task("t", 16, "- {type: trajectory, joints: [head], values: [[1.0, 2.0, 3.0]], frames: [4]}\n", 2),
  };
  ControlTargets ct = control_targets(base, tasks, 24);
  REQUIRE(ct.target.sizes() == torch::IntArrayRef({2, 24, 22, 3}));
  CHECK(ct.mask[0].sum().item<double>() == 8);  // 2 joints x 2 frames x 2 axes
  CHECK(ct.mask[1].sum().item<double>() == 3);
  // Targets are the base-normalised world values: (y - mean) / std.
  const float* src = tasks[0].source.data() + (9 * 22 + 20) * 3;
  CHECK(ct.target[0][9][20][2].item<double>() == Approx((src[2] - 0.1) / 0.8).epsilon(1e-5));
  CHECK(ct.mask[0][9][20][1].item<double>() == 0.0);
  CHECK(ct.target[1][4][15][1].item<double>() == Approx((2.0 - 0.9) / 0.4).epsilon(1e-5));

  std::vector<ControlTask> bad = {make_task(
      "cam", 10,
      "- {type: keyframe, joints: [0], frames: [1], from_source: true}\n"
      "- {type: camera_2d, name: side view, joints: [15], camera: {scale: 1.0, yaw_deg: 30}, from_source: true}\n",
      3)};
  std::string e = user_error_of([&] { control_targets(base, bad, 10); });
  INFO(e);
  CHECK(e.find("task 'cam'") != std::string::npos);
  CHECK(e.find("item 1 'side view' (camera_2d)") != std::string::npos);
  CHECK(e.find("only takes joint positions") != std::string::npos);

  // Upper-body editing fixes the lower body's joint positions: the ControlNet takes it.
  std::vector<ControlTask> edit = {make_task("edit", 10, "- {type: upper_body_edit}\n", 4)};
  ControlTargets et = control_targets(base, edit, 10);
  CHECK(et.mask[0].narrow(1, 10, 1).sum().item<double>() == 30);  // l_foot: every frame, x/y/z
  CHECK(et.mask[0].narrow(1, 15, 1).sum().item<double>() == 0);   // the head is free
}

TEST_CASE("ControlNet end to end: flow_tiny base on demand, train, sample through the generator",
          "[controlnet][slow]") {
  TempDir t("cn_e2e");
  std::string data = (t.path / "fx.h5").string();
  auto fx = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40", data));
  REQUIRE(fx.exit_code == 0);
  std::string base_ov = fmt::format("[optim.steps=20, optim.batch_size=8, optim.warmup=5, data.path={}, run.root={}, "
                                    "run.name=base, run.threads=1, run.log_every=10, run.checkpoint_every=20]",
                                    data, t.path.string());
  TrainResult r = run_train(
      "configs/prior/flow_controlnet_tiny.yaml",
      {"model.base.overrides=" + base_ov, "optim.steps=24", "optim.batch_size=8", "optim.warmup=4",
       "data.path=" + data, "run.root=" + t.path.string(), "run.name=cn", "run.threads=1", "run.log_every=8",
       "run.checkpoint_every=24"});
  fs::path cn_dir = t.path / "prior" / "cn";
  REQUIRE(r.run_dir == cn_dir);
  CHECK(fs::exists(t.path / "prior" / "base" / "DONE"));
  for (auto f : {"checkpoints/final.pt", "outputs/controlnet_meta.yaml", "DONE"}) CHECK(fs::exists(cn_dir / f));
  CHECK(std::isfinite(r.summary["val_ctrl"]));
  CHECK(std::isfinite(r.summary["val_fm"]));

  // Same config with the base already trained: the same branch (training the base on
  // demand must not disturb the ControlNet's RNG stream).
  TrainResult r2 = run_train(
      "configs/prior/flow_controlnet_tiny.yaml",
      {"model.base.overrides=" + base_ov, "optim.steps=24", "optim.batch_size=8", "optim.warmup=4",
       "data.path=" + data, "run.root=" + t.path.string(), "run.name=cn2", "run.threads=1", "run.log_every=8",
       "run.checkpoint_every=24"});
  {
    FlowControlNet a = FlowControlNet::load(cn_dir.string()), b = FlowControlNet::load(r2.run_dir.string());
    auto pa = a.branch()->parameters(), pb = b.branch()->parameters();
    REQUIRE(pa.size() == pb.size());
    for (size_t i = 0; i < pa.size(); ++i) CHECK(torch::equal(pa[i], pb[i]));
  }

  GeneratorFile job;
  parse_config(config_from_string(fmt::format("generator:\n  type: flow_controlnet\n  controlnet:\n    run_dir: {}\n"
                                              "  steps: 10\n",
                                              cn_dir.string())),
               job);
  auto gen = build_generator(job.generator);
  CHECK(gen->describe().find("ControlNet") != std::string::npos);
  std::vector<ControlTask> tasks = {
      make_task("a", 60, "- {type: trajectory, joints: [pelvis], from_source: true}\n", 5),
      make_task("b", 45, "- {type: keyframe, joints: [l_wrist, r_foot], frames: [0, 20, 44], from_source: true}\n",
                6),
  };
  GeneratedMotions g = gen->generate(tasks, 4);
  CHECK(g.world.sizes() == torch::IntArrayRef({2, 60, 22, 3}));
  CHECK(g.lengths == std::vector<int>{60, 45});
  CHECK(torch::isfinite(g.world).all().item<bool>());
  CHECK(g.world[1].narrow(0, 45, 15).abs().sum().item<double>() == 0.0);
  GeneratedMotions again = gen->generate(tasks, 4);
  CHECK(torch::equal(g.world, again.world));
  tasks[1].spec = parse_constraint_spec_yaml("- {type: planar_root, name: route, from_source: true}\n", "b.yaml");
  std::string e = user_error_of([&] { gen->generate(tasks, 4); });
  CHECK(e.find("item 0 'route' (planar_root)") != std::string::npos);
  CHECK(e.find("only takes joint positions") != std::string::npos);
}
