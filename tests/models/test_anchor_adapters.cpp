// Anchor adapters (AnchorRoute §3.2): feature layout, AnchorKV's per-layer key/value
// memory, zero-init baselines leaving the backbone unchanged, parameter counts, and
// eq. (16) steps that move only adapter weights (backbone and decoder stay bit-identical).
#include <catch2/catch.hpp>

#include <limits>
#include <random>

#include "core/error.h"
#include "models/anchor_adapters.h"
#include "models/vq_tokenizer.h"
#include "control/anchor_loss.h"

using namespace mc;

namespace {

TokenTransformerOptions backbone_options() {
  TokenTransformerOptions o;
  o.num_codes = 16;
  o.depth = 3;
  o.width = 32;
  o.heads = 4;
  o.dropout = 0.0;
  o.text_dim = 24;
  o.freq_dim = 16;
  return o;
}

// A random, frozen backbone (an untrained AdaLN-Zero net would have zero logits).
TokenTransformer frozen_backbone(const TokenTransformerOptions& o, uint64_t seed) {
  torch::manual_seed(seed);
  TokenTransformer net(o);
  torch::NoGradGuard ng;
  for (auto& p : net->parameters()) {
    p.normal_(0.0, 0.2);
    p.set_requires_grad(false);
  }
  net->eval();
  return net;
}

AnchorAdapterConfig adapter_config(const std::string& type) {
  AnchorAdapterConfig c;
  c.adapter = type;
  c.rank = 4;
  c.encoder_blocks = 1;
  c.heads = 4;
  return c;
}

TextContext random_text(int64_t B, int64_t W, int64_t dim) {
  TextContext c;
  c.pooled = torch::randn({B, dim});
  c.memory = torch::randn({B, W, dim});
  c.memory_valid = torch::ones({B, W}, torch::kBool);
  return c;
}

// A motion [T, 22, 3] with a drifting root, for anchor draws.
std::vector<float> toy_motion(int T) {
  std::vector<float> m(static_cast<size_t>(T) * 22 * 3);
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < 22; ++j) {
      m[(t * 22 + j) * 3 + 0] = 0.05f * t + 0.01f * j;
      m[(t * 22 + j) * 3 + 1] = 0.9f + 0.02f * j;
      m[(t * 22 + j) * 3 + 2] = 0.02f * t - 0.01f * j;
    }
  return m;
}

struct Inputs {
  AdapterInputs in;
  int64_t L;
};

Inputs make_inputs(const AnchorAdapterConfig& c, const TokenTransformerOptions& o, int64_t B, int64_t L,
                   int64_t stride) {
  torch::manual_seed(3);
  auto motion = toy_motion(static_cast<int>(L * stride));
  std::mt19937_64 rng(5);
  Inputs r;
  r.L = L;
  r.in.ids = torch::randint(0, o.num_codes, {B, L}, torch::kInt64);
  r.in.t = torch::rand({B});
  r.in.text = random_text(B, 5, o.text_dim);
  r.in.valid = torch::ones({B, L}, torch::kBool);
  r.in.valid[1].narrow(0, L - 2, 2).fill_(false);
  auto feats = torch::zeros({B, L * stride, adapter_feature_width(c.body_joints, c.features)});
  for (int64_t b = 0; b < B; ++b) {
    auto fam = b % 3 == 0 ? AnchorFamily::root_3d : b % 3 == 1 ? AnchorFamily::planar_root : AnchorFamily::body_point;
    auto set = draw_anchor_set(fam, 4, motion.data(), static_cast<int>(L * stride), 22, rng, c.body_joints);
    feats[b].copy_(adapter_features(set, c.body_joints, c.features));
  }
  r.in.features = feats;
  return r;
}

}  // namespace

