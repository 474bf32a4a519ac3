// VQ tokenizer: shapes, straight-through gradients, the EMA codebook update and
// dead-code reset on hand-made numbers, soft decode, the TMD distance table, and
// an end-to-end vq_tiny run with its loader.
#include <catch2/catch.hpp>

#include <cmath>
#include <sstream>

#include "cli/jobs.h"
#include "core/error.h"
#include "data/features.h"
#include "models/vq_tokenizer.h"
#include "test_util.h"
#include "models/motion_dataset.h"
#include "train/trainer.h"
#include "trainer_test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

VqTokenizerOptions tiny_options(int K = 16, int D = 8) {
  VqTokenizerOptions o;
  o.conv.in_dim = 22 * 3;
  o.conv.width = 16;
  o.conv.latent = D;
  o.conv.down_stages = 2;
  o.conv.res_depth = 1;
  o.quant.codebook_size = K;
  o.quant.code_dim = D;
  return o;
}

std::map<std::string, double> read_summary(const fs::path& p) {
  std::map<std::string, double> out;
  std::stringstream in(slurp(p));
  std::string line;
  std::getline(in, line);
  while (std::getline(in, line)) {
    auto c = line.find(',');
    if (c != std::string::npos) out[line.substr(0, c)] = std::stod(line.substr(c + 1));
  }
  return out;
}

}  // namespace

TEST_CASE("tokenizer shapes: T frames -> T/4 tokens -> T frames", "[tokenizer]") {
  torch::manual_seed(0);
  VqTokenizer vq(tiny_options());
  vq->eval();
  auto x = torch::randn({2, 32, 66});
  auto ids = vq->encode(x);
  CHECK(ids.sizes() == torch::IntArrayRef({2, 8}));
  CHECK(ids.scalar_type() == torch::kLong);
  CHECK(ids.min().item<int64_t>() >= 0);
  CHECK(ids.max().item<int64_t>() < 16);
  CHECK(vq->decode(ids).sizes() == torch::IntArrayRef({2, 32, 66}));
  auto out = vq->forward(x);
  CHECK(out.recon.sizes() == torch::IntArrayRef({2, 32, 66}));
  CHECK(torch::equal(out.ids, ids));
  CHECK(vq->soft_decode(torch::softmax(torch::randn({2, 8, 16}), -1)).sizes() == torch::IntArrayRef({2, 32, 66}));
  CHECK(vq->decode_embeddings(torch::randn({2, 8, 8})).sizes() == torch::IntArrayRef({2, 32, 66}));
  CHECK(vq->stride() == 4);
  CHECK_THROWS_AS(vq->encode(torch::randn({1, 30, 66})), UserError);
  // The mask zeroes padding: garbage in padded frames does not change the tokens.
  auto mask = torch::ones({2, 32}, torch::kBool);
  mask.slice(1, 20).fill_(false);
  auto garbage = x.clone();
  garbage.slice(1, 20).normal_().mul_(50);
  CHECK(torch::equal(vq->encode(x, mask), vq->encode(garbage, mask)));
}

TEST_CASE("straight-through estimator: the reconstruction gradient reaches the encoder", "[tokenizer]") {
  torch::manual_seed(1);
  VqTokenizer vq(tiny_options());
  vq->train();
  auto x = torch::randn({2, 16, 66});
  auto out = vq->forward(x);
  out.recon.pow(2).mean().backward();
  double enc = 0;
  for (auto& p : vq->encoder->parameters()) enc += p.grad().defined() ? p.grad().abs().sum().item<double>() : 0.0;
  CHECK(enc > 0);
  // The codebook is a buffer: the optimiser never sees it.
  for (auto& p : vq->parameters()) CHECK_FALSE(p.is_same(vq->codebook()));
  CHECK(vq->named_buffers().contains("quantizer.codebook"));
  CHECK(vq->named_buffers().contains("quantizer.cluster_size"));
  CHECK(vq->named_buffers().contains("joint_mean"));
}

