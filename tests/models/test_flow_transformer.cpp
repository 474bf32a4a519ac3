// Flow transformer and prior trainer: shapes, padding invariance, zero-init,
// RoPE's relative-position property, and one training step at the paper's S size.
#include <catch2/catch.hpp>

#include "../data/data_test_util.h"
#include "cli/jobs.h"
#include "core/error.h"
#include "data/normalizer.h"
#include "data/text_vocab.h"
#include "models/flow_prior.h"
#include "models/flow_transformer.h"
#include "train/trainer.h"
#include "trainer_test_util.h"

using namespace mc;

namespace {

FlowTransformerOptions tiny_options() {
  FlowTransformerOptions o;
  o.depth = 2;
  o.width = 64;
  o.heads = 2;
  o.cond_dim = 32;
  o.freq_dim = 32;
  return o;
}

// Zero-initialised modulations make the network ignore its input; random weights
// everywhere make the invariance tests mean something.
void randomize(torch::nn::Module& m, double std = 0.1) {
  torch::NoGradGuard ng;
  for (auto& p : m.parameters()) p.normal_(0.0, std);
}

}  // namespace

TEST_CASE("flow transformer: zero-initialised output, shapes", "[flow]") {
  torch::manual_seed(1);
  FlowTransformer net(tiny_options());
  auto x = torch::randn({3, 12, 22, 3});
  auto mask = torch::ones({3, 12}, torch::kBool);
  auto v = net->forward(x, torch::rand({3}), torch::randn({3, 32}), mask).velocity;
  CHECK(v.sizes().vec() == x.sizes().vec());
  CHECK(v.abs().max().item<double>() == 0.0);  // AdaLN-Zero + zero head
  randomize(*net);
  v = net->forward(x, torch::rand({3}), torch::randn({3, 32}), mask).velocity;
  CHECK(v.abs().max().item<double>() > 1e-3);
  CHECK(torch::isfinite(v).all().item<bool>());
}

TEST_CASE("flow transformer: valid-frame outputs ignore padded frames", "[flow]") {
  auto o = tiny_options();
  o.temporal_kernel = GENERATE(1, 3);  // per-frame Linear, and a temporal kernel that must not read padding
  INFO("temporal_kernel " << o.temporal_kernel);
  torch::manual_seed(2);
  FlowTransformer net(o);
  randomize(*net);
  net->eval();
  const int64_t T = 16;
  auto x = torch::randn({2, T, 22, 3});
  auto mask = torch::ones({2, T}, torch::kBool);
  mask[0].narrow(0, 9, T - 9).fill_(false);  // sample 0 has 9 valid frames
  auto t = torch::tensor({0.3f, 0.8f});
  auto c = torch::randn({2, 32});
  auto v1 = net->forward(x, t, c, mask).velocity;
  auto x2 = x.clone();
  x2[0].narrow(0, 9, T - 9).normal_(0.0, 10.0);  // garbage in the padding
  auto v2 = net->forward(x2, t, c, mask).velocity;
  CHECK(torch::allclose(v1[0].narrow(0, 0, 9), v2[0].narrow(0, 0, 9), 1e-5, 1e-5));
  CHECK(torch::allclose(v1[1], v2[1]));
  // A shorter padded tensor gives the same valid outputs too.
  auto v3 = net->forward(x.narrow(1, 0, 9).narrow(0, 0, 1), t.narrow(0, 0, 1), c.narrow(0, 0, 1),
                         torch::ones({1, 9}, torch::kBool))
                .velocity;
  CHECK(torch::allclose(v1[0].narrow(0, 0, 9), v3[0], 1e-4, 1e-5));
  // Without the mask the padding leaks in: the test can see a leak.
  auto v4 = net->forward(x2, t, c, torch::ones({2, T}, torch::kBool)).velocity;
  CHECK_FALSE(torch::allclose(v1[0].narrow(0, 0, 9), v4[0].narrow(0, 0, 9), 1e-5, 1e-5));
}

TEST_CASE("RoPE: attention scores depend only on relative positions", "[flow]") {
  torch::manual_seed(3);
  auto o = tiny_options();
  FlowAttention attn(o);
  randomize(*attn, 0.2);
  auto x = torch::randn({2, 10, o.width});
  auto pos = torch::arange(10, torch::kFloat32);
  auto s0 = attn->scores(x, pos);
  auto s1 = attn->scores(x, pos + 37.0);
  CHECK(torch::allclose(s0, s1, 1e-4, 1e-4));
  // ... but they do depend on positions (not a no-op).
  auto s2 = attn->scores(x, pos * 2.0);
  CHECK_FALSE(torch::allclose(s0, s2, 1e-3, 1e-3));
  // The rotation itself preserves norms.
  auto q = torch::randn({4, 10, 32});
  CHECK(torch::allclose(apply_rope(q, pos).norm(2, -1), q.norm(2, -1), 1e-5, 1e-5));
}