TEST_CASE("adapter features: one block per family plus a family one-hot", "[anchorkv]") {
  std::vector<int> bj = {0, 10, 11, 15, 20, 21};
  CHECK(adapter_feature_width(bj) == 11 + 8 + (3 * 18 + 2 * 6) + 3);
  auto motion = toy_motion(40);
  std::mt19937_64 rng(1);
  auto root = draw_anchor_set(AnchorFamily::root_3d, 3, motion.data(), 40, 22, rng, bj);
  auto f = adapter_features(root, bj);
  REQUIRE(f.sizes().vec() == std::vector<int64_t>{40, 88});
  // The root_3d block equals eqs. (5)-(6) for its own layout; other families' blocks are 0.
  FeatureMatrix m = anchor_features(root, anchor_feature_layout(AnchorFamily::root_3d, bj));
  auto own = torch::from_blob(m.data(), {40, 11}, torch::kFloat32);
  CHECK(torch::equal(f.narrow(1, 0, 11), own));
  CHECK(f.narrow(1, 11, 88 - 11 - 3).abs().max().item<float>() == 0.0f);
  CHECK(torch::equal(f.narrow(1, 85, 3)[0], torch::tensor({1.0f, 0.0f, 0.0f})));
  auto body = draw_anchor_set(AnchorFamily::body_point, 3, motion.data(), 40, 22, rng, bj);
  auto fb = adapter_features(body, bj);
  CHECK(fb.narrow(1, 0, 19).abs().max().item<float>() == 0.0f);
  CHECK(fb.narrow(1, 19, 66).abs().max().item<float>() > 0.0f);
  CHECK(torch::equal(fb.narrow(1, 85, 3)[5], torch::tensor({0.0f, 0.0f, 1.0f})));
  // delta_scale multiplies exactly the Delta p channels [2 d_f, 3 d_f) of the set's block.
  for (double scale : {0.5, 20.0}) {
    AdapterFeatureConfig fc;
    fc.delta_scale = scale;
    auto g = adapter_features(root, bj, fc);
    CHECK(torch::equal(g.narrow(1, 0, 6), f.narrow(1, 0, 6)));
    CHECK(torch::allclose(g.narrow(1, 6, 3), f.narrow(1, 6, 3) * scale));
    CHECK(torch::equal(g.narrow(1, 9, 88 - 9), f.narrow(1, 9, 88 - 9)));
  }
  CHECK(f.narrow(1, 6, 3).abs().max().item<float>() > 0.0f);  // the channel the check scales is live
  // A body-point anchor on a joint outside the layout is a clear error.
  auto other = draw_anchor_set(AnchorFamily::body_point, 2, motion.data(), 40, 22, rng, {7});
  CHECK_THROWS_AS(adapter_features(other, bj), UserError);
}

TEST_CASE("adapter features in the path frame: path blocks alone or after the world blocks, one-hot last",
          "[anchorkv][path_features]") {
  std::vector<int> bj = {0, 10, 11, 15, 20, 21};
  AdapterFeatureConfig world, path, both;
  path.frame = "path";
  both.frame = "both";
  CHECK(adapter_feature_width(bj, world) == 88);
  CHECK(adapter_feature_width(bj, path) == 14 + 10 + 17 * 6 + 3);
  CHECK(adapter_feature_width(bj, both) == 85 + 126 + 3);
  auto motion = toy_motion(40);
  std::mt19937_64 rng(4);
  for (auto fam : {AnchorFamily::root_3d, AnchorFamily::planar_root, AnchorFamily::body_point}) {
    auto set = draw_anchor_set(fam, 4, motion.data(), 40, 22, rng, bj);
    auto layout = anchor_feature_layout(fam, bj);
    const int64_t off = fam == AnchorFamily::root_3d ? 0 : fam == AnchorFamily::planar_root ? 14 : 24;
    FeatureMatrix m = anchor_path_features(set, layout);
    auto own = torch::from_blob(m.data(), {40, m.cols()}, torch::kFloat32);
    auto p = adapter_features(set, bj, path), b = adapter_features(set, bj, both), w = adapter_features(set, bj, world);
    CHECK(torch::equal(p.narrow(1, off, m.cols()), own));
    CHECK(p.narrow(1, 0, 126).abs().sum().item<double>() == Approx(own.abs().sum().item<double>()));
    CHECK(torch::equal(b.narrow(1, 0, 85), w.narrow(1, 0, 85)));
    CHECK(torch::equal(b.narrow(1, 85, 129), p));
    CHECK(torch::equal(b.narrow(1, 211, 3), w.narrow(1, 85, 3)));
  }
  // The default is left out of the dumped config (existing runs keep their hashes).
  AnchorAdapterConfig c;
  CHECK(dump_config(c).find("features") == std::string::npos);
  c.features.frame = "path";
  CHECK(dump_config(c).find("frame: \"path\"") != std::string::npos);
  // The feedback switch (ours) is left out too until it is on (shipped runs keep their hashes).
  CHECK(dump_config(c).find("feedback") == std::string::npos);
  c.features.feedback.enabled = true;
  CHECK(dump_config(c).find("feedback") != std::string::npos);
  CHECK(adapter_feature_width(bj, c.features) == 14 + 10 + 17 * 6 + 3 + 17);
  // adapter_features leaves the feedback block (last) at 0: it needs an estimate.
  auto set = draw_anchor_set(AnchorFamily::root_3d, 4, motion.data(), 40, 22, rng, bj);
  auto f = adapter_features(set, bj, c.features);
  CHECK(f.narrow(1, f.size(1) - 17, 17).abs().sum().item<double>() == 0.0);
  CHECK(torch::equal(f.narrow(1, 0, f.size(1) - 17), adapter_features(set, bj, path)));
  // Rollout states (ours) and their loss weights: in the dump only when set.
  AnchorAdapterConfig r;
  CHECK(dump_config(r).find("training") == std::string::npos);
  r.training.rollout.prob = 0.3;
  CHECK(dump_config(r).find("rollout") != std::string::npos);
  CHECK(dump_config(r).find("ce_weight") == std::string::npos);
  r.training.rollout.loss.anchor_weight = 1.0;
  CHECK(dump_config(r).find("ce_weight") != std::string::npos);
}

