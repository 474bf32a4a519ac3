// The contrastive text encoder (text_clip) and the priors' model.text_encoder switch:
// InfoNCE and pooled retrieval on hand-computed cases, the switch off leaves every
// existing config's dump and hash as they were, a frozen pretrained encoder stays
// bit-identical under training while the rest moves, size mismatches fail clearly,
// and (slow) text_clip_tiny beats chance, a flow_tiny prior trains it on demand and
// loads for sampling from final.pt alone.
#include <catch2/catch.hpp>

#include <cmath>
#include <random>

#include "core/atomic_file.h"
#include "core/error.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "models/flow_prior.h"
#include "models/text_clip.h"
#include "samplers/flow_sampler.h"
#include "test_util.h"
#include "train/dependencies.h"
#include "models/motion_dataset.h"
#include "train/pretrained.h"
#include "train/train_job.h"
#include "models/trainable.h"

using namespace mc;
using namespace mc::test;

namespace {

MotionSet clip_random_set(int n, unsigned seed) {
  MotionSet m;
  m.skeleton = humanml3d_skeleton();
  m.fps = 20;
  m.t_max = 40;
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 0.5f);
  for (int i = 0; i < n; ++i) m.lengths.push_back(24 + (i * 7) % 17);
  m.joints.assign(n * m.clip_stride(), 0.0f);
  for (int i = 0; i < n; ++i) {
    for (int t = 0; t < m.lengths[i]; ++t)
      for (int j = 0; j < 22; ++j)
        for (int a = 0; a < 3; ++a) m.at(i, t, j)[a] = g(rng) + (a == 1 ? 0.9f : 0.0f);
    m.ids.push_back("clip" + std::to_string(i));
    m.splits.push_back(i % 4 == 3 ? "val" : "train");
    m.captions.push_back({"a person walks number " + std::to_string(i % 5), "a person jumps"});
  }
  NormStats st;
  st.joint_mean = {0.0f, 0.9f, 0.0f};
  st.joint_std = {0.5f, 0.5f, 0.5f};
  m.stats = st;
  return m;
}

const char* kClipModel =
    "model:\n  type: text_clip\n  text_width: 32\n  text_layers: 1\n  text_heads: 4\n  text_ff: 64\n"
    "  motion_width: 32\n  motion_layers: 1\n  motion_heads: 2\n  motion_ff: 64\n";

// A finished-looking text_clip run of random weights (config.yaml, final.pt, vocab).
void write_clip_run(const fs::path& dir, const std::shared_ptr<MotionDataset>& data) {
  TrainJobConfig job;
  parse_config(config_from_string(kClipModel), job);
  TrainContext ctx{data, torch::kCPU, &job, 0};
  torch::manual_seed(12);
  auto tr = make_trainable(job.model, ctx);
  write_file_atomic(dir / "config.yaml", dump_config(job));
  fs::create_directories(dir / "outputs");
  tr->save_artifacts(dir / "outputs");
  torch::serialize::OutputArchive ar;
  tr->module().save(ar);
  fs::create_directories(dir / "checkpoints");
  ar.save_to((dir / "checkpoints" / "final.pt").string());
}

}  // namespace