TEST_CASE("EMA update moves a code toward the mean of its assigned vectors", "[tokenizer]") {
  EmaQuantizerOptions o;
  o.codebook_size = 2;
  o.code_dim = 2;
  o.decay = 0.9;
  o.reset_threshold = 0;  // no reset: isolate the EMA arithmetic
  o.epsilon = 1e-5;
  o.commitment = 0.02;
  EmaQuantizer q(o);
  q->codebook.copy_(torch::tensor({0.f, 0.f, 10.f, 10.f}).view({2, 2}));
  q->embed_sum.copy_(q->codebook);
  q->cluster_size.fill_(1.0);
  q->train();
  auto z = torch::tensor({1.f, 0.f, 1.f, 2.f, 9.f, 9.f}).view({3, 2});
  auto out = q->forward(z);
  CHECK(torch::equal(out.ids, torch::tensor({0, 0, 1}, torch::kLong)));
  // The output is the (pre-update) code; commitment = beta * mean ||z - e||^2.
  CHECK(torch::allclose(out.quantized, torch::tensor({0.f, 0.f, 0.f, 0.f, 10.f, 10.f}).view({3, 2})));
  double commit = 0.02 * (1 + 0 + 1 + 4 + 1 + 1) / 6.0;
  CHECK(out.commit_loss.item<double>() == Approx(commit).epsilon(1e-6));
  // Counts: N0 = 0.9*1 + 0.1*2, N1 = 0.9*1 + 0.1*1; sums likewise; Laplace-smoothed division.
  double N0 = 1.1, N1 = 1.0, n = N0 + N1, eps = 1e-5;
  double s0 = (N0 + eps) / (n + 2 * eps) * n, s1 = (N1 + eps) / (n + 2 * eps) * n;
  double m0x = 0.1 * 2, m0y = 0.1 * 2, m1 = 0.9 * 10 + 0.1 * 9;
  auto e = q->codebook;
  CHECK(q->cluster_size[0].item<double>() == Approx(N0));
  CHECK(q->cluster_size[1].item<double>() == Approx(N1));
  CHECK(e[0][0].item<double>() == Approx(m0x / s0).epsilon(1e-5));
  CHECK(e[0][1].item<double>() == Approx(m0y / s0).epsilon(1e-5));
  CHECK(e[1][0].item<double>() == Approx(m1 / s1).epsilon(1e-5));
  CHECK(e[1][1].item<double>() == Approx(m1 / s1).epsilon(1e-5));
  // Code 0 moved from the origin toward its assigned mean (1, 1); code 1 toward (9, 9).
  CHECK(e[0][0].item<double>() > 0.0);
  CHECK(e[1][0].item<double>() < 10.0);
  CHECK(out.perplexity.item<double>() == Approx(std::exp(-(2.0 / 3 * std::log(2.0 / 3) + 1.0 / 3 * std::log(1.0 / 3)))));
  // Eval mode leaves the codebook alone; masked-out vectors never count.
  auto before = q->codebook.clone();
  q->eval();
  q->forward(z);
  CHECK(torch::equal(before, q->codebook));
  q->train();
  auto sizes = q->cluster_size.clone();
  auto code = q->codebook.clone();
  q->forward(z, torch::tensor({true, false, false}));  // only (1, 0) counts, for code 0
  CHECK(q->cluster_size[0].item<double>() == Approx(sizes[0].item<double>() * 0.9 + 0.1));
  CHECK(q->cluster_size[1].item<double>() == Approx(sizes[1].item<double>() * 0.9));
  // A batch without valid vectors is no evidence: nothing moves.
  sizes = q->cluster_size.clone();
  code = q->codebook.clone();
  q->forward(z, torch::tensor({false, false, false}));
  CHECK(torch::equal(q->cluster_size, sizes));
  CHECK(torch::equal(q->codebook, code));
}