TEST_CASE("AnchorKV: one LayerKV per block, token-aligned [B, L, width], values zero at init", "[anchorkv]") {
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 1);
  auto c = adapter_config("anchorkv");
  auto a = make_anchor_adapter(c, bb, 4);
  auto x = make_inputs(c, o, 3, 7, 4);
  auto h = a->hooks(x.in);
  REQUIRE(h.extra_kv.size() == static_cast<size_t>(o.depth));
  CHECK(h.block_residuals.empty());
  for (auto& kv : h.extra_kv) {
    CHECK(kv.k.sizes().vec() == std::vector<int64_t>{3, 7, 32});
    CHECK(kv.v.sizes().vec() == std::vector<int64_t>{3, 7, 32});
    CHECK(torch::equal(kv.mask, x.in.valid));
    CHECK(kv.v.abs().max().item<float>() == 0.0f);  // U^V starts at zero
    CHECK(kv.k.abs().max().item<float>() > 0.0f);
  }
  // The memory is token-aligned: H^s has L slots for L * stride frames.
  auto Hs = a->scaffold(x.in.features, x.in.text);
  CHECK(Hs.sizes().vec() == std::vector<int64_t>{3, 7, 32});
  auto out = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h);
  CHECK(torch::isfinite(out.logits).all().item<bool>());
  // Without dual context the memory ignores the text.
  auto c2 = c;
  c2.dual_context = false;
  auto a2 = make_anchor_adapter(c2, bb, 4);
  auto t2 = x.in;
  t2.text = random_text(3, 5, o.text_dim);
  CHECK(torch::equal(a2->scaffold(x.in.features, x.in.text), a2->scaffold(t2.features, t2.text)));
}

TEST_CASE("zero-init baselines leave the frozen backbone's logits unchanged", "[anchorkv]") {
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 2);
  for (std::string type : {"cross_attention", "controlnet"}) {
    auto c = adapter_config(type);
    auto a = make_anchor_adapter(c, bb, 4);
    a->eval();
    auto x = make_inputs(c, o, 3, 6, 4);
    auto h = a->hooks(x.in);
    REQUIRE(h.block_residuals.size() == static_cast<size_t>(o.depth));
    auto base = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid).logits;
    auto with = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h).logits;
    CHECK(torch::equal(base, with));
  }
  // The ControlNet copy starts as the frozen blocks.
  auto cn = std::dynamic_pointer_cast<ControlNetAdapterImpl>(make_anchor_adapter(adapter_config("controlnet"), bb, 4));
  REQUIRE(cn);
  auto src = bb->blocks[1]->named_parameters();
  for (auto& p : cn->blocks[1]->named_parameters()) CHECK(torch::equal(p.value(), src[p.key()]));
}