TEST_CASE("text_clip InfoNCE: symmetric cross entropy on a hand-computed 2 x 2 case", "[models]") {
  auto text = torch::tensor({{1.0, 0.0}, {0.0, 3.0}}, torch::kFloat64);
  auto motion = torch::tensor({{2.0, 0.0}, {0.6, 0.8}}, torch::kFloat64);  // rows normalise to e0, (0.6, 0.8)
  auto scale = torch::tensor(2.0, torch::kFloat64);
  // logits = 2 cos = [[2, 1.2], [0, 1.6]]
  auto ce = [](double own, double other) { return -std::log(std::exp(own) / (std::exp(own) + std::exp(other))); };
  const double t2m = 0.5 * (ce(2.0, 1.2) + ce(1.6, 0.0));
  const double m2t = 0.5 * (ce(2.0, 0.0) + ce(1.6, 1.2));
  CHECK(clip_infonce(text, motion, scale).item<double>() == Approx(0.5 * (t2m + m2t)).epsilon(1e-12));
  // Both captions the same string: each text's target is both motions, half each.
  auto same = torch::ones({2, 2}, torch::kBool);
  auto lse = [](double a, double b) { return std::log(std::exp(a) + std::exp(b)); };
  const double t2m_s = 0.5 * ((lse(2.0, 1.2) - 0.5 * (2.0 + 1.2)) + (lse(0.0, 1.6) - 0.5 * (0.0 + 1.6)));
  const double m2t_s = 0.5 * ((lse(2.0, 0.0) - 0.5 * (2.0 + 0.0)) + (lse(1.2, 1.6) - 0.5 * (1.2 + 1.6)));
  CHECK(clip_infonce(text, motion, scale, same).item<double>() == Approx(0.5 * (t2m_s + m2t_s)).epsilon(1e-12));
  CHECK(same_caption_matrix({"a", "b", "a"}).equal(
      torch::tensor({1, 0, 1, 0, 1, 0, 1, 0, 1}, torch::kInt64).to(torch::kBool).view({3, 3})));
  // The temperature is learned: the loss has a gradient in the scale.
  auto s = torch::tensor(2.0, torch::TensorOptions().dtype(torch::kFloat64).requires_grad(true));
  clip_infonce(text, motion, s).backward();
  CHECK(std::abs(s.grad().item<double>()) > 1e-6);
}

TEST_CASE("text_clip retrieval: rank of the own motion in pools, ties to the lower index", "[models]") {
  // Pool of 3: text 0 is closest to motion 0; text 1 to motion 2 (own second); text 2
  // ties motions 0 and 2 (identical), so its own (index 2) ranks after index 0.
  auto text = torch::tensor({{1.0, 0.0}, {0.0, 1.0}, {1.0, 1.0}, {1.0, 0.0}}, torch::kFloat64);
  auto motion = torch::tensor({{1.0, 1.0}, {0.5, 1.0}, {1.0, 1.0}, {5.0, 5.0}}, torch::kFloat64);
  // text 0 (e0): cos with m0 = .707, m1 = .447, m2 = .707 -> own first (tie, lower index).
  // text 1 (e1): m0 .707, m1 .894, m2 .707 -> own first.
  // text 2: m0 1, m1 .949, m2 1 -> m0 ties and wins -> own second.
  auto h = clip_retrieval(text, motion, 3, 3);  // the 4th pair is a partial pool, dropped
  REQUIRE(h.size() == 3);
  CHECK(h[0] == Approx(2.0 / 3.0));
  CHECK(h[1] == Approx(1.0));
  CHECK(h[2] == Approx(1.0));
}

TEST_CASE("model.text_encoder off: existing prior configs dump and hash as before", "[models]") {
  // The hashes the shipped priors (pretrained/manifest.yaml) were trained under.
  // flow_standard now sets the switch in its yaml; with it turned off by override it is
  // the jointly trained prior of before, under its old hash.
  CHECK(run_config_hash("configs/prior/flow_standard.yaml", {"model.text_encoder.config="}) == "a00a8e408998");
  CHECK(run_config_hash("configs/prior/flow_standard.yaml", {}) == "2963352f45e9");
  CHECK(run_config_hash("configs/prior/flow_tiny.yaml", {}) == "fc61388ed1df");
  auto job = load_job<TrainJobConfig>("configs/prior/flow_tiny.yaml", {});
  const std::string plain = dump_config(job);
  CHECK(plain.find("text_encoder") == std::string::npos);
  // On, it is in the dump (a different run), and the dump parses back to itself.
  auto on = load_job<TrainJobConfig>("configs/prior/flow_tiny.yaml",
                                     {"model.text_encoder.config=configs/text/text_clip_tiny.yaml"});
  const std::string d = dump_config(on);
  CHECK(d.find("text_encoder") != std::string::npos);
  CHECK(run_config_hash("configs/prior/flow_tiny.yaml", {"model.text_encoder.config=configs/text/text_clip_tiny.yaml"}) !=
        "fc61388ed1df");
  TrainJobConfig back;
  parse_config(config_from_string(d), back);
  CHECK(dump_config(back) == d);
  CHECK(back.model.as<FlowPriorConfig>().text_encoder.frozen);
  // frozen: false alone (no run named) would vanish from the dump: refused.
  std::string e = user_error_of([&] {
    load_job<TrainJobConfig>("configs/prior/flow_tiny.yaml", {"model.text_encoder.frozen=false"});
  });
  INFO(e);
  CHECK(e.find("text_encoder") != std::string::npos);
  // The text_clip configs give the text encoder the sizes of the priors they serve.
  auto tiny = load_job<TrainJobConfig>("configs/text/text_clip_tiny.yaml", {});
  auto stdc = load_job<TrainJobConfig>("configs/text/text_clip_standard.yaml", {});
  auto ptiny = load_job<TrainJobConfig>("configs/prior/flow_tiny.yaml", {});
  auto pstd = load_job<TrainJobConfig>("configs/prior/flow_standard.yaml", {});
  auto same_sizes = [](const TrainJobConfig& clip, const TrainJobConfig& prior) {
    auto a = clip.model.as<TextClipConfig>().text_encoder_options(10);
    auto b = prior.model.as<FlowPriorConfig>().text_encoder_options(10);
    return a.width == b.width && a.layers == b.layers && a.heads == b.heads && a.ff == b.ff &&
           a.max_words == b.max_words && a.dropout == b.dropout;
  };
  CHECK(same_sizes(tiny, ptiny));
  CHECK(same_sizes(stdc, pstd));
}