TEST_CASE("dead-code reset replaces an unused code with a batch vector", "[tokenizer]") {
  EmaQuantizerOptions o;
  o.codebook_size = 3;
  o.code_dim = 2;
  o.decay = 0.99;
  o.reset_threshold = 1.0;
  auto run = [&](uint64_t seed) {
    torch::manual_seed(seed);
    EmaQuantizer q(o);
    q->codebook.copy_(torch::tensor({0.f, 0.f, 10.f, 10.f, 100.f, 100.f}).view({3, 2}));
    q->embed_sum.copy_(q->codebook);
    q->cluster_size.fill_(1.0);
    q->train();
    auto z = torch::tensor({0.5f, 0.f, -0.5f, 0.f, 10.f, 9.f, 11.f, 10.f}).view({4, 2});
    auto out = q->forward(z);
    CHECK(out.resets.item<int64_t>() == 1);
    auto code2 = q->codebook[2];
    bool from_batch = false;
    for (int i = 0; i < 4; ++i) from_batch |= torch::equal(code2, z[i]);
    CHECK(from_batch);
    CHECK(q->cluster_size[2].item<double>() == Approx(1.0));
    // Used codes are EMA-updated, not reset.
    CHECK(q->codebook[0][0].item<double>() == Approx(0.0).margin(1e-6));
    CHECK(q->codebook[1][0].item<double>() > 9.9);
    return q->codebook.clone();
  };
  // The draw comes from torch's generator: same seed, same replacement.
  CHECK(torch::equal(run(5), run(5)));
}

TEST_CASE("decode(encode(x)) equals soft_decode(one_hot(encode(x)))", "[tokenizer]") {
  torch::manual_seed(2);
  VqTokenizer vq(tiny_options());
  vq->eval();
  torch::NoGradGuard ng;
  auto x = torch::randn({3, 24, 66});
  auto ids = vq->encode(x);
  auto hard = vq->decode(ids);
  auto soft = vq->soft_decode(torch::one_hot(ids, vq->codebook_size()).to(torch::kFloat32));
  CHECK(torch::allclose(hard, soft, 1e-5, 1e-6));
  CHECK(torch::allclose(vq->decode_embeddings(vq->codebook().index_select(0, ids.view(-1)).view({3, 6, 8})), hard));
}

TEST_CASE("soft decode is differentiable in the token probabilities", "[tokenizer]") {
  torch::manual_seed(3);
  VqTokenizer vq(tiny_options());
  vq->eval();
  auto logits = torch::randn({1, 4, 16}, torch::requires_grad());
  vq->soft_decode(torch::softmax(logits, -1)).sum().backward();
  REQUIRE(logits.grad().defined());
  CHECK(logits.grad().abs().sum().item<double>() > 0);
}

TEST_CASE("token distance table: zero diagonal, symmetric, (2 - 2 cos)^2", "[tokenizer]") {
  torch::manual_seed(4);
  VqTokenizer vq(tiny_options(12, 5));
  auto d = vq->token_distance_table();
  REQUIRE(d.sizes() == torch::IntArrayRef({12, 12}));
  CHECK(d.diagonal().abs().max().item<double>() == 0.0);
  CHECK(torch::equal(d, d.t()));
  auto e = vq->codebook().to(torch::kFloat64);
  auto n = vq->normalized_codebook();
  CHECK(torch::allclose(n.norm(2, 1), torch::ones({12}), 1e-5, 1e-6));
  for (int i = 0; i < 12; ++i)
    for (int j = 0; j < 12; ++j) {
      if (i == j) continue;
      double c = (e[i] * e[j]).sum().item<double>() / (e[i].norm().item<double>() * e[j].norm().item<double>());
      CHECK(d[i][j].item<double>() == Approx((2 - 2 * c) * (2 - 2 * c)).margin(1e-5));
    }
  CHECK(d.min().item<double>() >= 0.0);
  CHECK(d.max().item<double>() <= 16.0 + 1e-5);
}