TEST_CASE("trainable parameter counts: AnchorKV is far smaller than ControlNet and cross-attention", "[anchorkv]") {
  auto o = backbone_options();
  o.depth = 6;
  o.width = 128;
  o.heads = 4;
  auto bb = frozen_backbone(o, 3);
  auto kv = make_anchor_adapter(adapter_config("anchorkv"), bb, 4);
  auto ca = make_anchor_adapter(adapter_config("cross_attention"), bb, 4);
  auto cn = make_anchor_adapter(adapter_config("controlnet"), bb, 4);
  int64_t n_kv = count_parameters(*kv), n_ca = count_parameters(*ca), n_cn = count_parameters(*cn);
  CHECK(n_kv * 3 < n_cn);
  CHECK(n_kv * 3 < n_ca);
  CHECK(count_parameters(*bb) == 0);  // frozen: none counted as trainable
  // The low-rank projections: r (d_s + 2 d) per block.
  auto c = adapter_config("anchorkv");
  auto c8 = c;
  c8.rank = 8;
  auto kv8 = make_anchor_adapter(c8, bb, 4);
  CHECK(count_parameters(*kv8) - count_parameters(*kv) == 6 * 4 * (128 + 2 * 128));
}

TEST_CASE("eq. (16) steps move only adapter weights, backbone and decoder stay bit-identical", "[anchorkv]") {
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 4);
  torch::manual_seed(9);
  VqTokenizerOptions vo;
  vo.conv.in_dim = 22 * 3;
  vo.conv.width = 16;
  vo.conv.latent = 8;
  vo.conv.down_stages = 2;
  vo.conv.res_depth = 1;
  vo.quant.codebook_size = 16;
  vo.quant.code_dim = 8;
  VqTokenizer vq(vo);
  vq->eval();
  for (auto& p : vq->parameters()) p.set_requires_grad(false);
  std::vector<torch::Tensor> frozen_before;
  for (auto& p : bb->parameters()) frozen_before.push_back(p.clone());
  for (auto& p : vq->parameters()) frozen_before.push_back(p.clone());
  for (std::string type : {"anchorkv", "cross_attention", "controlnet"}) {
    auto c = adapter_config(type);
    auto a = make_anchor_adapter(c, bb, 4);
    std::vector<torch::Tensor> params = a->parameters();
    std::vector<torch::Tensor> before;
    for (auto& p : params) before.push_back(p.clone());
    torch::optim::AdamW opt(params, torch::optim::AdamWOptions(1e-2));
    auto x = make_inputs(c, o, 3, 6, 4);
    auto motion = toy_motion(24);
    std::mt19937_64 rng(2);
    std::vector<AnchorSet> sets;
    for (int b = 0; b < 3; ++b) sets.push_back(draw_anchor_set(AnchorFamily::root_3d, 4, motion.data(), 24, 22, rng));
    auto gt = torch::from_blob(motion.data(), {1, 24, 22, 3}, torch::kFloat32).expand({3, 24, 22, 3}).clone();
    for (int step = 0; step < 3; ++step) {
      auto h = a->hooks(x.in);
      auto logits = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h).logits;
      auto ce = torch::nn::functional::cross_entropy(logits.reshape({-1, 16}), x.in.ids.reshape({-1}));
      auto world = vq->denormalize(vq->soft_decode(torch::softmax(logits, -1)).view({3, 24, 22, 3}));
      auto support = make_support_batch(sets, 2, gt);
      auto loss = ce + 0.3 * anchor_loss(world, support).sum() / support.valid.sum();
      opt.zero_grad();
      loss.backward();
      opt.step();
    }
    bool moved = false;
    for (size_t i = 0; i < params.size(); ++i) moved |= !torch::equal(params[i], before[i]);
    CHECK(moved);
    size_t k = 0;
    for (auto& p : bb->parameters()) CHECK(torch::equal(p, frozen_before[k++]));
    for (auto& p : vq->parameters()) CHECK(torch::equal(p, frozen_before[k++]));
  }
}