TEST_CASE("model.text_encoder: a frozen pretrained encoder stays bit-identical while the prior trains", "[models]") {
  TempDir dir("textenc_frozen");
  auto data = std::make_shared<MotionDataset>(clip_random_set(24, 3), "random");
  write_clip_run(dir.path / "clip", data);
  TextClipRun run = read_text_clip_run((dir.path / "clip").string());
  // The clip run's own text weights, through the same module type.
  TextEncoder ref(run.cfg.text_encoder_options(static_cast<int>(run.vocab.size())));
  load_text_clip_encoder(run, *ref, run.cfg.text_encoder_options(static_cast<int>(run.vocab.size())), "test");

  const std::string prior_model = fmt::format(
      "model:\n  type: flow_prior\n  depth: 1\n  width: 32\n  heads: 2\n  text_width: 32\n  text_layers: 1\n"
      "  text_heads: 4\n  text_ff: 64\n  text_encoder:\n    run_dir: {}\n",
      (dir.path / "clip").string());
  TrainJobConfig job;
  parse_config(config_from_string(prior_model), job);
  TrainContext ctx{data, torch::kCPU, &job, 0};
  torch::manual_seed(4);
  auto tr = make_trainable(job.model, ctx);
  auto& net = dynamic_cast<FlowPriorNetImpl&>(tr->module());
  REQUIRE(net.text_adapter);
  auto ref_p = ref->named_parameters(), got_p = net.text->named_parameters();
  REQUIRE(ref_p.size() == got_p.size());
  for (auto& kv : ref_p) CHECK(torch::equal(kv.value(), got_p[kv.key()]));
  // Not optimised: no text parameter among the trainable ones.
  auto params = tr->trainable_parameters();
  for (auto& p : params)
    for (auto& q : net.text->parameters()) CHECK_FALSE(p.is_same(q));
  CHECK(params.size() == net.parameters().size() - net.text->parameters().size());
  std::vector<torch::Tensor> before;
  for (auto& p : params) before.push_back(p.detach().clone());
  net.train();
  torch::optim::AdamW opt(params, torch::optim::AdamWOptions(1e-2));
  for (int s = 0; s < 3; ++s) {
    LossOutput out = tr->loss({0, 1, 2, 4, 5, 6});
    REQUIRE(std::isfinite(out.loss.item<double>()));
    opt.zero_grad();
    out.loss.backward();
    opt.step();
  }
  for (auto& kv : ref_p) CHECK(torch::equal(kv.value(), got_p[kv.key()]));
  for (auto& p : net.text->parameters()) CHECK_FALSE(p.grad().defined());
  CHECK_FALSE(net.text->is_training());  // eval mode (no dropout) though the bundle trains
  int moved = 0;
  for (size_t i = 0; i < params.size(); ++i) moved += !torch::equal(params[i], before[i]);
  CHECK(moved > static_cast<int>(params.size()) / 2);
  // The prior's vocabulary is the text encoder run's.
  TempDir out("textenc_out");
  tr->save_artifacts(out.path);
  CHECK(slurp(out.path / "vocab.txt") == slurp(dir.path / "clip" / "outputs" / "vocab.txt"));
  CHECK(slurp(out.path / "prior_meta.yaml").find("text_encoder_run: " + (dir.path / "clip").string()) !=
        std::string::npos);

  // Sizes that differ from the run's fail naming the key.
  TrainJobConfig bad;
  parse_config(config_from_string(fmt::format(
                   "model:\n  type: flow_prior\n  depth: 1\n  width: 32\n  heads: 2\n  text_width: 32\n"
                   "  text_layers: 2\n  text_heads: 4\n  text_ff: 64\n  text_encoder:\n    run_dir: {}\n",
                   (dir.path / "clip").string())),
               bad);
  TrainContext bctx{data, torch::kCPU, &bad, 0};
  std::string e = user_error_of([&] { make_trainable(bad.model, bctx); });
  INFO(e);
  CHECK(e.find("text_layers = 1") != std::string::npos);
  CHECK(e.find("text_layers = 2") != std::string::npos);
  // A run of another model type is refused.
  e = user_error_of([&] { read_text_clip_run((dir.path / "nothing").string()); });
  CHECK(e.find("does not exist") != std::string::npos);
}