TEST_CASE("vq_tiny trains end to end, beats the mean pose and loads back", "[tokenizer][slow]") {
  TempDir t("vq");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data)).exit_code ==
          0);
  std::string common = fmt::format("configs/tokenizer/vq_tiny.yaml data.path={} run.root={} run.threads=1",
                                   data, t.path.string());
  // The trainer's weight EMA would desynchronise the encoder from its EMA codebook.
  auto refused = run_motionctl(fmt::format("train {} run.name=ema optim.ema_decay=0.9 optim.steps=5", common));
  CHECK(refused.exit_code == 2);
  CHECK(refused.output.find("ema_decay") != std::string::npos);

  auto r = run_motionctl(fmt::format("train {} run.name=e2e optim.steps=200", common));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  fs::path run = t.path / "tokenizer" / "e2e";
  REQUIRE(fs::exists(run / "DONE"));
  auto s = read_summary(run / "summary.csv");
  for (auto k : {"test_mpjpe_m", "test_mpjpe_root_aligned_m", "test_mean_pose_mpjpe_m", "test_perplexity",
                 "test_dead_codes", "ema_dead_codes"})
    REQUIRE(s.count(k));
  INFO("mpjpe " << s["test_mpjpe_m"] << " mean pose " << s["test_mean_pose_mpjpe_m"] << " perplexity "
                << s["test_perplexity"]);
  CHECK(s["test_mpjpe_m"] < s["test_mean_pose_mpjpe_m"]);
  CHECK(s["test_perplexity"] > 1.0);
  CHECK(s["test_dead_codes"] < 128);

  // Loader: ready module, normaliser stats of the training data, compatibility checks.
  auto tok = load_vq_tokenizer(run.string());
  CHECK(tok.cfg.codebook_size == 128);
  CHECK(tok.model->codebook().sizes() == torch::IntArrayRef({128, 64}));
  CHECK_FALSE(tok.model->is_training());
  auto ds = MotionDataset::load(data);
  CHECK(torch::allclose(tok.model->joint_mean, ds->joint_mean()));
  CHECK(torch::allclose(tok.model->joint_std, ds->joint_std()));
  CHECK_NOTHROW(tok.check_compatible(ds->set(), data));
  {
    torch::NoGradGuard ng;
    auto b = ds->batch(ds->split("test"), 0, 4, torch::kCPU);
    auto ids = tok.model->encode(b.joints.flatten(2), b.mask);
    CHECK(ids.size(1) == b.joints.size(1) / 4);
    auto y = tok.model->decode(ids);
    CHECK(torch::isfinite(y).all().item<bool>());
  }
  MotionSet fewer = ds->set().subset({0});
  fewer.skeleton.parents.pop_back();
  fewer.skeleton.joint_names.pop_back();
  CHECK_THROWS_WITH(tok.check_compatible(fewer, "fewer.h5"), Catch::Contains("joints"));
  MotionSet faster = ds->set().subset({0});
  faster.fps = 30;
  CHECK_THROWS_AS(tok.check_compatible(faster, "faster.h5"), UserError);

  // Clear errors for a missing run, an incomplete run and a run of another model.
  CHECK_THROWS_AS(load_vq_tokenizer((t.path / "nope").string()), UserError);
  fs::path partial = t.path / "partial";
  fs::create_directories(partial);
  fs::copy_file(run / "config.yaml", partial / "config.yaml");
  CHECK_THROWS_WITH(load_vq_tokenizer(partial.string()), Catch::Contains("final.pt"));
  fs::path other = t.path / "other";
  fs::create_directories(other / "checkpoints");
  fs::create_directories(other / "outputs");
  fs::copy_file(run / "checkpoints" / "final.pt", other / "checkpoints" / "final.pt");
  fs::copy_file(run / "outputs" / "tokenizer_meta.yaml", other / "outputs" / "tokenizer_meta.yaml");
  {
    std::string cfg = slurp(run / "config.yaml");
    auto p = cfg.find("type: vq_tokenizer");
    REQUIRE(p != std::string::npos);
    cfg.replace(p, std::string("type: vq_tokenizer").size(), "type: motion_autoencoder");
    std::ofstream(other / "config.yaml") << cfg;
  }
  CHECK_THROWS_AS(load_vq_tokenizer(other.string()), UserError);
}