namespace {

// AnchorKV options of issue 15: the block's own normaliser and a token-aligned window.
AnchorAdapterConfig aligned_config(int window) {
  auto c = adapter_config("anchorkv");
  c.anchorkv.normaliser = "own";
  c.anchorkv.window = window;
  return c;
}

AnchorAdapterConfig path_config() {
  auto c = aligned_config(1);
  c.features.frame = "both";
  return c;
}

AnchorAdapterConfig text_slots_config() {
  auto c = aligned_config(1);
  c.dual_context = false;
  c.anchorkv.text_slots.enabled = true;
  return c;
}

double max_abs_diff(const torch::Tensor& a, const torch::Tensor& b) { return (a - b).abs().max().item<double>(); }

// Randomises every trainable weight so an adapter's effect is visible.
void randomise(torch::nn::Module& m, uint64_t seed, double std = 0.3) {
  torch::manual_seed(seed);
  torch::NoGradGuard ng;
  for (auto& p : m.parameters())
    if (p.requires_grad()) p.normal_(0.0, std);
}

}  // namespace

TEST_CASE("identity at initialisation: untrained adapters leave the frozen prior's logits unchanged",
          "[anchorkv]") {
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 6);
  std::vector<std::pair<std::string, AnchorAdapterConfig>> cases = {
      {"anchorkv own, all slots", aligned_config(-1)},
      {"anchorkv own, window 0", aligned_config(0)},
      {"anchorkv own, window 1", aligned_config(1)},
      {"anchorkv own, window 1, path-frame features", path_config()},
      {"anchorkv own, window 1, text slots, no dual context", text_slots_config()},
      {"cross_attention", adapter_config("cross_attention")},
      {"controlnet", adapter_config("controlnet")}};
  for (auto& [name, c] : cases) {
    INFO(name);
    auto a = make_anchor_adapter(c, bb, 4);
    a->eval();
    auto x = make_inputs(c, o, 3, 7, 4);
    auto base = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid).logits;
    auto h = a->hooks(x.in);
    auto with = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h).logits;
    auto valid = x.in.valid.unsqueeze(-1).expand_as(base);
    // Equal up to float32 rounding: the hooked forward takes another computation path (its
    // matmuls have other shapes, so BLAS may sum in another order: 1.4e-6 measured on an
    // AMD EPYC), three orders below what random weights move (> 1e-3, below).
    CHECK(max_abs_diff(base.masked_select(valid), with.masked_select(valid)) < 1e-5);
    // Zero-init is not zero effect forever: the same adapter with random weights moves them.
    randomise(*a, 8);
    auto h2 = a->hooks(x.in);
    auto moved = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h2).logits;
    CHECK(max_abs_diff(base.masked_select(valid), moved.masked_select(valid)) > 1e-3);
  }
  // eq. (15) as written (one softmax over [K; K^s]) is not the identity at initialisation:
  // the memory takes attention mass from the frozen block though its values are zero.
  auto c = adapter_config("anchorkv");
  REQUIRE(c.anchorkv.paper());
  auto a = make_anchor_adapter(c, bb, 4);
  a->eval();
  auto x = make_inputs(c, o, 3, 7, 4);
  auto h = a->hooks(x.in);
  auto base = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid).logits;
  CHECK(max_abs_diff(base, bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &h).logits) > 1e-4);
}