TEST_CASE("model.text_encoder with frozen: false initialises from the run and trains the encoder", "[models]") {
  TempDir dir("textenc_ft");
  auto data = std::make_shared<MotionDataset>(clip_random_set(24, 5), "random");
  write_clip_run(dir.path / "clip", data);
  TrainJobConfig job;
  parse_config(config_from_string(fmt::format(
                   "model:\n  type: flow_prior\n  depth: 1\n  width: 32\n  heads: 2\n  text_width: 32\n"
                   "  text_layers: 1\n  text_heads: 4\n  text_ff: 64\n  text_encoder:\n    run_dir: {}\n"
                   "    frozen: false\n",
                   (dir.path / "clip").string())),
               job);
  TrainContext ctx{data, torch::kCPU, &job, 0};
  auto tr = make_trainable(job.model, ctx);
  auto& net = dynamic_cast<FlowPriorNetImpl&>(tr->module());
  CHECK(tr->trainable_parameters().size() == net.parameters().size());
  auto w0 = net.text->out->weight.detach().clone();
  torch::optim::AdamW opt(tr->trainable_parameters(), torch::optim::AdamWOptions(1e-2));
  LossOutput out = tr->loss({0, 1, 2, 4});
  opt.zero_grad();
  out.loss.backward();
  opt.step();
  CHECK_FALSE(torch::equal(w0, net.text->out->weight));
}

TEST_CASE("text_clip_tiny trains and retrieves val motions from their captions well above chance",
          "[models][slow]") {
  TempDir t("text_clip_tiny");
  TrainResult r = run_train("configs/text/text_clip_tiny.yaml",
                            {"run.root=" + t.path.string(), "run.threads=1"});
  INFO("val_top1 " << r.summary["val_top1"] << " val_top3 " << r.summary["val_top3"] << " val_nce "
                   << r.summary["val_nce"] << " temperature " << r.summary["temperature"]);
  REQUIRE(r.summary["val_pools"] >= 1);
  // One pool of 32 val clips; chance is 3/32 (top-3) and 1/32 (top-1). Measured:
  // 0.875 and 0.625 (deterministic for this config and seed).
  CHECK(r.summary["val_top3"] > 0.5);
  CHECK(r.summary["val_top1"] > 0.25);
  CHECK(r.summary["val_nce"] < std::log(32.0));  // better than uniform logits
  CHECK(fs::exists(r.run_dir / "outputs" / "vocab.txt"));
}