TEST_CASE("RMSNorm: unit root-mean-square, learnable scale", "[flow]") {
  RMSNorm n(16);
  auto y = n->forward(torch::randn({5, 16}) * 7.0);
  CHECK(torch::allclose(y.pow(2).mean(-1), torch::ones({5}), 1e-3, 1e-3));
  RMSNorm plain(16, false);
  CHECK(plain->parameters().empty());
}

TEST_CASE("flow prior: the S config builds and runs one training step", "[flow]") {
  auto job = load_job<TrainJobConfig>(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/prior/flow_s.yaml", {});
  REQUIRE(job.model.type == "flow_prior");
  auto& cfg = job.model.as<FlowPriorConfig>();
  auto o = cfg.transformer_options(22);
  CHECK(o.depth == 8);
  CHECK(o.width == 512);
  CHECK(o.heads == 8);
  CHECK(job.optim.lr == Approx(2e-4));
  CHECK(job.optim.batch_size == 64);
  CHECK(job.optim.warmup == 2000);
  CHECK(job.optim.ema_decay == Approx(0.9999));
  REQUIRE(job.optim.decay_at == std::vector<int>{50000});

  MotionSet set = test::random_motion_set({24, 17, 30}, {"train", "val"});
  set.stats = compute_norm_stats(set);
  set.vocab = TextVocab::build(set).words();
  auto data = std::make_shared<MotionDataset>(set, "<memory>");
  torch::manual_seed(4);
  TrainContext ctx{data, torch::kCPU, &job, 0};
  auto tr = make_trainable(job.model, ctx);
  int64_t n = 0;
  for (auto& p : tr->trainable_parameters()) n += p.numel();
  CHECK(n > 20'000'000);  // 8 blocks of ~4.8M (attention 1.0M, SwiGLU 2.2M, AdaLN 1.6M) plus the text encoder
  auto out = tr->loss({0, 1});
  REQUIRE(std::isfinite(out.loss.item<double>()));
  out.loss.backward();
  double gsq = 0;
  for (auto& p : tr->trainable_parameters())
    if (p.grad().defined()) {
      REQUIRE(torch::isfinite(p.grad()).all().item<bool>());
      gsq += p.grad().pow(2).sum().item<double>();
    }
  CHECK(gsq > 0);
  // Validation flow loss at fixed t is deterministic.
  tr->module().eval();
  auto e1 = tr->evaluate(), e2 = tr->evaluate();
  CHECK(e1.at("val_fm") == e2.at("val_fm"));
  CHECK(e1.count("val_fm_t0.50") == 1);
}

namespace {
// A tiny flow prior trainer on random clips of 12, 30, 17 and 9 frames.
std::unique_ptr<Trainable> tiny_flow_trainer(TrainJobConfig& job, const std::string& extra, bool trim,
                                             std::shared_ptr<MotionDataset>* data_out = nullptr) {
  return test::trainer_on_random_clips(job,
                                       "model:\n  type: flow_prior\n  depth: 2\n  width: 32\n  heads: 2\n"
                                       "  text_width: 16\n  text_heads: 2\n  text_ff: 32\n  text_layers: 1\n" +
                                           extra,
                                       {12, 30, 17, 9}, trim, data_out);
}
}  // namespace

TEST_CASE("flow prior: batches trimmed to their longest clip, FLOPs count valid frames only",
          "[flow]") {
  TrainJobConfig a, b;
  std::shared_ptr<MotionDataset> data;
  auto padded = tiny_flow_trainer(a, "", false, &data);
  auto trimmed = tiny_flow_trainer(b, "", true);
  test::same_random_weights({padded.get(), trimmed.get()});
  // Clips 0 and 2 (12 and 17 frames of 30): the trimmed batch has 17 frames.
  CHECK(data->batch({0, 2}, 0, 1, torch::kCPU, true).joints.size(1) == 17);
  CHECK(data->batch({0, 2}, 0, 1, torch::kCPU, false).joints.size(1) == 30);
  // The noise x0 is drawn in the batch's shape, so the two losses are different
  // draws of the same quantity; their valid-frame outputs for the same input are
  // equal (test above), and the FLOP count follows the valid frames only.
  CHECK(std::isfinite(trimmed->loss({0, 2}).loss.item<double>()));
  CHECK(padded->flops_per_step({0, 2}) == trimmed->flops_per_step({0, 2}));
  CHECK(padded->flops_per_step({0, 2}) < padded->flops_per_step({1, 2}));  // FLOPs follow valid frames
}

TEST_CASE("flow prior: clean prediction turns x1_hat into the velocity of the straight path", "[flow]") {
  TrainJobConfig job;
  auto tr = tiny_flow_trainer(job, "  prediction: clean\n  loss: velocity\n  clean_eps: 0.05\n  smooth_weight: 1.0\n", true);
  auto& net = dynamic_cast<FlowPriorNetImpl&>(tr->module());
  REQUIRE(net.clean_prediction);
  auto x = torch::randn({2, 5, 22, 3}), x1 = torch::randn({2, 5, 22, 3});
  auto t = torch::tensor({0.3f, 0.99f});
  auto mask = torch::ones({2, 5}, torch::kBool);
  auto v = net.to_velocity(x1, x, t, mask);
  // x + (1 - t) v lands on x1_hat exactly, also next to t = 1 (the sampler's last step).
  CHECK(torch::allclose(x[0] + 0.7 * v[0], x1[0], 1e-5, 1e-5));
  CHECK(torch::allclose(x[1] + 0.01 * v[1], x1[1], 1e-4, 1e-4));
  CHECK(torch::allclose(net.to_clean(x1, x, t, mask), x1));
  // Training and validation run, and report the clean-endpoint error beside the velocity error.
  auto out = tr->loss({0, 1});
  REQUIRE(std::isfinite(out.loss.item<double>()));
  out.loss.backward();
  tr->module().eval();
  auto e = tr->evaluate();
  CHECK(e.count("val_x1") == 1);
  CHECK(e.count("val_x1_t0.90") == 1);
  // A velocity network cannot be trained on the clean error (that loss is its velocity error times 1 - t).
  TrainJobConfig bad;
  CHECK_THROWS_AS(tiny_flow_trainer(bad, "  prediction: velocity\n  loss: clean\n", true), mc::UserError);
}

TEST_CASE("flow prior: the smoothness term adds the error's frame-to-frame differences", "[flow]") {
  TrainJobConfig a, b;
  auto plain = tiny_flow_trainer(a, "", true);
  auto smooth = tiny_flow_trainer(b, "  smooth_weight: 2.0\n", true);
  test::same_random_weights({plain.get(), smooth.get()});
  torch::manual_seed(9);
  double lp = plain->loss({0, 1}).loss.item<double>();
  torch::manual_seed(9);
  double ls = smooth->loss({0, 1}).loss.item<double>();
  // The error of an untrained network is mostly white: its differences have about
  // twice its variance, so the total is about (1 + 2 * 2) times the plain loss.
  CHECK(ls > 3.0 * lp);
  CHECK(ls < 6.0 * lp);
}

TEST_CASE("flow prior: the geometry loss sees bone and toe-slip errors, not common-mode or resting ones",
          "[flow]") {
  const Skeleton& sk = humanml3d_skeleton();
  const int64_t B = 3, T = 7, J = sk.num_joints();
  GeometryLossConfig g;
  g.bone_weight = 2.0;
  g.contact_weight = 5.0;
  auto valid = torch::ones({B, T, 1, 1});
  auto whole = torch::ones({B, T});
  auto ground = torch::zeros({B, T, J});           // every toe on the floor (in contact)
  auto air = torch::full({B, T, J}, 0.5);          // every toe in the air
  torch::manual_seed(3);
  for (int rep = 0; rep < 5; ++rep) {
    // A common-mode error (the same offset for every joint, changing each frame)
    // is no bone error; a constant error of every joint over time is no slip.
    auto common = torch::randn({B, T, 1, 3}).expand({B, T, J, 3}).contiguous();
    g.contact_weight = 0.0;
    CHECK(geometry_loss(g, sk, common, ground, valid, whole).item<double>() == Approx(0.0).margin(1e-10));
    g.contact_weight = 5.0;
    g.bone_weight = 0.0;
    auto still = torch::randn({B, 1, J, 3}).expand({B, T, J, 3}).contiguous();
    CHECK(geometry_loss(g, sk, still, ground, valid, whole).item<double>() == Approx(0.0).margin(1e-10));
    // A sliding toe counts on contact frames only, and only horizontally.
    auto slide = torch::zeros({B, T, J, 3});
    const int toe = sk.role("toes")[0];
    slide.select(2, toe).select(2, 0).copy_(torch::arange(T).to(torch::kFloat).expand({B, T}) * 0.1);
    const double on = geometry_loss(g, sk, slide, ground, valid, whole).item<double>();
    // 0.1 m per frame on one of the two toes: 5 * 0.01 * (T - 1 pairs of B clips) / (pairs * 2 toes).
    CHECK(on == Approx(5.0 * 0.01 / 2));
    CHECK(geometry_loss(g, sk, slide, air, valid, whole).item<double>() == Approx(0.0).margin(1e-10));
    auto lift = torch::zeros({B, T, J, 3});
    lift.select(2, toe).select(2, 1).copy_(torch::arange(T).to(torch::kFloat).expand({B, T}) * 0.1);
    CHECK(geometry_loss(g, sk, lift, ground, valid, whole).item<double>() == Approx(0.0).margin(1e-10));
    // Moving one joint alone is a bone error on each bone it ends: 1 m on a leaf joint.
    g.contact_weight = 0.0;
    g.bone_weight = 2.0;
    auto one = torch::zeros({B, T, J, 3});
    one.select(2, toe).select(2, 2).fill_(1.0);
    CHECK(geometry_loss(g, sk, one, air, valid, whole).item<double>() == Approx(2.0 / ((J - 1) * 3)));
    g.contact_weight = 5.0;
    // The floor term: a toe's height error on contact frames only, whatever its slip.
    {
      GeometryLossConfig f;
      f.floor.weight = 3.0;
      CHECK(f.enabled());
      auto sunk = torch::zeros({B, T, J, 3});
      sunk.select(2, toe).select(2, 1).fill_(-0.02);  // one toe 2 cm too low on every frame
      // 3 * 0.0004 over (frames x 2 toes), one toe of two in error.
      CHECK(geometry_loss(f, sk, sunk, ground, valid, whole).item<double>() == Approx(3.0 * 0.0004 / 2));
      CHECK(geometry_loss(f, sk, sunk, air, valid, whole).item<double>() == Approx(0.0).margin(1e-12));
      CHECK(geometry_loss(f, sk, slide, ground, valid, whole).item<double>() == Approx(0.0).margin(1e-12));
      auto pelvis_low = torch::zeros({B, T, J, 3});
      pelvis_low.select(2, 0).select(2, 1).fill_(-0.05);  // another joint's height error: not the toes'
      CHECK(geometry_loss(f, sk, pelvis_low, ground, valid, whole).item<double>() == Approx(0.0).margin(1e-12));
    }
  }
  // Off: exactly zero; invalid frames do not count.
  GeometryLossConfig off;
  CHECK(geometry_loss(off, sk, torch::randn({B, T, J, 3}), ground, valid, whole).item<double>() == 0.0);
  auto none = torch::zeros({B, T, 1, 1});
  CHECK(geometry_loss(g, sk, torch::randn({B, T, J, 3}), ground, none, whole).item<double>() == 0.0);
}

TEST_CASE("flow prior: the geometry loss section is off by default and then absent from the dump", "[flow]") {
  TrainJobConfig a, b;
  auto plain = tiny_flow_trainer(a, "", true);
  auto geo = tiny_flow_trainer(b, "  geometry_loss:\n    bone_weight: 1.0\n    contact_weight: 1.0\n", true);
  CHECK(dump_config(a).find("geometry_loss") == std::string::npos);
  CHECK(dump_config(b).find("geometry_loss") != std::string::npos);
  CHECK(dump_config(b).find("floor") == std::string::npos);  // the floor term's section stays out when off
  TrainJobConfig c;
  tiny_flow_trainer(c, "  geometry_loss:\n    floor:\n      weight: 10\n", true);
  CHECK(dump_config(c).find("floor") != std::string::npos);
  test::same_random_weights({plain.get(), geo.get()});
  torch::manual_seed(9);
  double lp = plain->loss({0, 1}).loss.item<double>();
  torch::manual_seed(9);
  double lg = geo->loss({0, 1}).loss.item<double>();
  CHECK(lg > lp);  // same draws: the geometry terms add to the same flow loss
}