TEST_CASE("tokenizer training resumes exactly: codebook buffers and reset draws are checkpointed", "[tokenizer][slow]") {
  TempDir t("vqres");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40", data)).exit_code ==
          0);
  auto job_for = [&](const std::string& root) {
    std::vector<std::string> ov = {"data.path=" + data, "run.root=" + root, "run.name=r", "run.threads=1",
                                   "optim.steps=40", "run.log_every=5", "run.checkpoint_every=10",
                                   "model.width=24", "model.code_dim=16", "model.codebook_size=64",
                                   "optim.batch_size=8"};
    auto job = std::make_unique<TrainJobConfig>();
    parse_config(compose_config(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/tokenizer/vq_tiny.yaml", ov), *job);
    return std::make_pair(std::move(job), ov);
  };
  auto [ja, ova] = job_for((t.path / "a").string());
  auto ra = train(*ja, ova, "r");
  auto [jb, ovb] = job_for((t.path / "b").string());
  auto first = train(*jb, ovb, "r", TrainLoopOptions{15});  // stops at step 15; last.pt holds step 10
  REQUIRE_FALSE(fs::exists(first.run_dir / "DONE"));
  auto [jc, ovc] = job_for((t.path / "b").string());
  auto rb = train(*jc, ovc, "r");
  REQUIRE(fs::exists(rb.run_dir / "DONE"));
  auto strip_wall = [](const std::string& csv) {
    std::stringstream in(csv), out;
    std::string line;
    while (std::getline(in, line)) {
      auto a = line.find(','), b = line.find(',', a + 1);
      out << line.substr(0, a) << line.substr(b) << "\n";  // drop column 2 (wall_time)
    }
    return out.str();
  };
  std::string ma = slurp(ra.run_dir / "metrics.csv"), mb = slurp(rb.run_dir / "metrics.csv");
  REQUIRE(ma.find("wall_time") != std::string::npos);
  CHECK(strip_wall(ma) == strip_wall(mb));
  CHECK(ra.summary.at("test_mpjpe_m") == rb.summary.at("test_mpjpe_m"));
  CHECK(ra.summary.at("test_perplexity") == rb.summary.at("test_perplexity"));
}

// ---------------------------------------------------------------- invariant representation

namespace {

// A turning, travelling clip of the HumanML3D skeleton's rest pose [T, 22, 3] (starts
// off the origin and facing 0.3 rad, so frame -1's canonical frame matters).
torch::Tensor wandering_world(int T, double phase = 0.0) {
  const Skeleton& sk = humanml3d_skeleton();
  auto rest = sk.rest_pose();
  auto out = torch::zeros({T, 22, 3});
  auto a = out.accessor<float, 3>();
  double x = 0.2, z = -0.1;
  for (int t = 0; t < T; ++t) {
    const double h = 0.3 + 0.8 * std::sin(0.06 * t + phase);
    x += 0.04 * std::sin(h);
    z += 0.04 * std::cos(h);
    for (int j = 0; j < 22; ++j) {
      const double rx = std::cos(h) * rest[j].x() + std::sin(h) * rest[j].z();
      const double rz = -std::sin(h) * rest[j].x() + std::cos(h) * rest[j].z();
      a[t][j][0] = static_cast<float>(rx + x);
      a[t][j][1] = static_cast<float>(rest[j].y() + 0.9 + 0.02 * std::sin(0.4 * t + j));
      a[t][j][2] = static_cast<float>(rz + z);
    }
  }
  return out;
}

VqTokenizerOptions invariant_options(const std::string& layout = "inv67") {
  VqTokenizerOptions o = tiny_options();
  o.representation.type = "invariant";
  o.representation.layout = layout;
  o.num_joints = 22;
  o.skeleton = humanml3d_skeleton();
  o.conv.in_dim = feature_dim(layout, o.skeleton);
  return o;
}

}  // namespace

TEST_CASE("invariant recovery in torch equals the CPU recovery and inverts the features", "[tokenizer][invariant]") {
  const int T = 40;
  auto w = wandering_world(T).contiguous();
  for (const std::string layout : {"inv67", "inv67+vel+contact"}) {
    const int F = feature_dim(layout, humanml3d_skeleton());
    auto f = compute_features(layout, w.data_ptr<float>(), T, humanml3d_skeleton());
    auto ft = torch::from_blob(f.data(), {1, T, F}, torch::kFloat32).to(torch::kFloat64);
    auto rec = recover_world_from_invariant(ft, 22).to(torch::kFloat32)[0];
    CHECK((rec - w).abs().max().item<double>() < 1e-4);
    auto cpu = recover_joints_from_invariant(f.data(), T, 22, F);
    CHECK(torch::allclose(rec, torch::from_blob(cpu.data(), {T, 22, 3}), 1e-4, 1e-4));
  }
}

TEST_CASE("invariant tokenizer: world joints in and out, padding ignored, soft decode differentiable",
          "[tokenizer][invariant]") {
  torch::manual_seed(4);
  VqTokenizer vq(invariant_options());
  CHECK(vq->invariant());
  CHECK(vq->num_joints() == 22);
  CHECK(vq->input_dim() == 67);
  {
    auto wrong = invariant_options();
    wrong.conv.in_dim = 66;
    CHECK_THROWS_AS(VqTokenizer(wrong), UserError);
  }
  {
    torch::NoGradGuard ng;
    vq->joint_mean.copy_(torch::tensor({0.1f, 0.9f, 0.3f}));
    vq->joint_std.copy_(torch::tensor({0.8f, 0.5f, 1.1f}));
    vq->feature_mean.normal_(0, 0.01);
    vq->feature_std.uniform_(0.5, 1.5);
  }
  vq->eval();
  // model_input -> model_output_to_joints is the identity on a clip (exact recovery).
  auto w = torch::stack({wandering_world(32), wandering_world(32, 1.0)});  // [2, 32, 22, 3]
  auto x = vq->normalize(w).flatten(2);
  auto feats = vq->model_input(x);
  CHECK(feats.sizes() == torch::IntArrayRef({2, 32, 67}));
  CHECK(torch::allclose(vq->model_output_to_joints(feats), x, 1e-4, 1e-4));
  // Padding is ignored: the tokens of a clip's valid frames do not depend on what follows.
  auto mask = torch::ones({2, 32}, torch::kBool);
  mask[1].narrow(0, 20, 12).fill_(false);
  auto garbage = x.clone();
  garbage[1].narrow(0, 20, 12).normal_();
  CHECK(torch::equal(vq->encode(x, mask), vq->encode(garbage, mask)));
  CHECK(torch::equal(vq->model_input(x, mask)[1].narrow(0, 20, 12), torch::zeros({12, 67})));
  // decode / soft_decode / decode_embeddings all return normalised joints [B, T, 66].
  auto ids = vq->encode(x);
  CHECK(ids.sizes() == torch::IntArrayRef({2, 8}));
  auto hard = vq->decode(ids);
  CHECK(hard.sizes() == torch::IntArrayRef({2, 32, 66}));
  auto soft = vq->soft_decode(torch::one_hot(ids, vq->codebook_size()).to(torch::kFloat32));
  CHECK(torch::allclose(hard, soft, 1e-4, 1e-5));
  CHECK(torch::allclose(vq->decode_embeddings(vq->codebook().index_select(0, ids.view(-1)).view({2, 8, 8})), hard,
                        1e-4, 1e-5));
  auto logits = torch::randn({1, 4, 16}, torch::requires_grad());
  vq->denormalize(vq->soft_decode(torch::softmax(logits, -1)).view({1, 16, 22, 3})).select(2, 0).sum().backward();
  REQUIRE(logits.grad().defined());
  CHECK(logits.grad().abs().sum().item<double>() > 0);
}

TEST_CASE("the absolute tokenizer configs keep their hash, standard ones read invariant features",
          "[tokenizer][invariant]") {
  auto tiny = load_job<TrainJobConfig>("configs/tokenizer/vq_tiny.yaml", {});
  CHECK(dump_config(tiny).find("representation") == std::string::npos);
  auto standard = load_job<TrainJobConfig>("configs/tokenizer/vq_standard.yaml", {});
  CHECK(standard.model.as<VqTokenizerConfig>().representation.type == "invariant");
  CHECK(dump_config(standard).find("representation") != std::string::npos);
  CHECK_THROWS_AS(load_job<TrainJobConfig>("configs/tokenizer/vq_tiny.yaml", {"model.representation.world_weight=1"}),
                  UserError);
}

TEST_CASE("invariant vq_tiny trains, reports the oracle control error and loads back", "[tokenizer][invariant][slow]") {
  TempDir t("vqinv");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data)).exit_code ==
          0);
  auto r = run_motionctl(fmt::format(
      "train configs/tokenizer/vq_tiny.yaml data.path={} run.root={} run.threads=1 run.name=inv optim.steps=60 "
      "model.representation.type=invariant model.representation.world_weight=0.5",
      data, t.path.string()));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  fs::path run = t.path / "tokenizer" / "inv";
  auto s = read_summary(run / "summary.csv");
  for (auto k : {"test_mpjpe_m", "val_oracle_root_3d_m", "val_oracle_planar_root_m", "val_oracle_body_point_m",
                 "val_oracle_control_error_m"})
    REQUIRE(s.count(k));
  CHECK(s["test_mpjpe_m"] < s["test_mean_pose_mpjpe_m"]);
  auto tok = load_vq_tokenizer(run.string());
  CHECK(tok.model->invariant());
  CHECK(tok.model->feature_mean.size(0) == 67);
  auto ds = MotionDataset::load(data);
  torch::NoGradGuard ng;
  auto b = ds->batch(ds->split("test"), 0, 4, torch::kCPU);
  auto y = tok.model->decode(tok.model->encode(b.joints.flatten(2), b.mask));
  CHECK(y.sizes() == b.joints.flatten(2).sizes());
  CHECK(torch::isfinite(y).all().item<bool>());
}