TEST_CASE("AnchorKV window: token n reads memory slots |n - m| <= w only (own and joint normaliser)",
          "[anchorkv]") {
  auto o = backbone_options();
  o.depth = 1;  // one block: token n's logits see the memory only through its own attention row
  auto bb = frozen_backbone(o, 7);
  const int64_t B = 2, L = 9, m = 4;
  torch::manual_seed(1);
  auto ids = torch::randint(0, o.num_codes, {B, L}, torch::kInt64);
  auto t = torch::rand({B});
  auto text = random_text(B, 5, o.text_dim);
  auto valid = torch::ones({B, L}, torch::kBool);
  auto k = torch::randn({B, L, o.width}), v = torch::randn({B, L, o.width});
  for (std::string norm : {"own", "joint"})
    for (int w : {0, 1, 3}) {
      INFO(norm << " window " << w);
      auto pos = torch::arange(L, torch::kFloat32);
      auto bias = torch::zeros({L, L}).masked_fill((pos.unsqueeze(1) - pos.unsqueeze(0)).abs() > w,
                                                   -std::numeric_limits<float>::infinity());
      auto run = [&](const torch::Tensor& vv) {
        TokenTransformerHooks h;
        LayerKV kv{k, vv, valid};
        kv.bias = bias;
        kv.own_normaliser = norm == "own";
        h.extra_kv.push_back(kv);
        return bb->forward(ids, t, text, valid, &h).logits;
      };
      auto v2 = v.clone();
      v2.select(1, m).add_(1.0);  // change memory slot m's value only
      auto d = (run(v) - run(v2)).abs().amax({0, 2});  // [L]
      for (int64_t n = 0; n < L; ++n) {
        if (std::abs(n - m) <= w)
          CHECK(d[n].item<double>() > 1e-5);
        else
          CHECK(d[n].item<double>() == 0.0);
      }
    }
}

TEST_CASE("AnchorKV own normaliser: zero memory values leave the block as it was, the joint softmax does not",
          "[anchorkv]") {
  auto o = backbone_options();
  o.depth = 1;
  auto bb = frozen_backbone(o, 9);
  const int64_t B = 2, L = 6;
  torch::manual_seed(2);
  auto ids = torch::randint(0, o.num_codes, {B, L}, torch::kInt64);
  auto t = torch::rand({B});
  auto text = random_text(B, 5, o.text_dim);
  auto valid = torch::ones({B, L}, torch::kBool);
  auto k = torch::randn({B, L, o.width}) * 3;
  auto base = bb->forward(ids, t, text, valid).logits;
  TokenTransformerHooks h;
  LayerKV kv{k, torch::zeros({B, L, o.width}), valid};
  kv.own_normaliser = true;
  h.extra_kv.push_back(kv);
  CHECK(max_abs_diff(base, bb->forward(ids, t, text, valid, &h).logits) < 1e-6);
  h.extra_kv[0].own_normaliser = false;
  CHECK(max_abs_diff(base, bb->forward(ids, t, text, valid, &h).logits) > 1e-4);
}

TEST_CASE("anchor guidance: CFG passes with and without hooks, and the anchor weight pushes toward the anchors",
          "[anchorkv]") {
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 10);
  auto c = aligned_config(1);
  auto a = make_anchor_adapter(c, bb, 4);
  randomise(*a, 12);
  a->eval();
  auto x = make_inputs(c, o, 3, 7, 4);
  torch::NoGradGuard ng;
  auto null = random_text(3, 5, o.text_dim);
  auto h = a->hooks(x.in);
  auto fwd = [&](const TextContext& txt, bool hooks) {
    return bb->forward(x.in.ids, x.in.t, txt, x.in.valid, hooks ? &h : nullptr).logits;
  };
  auto lcA = fwd(x.in.text, true), luA = fwd(null, true), lc0 = fwd(x.in.text, false), lu0 = fwd(null, false);
  const double s = 3.0;
  auto guided = [&](bool in_uncond, double scale) {
    h.guidance = {in_uncond, scale};
    return guided_token_logits(*bb, x.in.ids, x.in.t, x.in.text, null, x.in.valid, s, &h);
  };
  // The default is the two-pass CFG with the hooks in both halves (what sampling did before).
  CHECK(max_abs_diff(guided(true, 1.0), luA + s * (lcA - luA)) < 1e-4);
  CHECK(max_abs_diff(guided(false, 1.0), lu0 + s * (lcA - lu0)) < 1e-4);
  CHECK(max_abs_diff(guided(true, 2.5), luA + s * (lcA - luA) + 1.5 * (lcA - lc0)) < 1e-4);
  CHECK(max_abs_diff(guided_token_logits(*bb, x.in.ids, x.in.t, x.in.text, null, x.in.valid, s, nullptr),
                     lu0 + s * (lc0 - lu0)) < 1e-4);
  // Direction: at each position the code the anchors favour most (argmax of l_cA - l_c0)
  // gains log-probability as the anchor weight grows. Anchors conditional-only add
  // (s - 1)(l_uA - l_u0) to the default, so argmax(l_uA - l_u0) gains too.
  auto favoured = (lcA - lc0).argmax(-1, true);
  auto logp = [&](const torch::Tensor& l, const torch::Tensor& idx) {
    return torch::log_softmax(l, -1).gather(-1, idx).squeeze(-1);
  };
  auto p1 = logp(guided(true, 1.0), favoured), p2 = logp(guided(true, 2.0), favoured),
       p4 = logp(guided(true, 4.0), favoured);
  CHECK((p2 > p1).all().item<bool>());
  CHECK((p4 > p2).all().item<bool>());
  auto fav_u = (luA - lu0).argmax(-1, true);
  CHECK((logp(guided(false, 1.0), fav_u) > logp(guided(true, 1.0), fav_u)).all().item<bool>());
}