TEST_CASE("flow_tiny with model.text_encoder: trains text_clip on demand, keeps it frozen, loads for sampling",
          "[models][slow]") {
  TempDir t("textenc_prior");
  const std::string clip_ov = fmt::format(
      "[optim.steps=30, run.root={}, run.name=clip, run.threads=1, run.log_every=10, run.checkpoint_every=30]",
      t.path.string());
  const std::vector<std::string> ov = {"model.text_encoder.config=configs/text/text_clip_tiny.yaml",
                                       "model.text_encoder.overrides=" + clip_ov,
                                       "optim.steps=12",
                                       "optim.warmup=4",
                                       "run.root=" + t.path.string(),
                                       "run.name=prior",
                                       "run.threads=1",
                                       "run.log_every=6",
                                       "run.checkpoint_every=12"};
  TrainResult r = run_train("configs/prior/flow_tiny.yaml", ov);
  const fs::path clip_dir = t.path / "text" / "clip", prior_dir = t.path / "prior" / "prior";
  REQUIRE(r.run_dir == prior_dir);
  REQUIRE(fs::exists(clip_dir / "DONE"));
  REQUIRE(fs::exists(prior_dir / "DONE"));
  // Shipping the prior ships its text encoder run.
  auto deps = run_dependencies(prior_dir);
  REQUIRE(deps.size() == 1);
  CHECK(fs::path(deps[0]) == clip_dir);
  CHECK(slurp(prior_dir / "outputs" / "vocab.txt") == slurp(clip_dir / "outputs" / "vocab.txt"));

  // final.pt alone carries everything: the text weights are the clip run's, bit for bit.
  FlowPrior prior = FlowPrior::load(prior_dir.string());
  TextClipRun run = read_text_clip_run(clip_dir.string());
  const auto o = run.cfg.text_encoder_options(static_cast<int>(run.vocab.size()));
  TextEncoder ref(o);
  load_text_clip_encoder(run, *ref, o, "test");
  auto ref_p = ref->named_parameters(), got_p = prior.net()->text->named_parameters();
  REQUIRE(ref_p.size() == got_p.size());
  for (auto& kv : ref_p) CHECK(torch::equal(kv.value(), got_p[kv.key()]));
  // ... while the rest moved away from its initial weights (same seed, same draws).
  auto job = load_job<TrainJobConfig>("configs/prior/flow_tiny.yaml", ov);
  auto data = MotionDataset::load(resolve_data_path(job.data.path));
  TrainContext ctx{data, torch::kCPU, &job, 0};
  resolve_dependencies(job.model, nullptr);  // as train() does: the text_clip run, found
  torch::manual_seed(static_cast<uint64_t>(job.run.seed));
  auto fresh = make_trainable(job.model, ctx);
  auto init = fresh->module().named_parameters();
  auto trained = prior.net()->named_parameters();
  int moved = 0, total = 0;
  for (auto& kv : init) {
    if (kv.key().rfind("text.", 0) == 0) {
      CHECK(torch::equal(kv.value(), trained[kv.key()]));
      continue;
    }
    ++total;
    moved += !torch::equal(kv.value(), trained[kv.key()]);
  }
  INFO(moved << " of " << total << " non-text parameters moved");
  CHECK(moved == total);
  // Same config with the text_clip run already finished: the same prior (training it
  // on demand must not disturb the prior's random stream).
  std::vector<std::string> ov2 = ov;
  for (auto& o : ov2)
    if (o == "run.name=prior") o = "run.name=prior2";
  TrainResult r2 = run_train("configs/prior/flow_tiny.yaml", ov2);
  {
    FlowPrior again = FlowPrior::load(r2.run_dir.string());
    auto pa = prior.net()->parameters(), pb = again.net()->parameters();
    REQUIRE(pa.size() == pb.size());
    for (size_t i = 0; i < pa.size(); ++i) CHECK(torch::equal(pa[i], pb[i]));
  }
  auto cond = prior.encode_texts({"a person walks forward", "a person jumps"});
  CHECK(cond.sizes() == torch::IntArrayRef({2, 128}));
  CHECK(torch::isfinite(cond).all().item<bool>());
  CHECK((cond[0] - cond[1]).abs().max().item<double>() > 1e-6);
}