// ---------------------------------------------------------------- geometry terms (issue 13)

namespace {

// A tiny tokenizer trainer on random clips of 12, 28, 17 and 9 frames (whole clips,
// padded to 28, a multiple of the stride).
std::unique_ptr<Trainable> tiny_vq_trainer(TrainJobConfig& job, const std::string& extra) {
  return test::trainer_on_random_clips(
      job, "model:\n  type: vq_tokenizer\n  width: 16\n  code_dim: 8\n  codebook_size: 16\n  res_depth: 1\n" + extra,
      {12, 28, 17, 9});
}

}  // namespace

TEST_CASE("tokenizer: the geometry terms add exactly their part to the loss, in both representations",
          "[tokenizer][invariant]") {
  const std::string invariant = "  representation:\n    type: invariant\n    world_weight: 0.5\n";
  const std::string geo = "  geometry_loss:\n    bone_weight: 3.0\n    contact_weight: 2.0\n";
  for (const std::string& rep : {std::string(), invariant}) {
    INFO("representation: " << (rep.empty() ? "absolute" : "invariant"));
    TrainJobConfig a, b;
    auto off = tiny_vq_trainer(a, rep);
    auto on = tiny_vq_trainer(b, rep + geo);
    test::same_random_weights({off.get(), on.get()});
    // Same weights, same clips (window 0: no crops), eval mode so the codebook does not move.
    off->module().eval();
    on->module().eval();
    auto lo = off->loss({0, 1});
    auto ln = on->loss({0, 1});
    double part = -1;
    for (auto& [k, v] : ln.parts)
      if (k == "geometry") part = v.item<double>();
    REQUIRE(part > 0);
    for (auto& [k, v] : lo.parts) CHECK(k != "geometry");
    CHECK(ln.loss.item<double>() == Approx(lo.loss.item<double>() + part).epsilon(1e-5));
    // A reconstruction of random weights is wrong in every bone.
    CHECK(part > 1e-6);
  }
  // Off by default, and then absent from the dump: every tokenizer run keeps its name.
  auto small = load_job<TrainJobConfig>("configs/tokenizer/vq_small.yaml", {});
  CHECK(dump_config(small).find("geometry_loss") == std::string::npos);
  auto with = load_job<TrainJobConfig>("configs/tokenizer/vq_small.yaml", {"model.geometry_loss.bone_weight=1"});
  CHECK(dump_config(with).find("geometry_loss") != std::string::npos);
  // The standard tokenizer adopted bone 1000 / contact 3000 (docs/choices.md).
  auto standard = load_job<TrainJobConfig>("configs/tokenizer/vq_standard.yaml", {});
  CHECK(standard.model.as<VqTokenizerConfig>().geometry_loss.bone_weight == 1000.0);
  CHECK(standard.model.as<VqTokenizerConfig>().geometry_loss.contact_weight == 3000.0);
}