TEST_CASE("CFG: an adapter that reads the text gives the null-text pass hooks computed on the null text",
          "[anchorkv]") {
  // Training drops the caption for the backbone and the adapter together (cond_drop), so the
  // null-text pass must not see a memory (or ControlNet copy) computed from the caption.
  auto o = backbone_options();
  auto bb = frozen_backbone(o, 13);
  auto no_dual = adapter_config("anchorkv");
  no_dual.dual_context = false;
  std::vector<std::pair<std::string, AnchorAdapterConfig>> cases = {
      {"anchorkv, dual context", adapter_config("anchorkv")},
      {"controlnet", adapter_config("controlnet")},
      {"anchorkv, text slots", text_slots_config()},
      {"anchorkv, no dual context", no_dual}};
  for (auto& [name, c] : cases) {
    INFO(name);
    auto a = make_anchor_adapter(c, bb, 4);
    randomise(*a, 14);
    a->eval();
    torch::NoGradGuard ng;
    auto x = make_inputs(c, o, 3, 7, 4);
    torch::manual_seed(15);
    auto null = random_text(3, x.in.text.memory.size(1), o.text_dim);
    const bool reads = name != "anchorkv, no dual context";
    CHECK(a->reads_text() == reads);
    auto h = a->guided_hooks(x.in, null);
    CHECK((h.null_text != nullptr) == reads);
    auto valid = x.in.valid.unsqueeze(-1).expand({-1, -1, o.num_codes});
    auto on_valid = [&](const torch::Tensor& l) { return l.masked_select(valid); };
    // cfg 0 = the null-text pass alone; cfg 1 = the text pass alone.
    auto uncond = guided_token_logits(*bb, x.in.ids, x.in.t, x.in.text, null, x.in.valid, 0.0, &h);
    auto cond = guided_token_logits(*bb, x.in.ids, x.in.t, x.in.text, null, x.in.valid, 1.0, &h);
    AdapterInputs n = x.in;
    n.text = null;
    auto hn = a->hooks(n);
    auto hc = a->hooks(x.in);
    auto want_uncond = bb->forward(x.in.ids, x.in.t, null, x.in.valid, &hn).logits;
    auto want_cond = bb->forward(x.in.ids, x.in.t, x.in.text, x.in.valid, &hc).logits;
    CHECK(max_abs_diff(on_valid(uncond), on_valid(want_uncond)) < 1e-4);
    CHECK(max_abs_diff(on_valid(cond), on_valid(want_cond)) < 1e-4);
    // The caption's hooks in the null pass (what sampling did before) are another thing
    // for a text-reading adapter, and the same for one that ignores the text.
    auto stale = bb->forward(x.in.ids, x.in.t, null, x.in.valid, &hc).logits;
    if (reads)
      CHECK(max_abs_diff(on_valid(stale), on_valid(want_uncond)) > 1e-3);
    else
      CHECK(max_abs_diff(on_valid(stale), on_valid(want_uncond)) < 1e-5);
  }
}