TEST_CASE("tokenizer: the whole-clip world loss adds exactly its part and leaves the codebook to the window pass",
          "[tokenizer][invariant]") {
  // Train mode, so the quantiser takes its EMA step in the window pass.
  const std::string rep = "  representation:\n    type: invariant\n    world_weight: 0.5\n";
  const std::string clip = "  clip_world_loss:\n    weight: 2.0\n    clips: 3\n";
  TrainJobConfig a, b;
  auto off = tiny_vq_trainer(a, rep);
  auto on = tiny_vq_trainer(b, rep + clip);
  test::same_random_weights({off.get(), on.get()});
  off->module().train();
  on->module().train();
  torch::manual_seed(5);
  auto lo = off->loss({1, 0, 2, 3});
  torch::manual_seed(5);
  auto ln = on->loss({1, 0, 2, 3});
  double part = -1;
  for (auto& [k, v] : ln.parts)
    if (k == "clip_world") part = v.item<double>();
  REQUIRE(part > 0);
  for (auto& [k, v] : lo.parts) CHECK(k != "clip_world");
  CHECK(ln.loss.item<double>() == Approx(lo.loss.item<double>() + 2.0 * part).epsilon(1e-5));
  // The whole-clip pass took no EMA step: both codebooks moved by the window pass only.
  auto* qa = dynamic_cast<VqTokenizerImpl*>(&off->module());
  auto* qb = dynamic_cast<VqTokenizerImpl*>(&on->module());
  REQUIRE(qa != nullptr);
  REQUIRE(qb != nullptr);
  CHECK(torch::equal(qa->quantizer->codebook, qb->quantizer->codebook));
  CHECK(torch::equal(qa->quantizer->cluster_size, qb->quantizer->cluster_size));
  CHECK(qb->quantizer->is_training());
  // Off by default (absent from the dump); absolute joints refuse it, naming the key.
  auto small = load_job<TrainJobConfig>("configs/tokenizer/vq_small.yaml", {});
  CHECK(dump_config(small).find("clip_world_loss") == std::string::npos);
  auto with = load_job<TrainJobConfig>("configs/tokenizer/vq_small.yaml", {"model.clip_world_loss.weight=1"});
  CHECK(dump_config(with).find("clip_world_loss") != std::string::npos);
  CHECK_THROWS_WITH(load_job<TrainJobConfig>("configs/tokenizer/vq_tiny.yaml", {"model.clip_world_loss.weight=1"}),
                    Catch::Contains("clip_world_loss"));
}
