// TMD transition rates and jumps (eqs. (21)-(23)), inverse-CDF sampling, and the
// token priors end to end: tokenizer + TMD + masked training, loading, sampling, generators.
#include <catch2/catch.hpp>

#include <chrono>
#include <cmath>

#include "core/error.h"
#include "models/token_prior.h"
#include "samplers/motion_generator.h"
#include "samplers/tmd_sampler.h"
#include "test_util.h"
#include "train/train_job.h"

using namespace mc;
using namespace mc::test;

namespace {

torch::Tensor random_distance(int64_t K, int64_t D, uint64_t seed) {
  torch::manual_seed(seed);
  auto e = torch::nn::functional::normalize(torch::randn({K, D}, torch::kFloat64),
                                            torch::nn::functional::NormalizeFuncOptions().dim(1));
  auto d = (2.0 - 2.0 * torch::matmul(e, e.t()).clamp(-1.0, 1.0)).pow(2);
  d.fill_diagonal_(0.0);
  return d;
}

}  // namespace

TEST_CASE("TMD rates: zero for tokens no closer to x1_hat than x_t, u(x_t) = 0, eq. (21) values", "[tmd]") {
  const int64_t K = 20;
  auto dist = random_distance(K, 5, 31);
  torch::manual_seed(32);
  auto xt = torch::randint(0, K, {4, 6}, torch::kInt64);
  auto x1 = torch::randint(0, K, {4, 6}, torch::kInt64);
  x1[0][0] = xt[0][0].item<int64_t>();  // already at the target: nothing may move
  const double c = 3.0, a = 0.9;
  for (double t : {0.05, 0.5, 0.9}) {
    auto u = tmd_transition_rates(dist, xt, x1, t, c, a);
    REQUIRE(u.sizes().vec() == std::vector<int64_t>{4, 6, K});
    CHECK((u >= 0).all().item<bool>());
    CHECK(u.gather(-1, xt.unsqueeze(-1)).abs().max().item<double>() == 0.0);
    CHECK(u[0][0].abs().max().item<double>() == 0.0);
    auto rows = torch::nn::functional::embedding(x1, dist);
    auto d_xt = rows.gather(-1, xt.unsqueeze(-1));
    auto no_closer = rows >= d_xt;
    CHECK(u.masked_select(no_closer).abs().max().item<double>() == 0.0);
    CHECK((u.masked_select(rows < d_xt) > 0).all().item<bool>());
    // One entry by hand: q_t(i | x1) beta'(t) (d(x_t, x1) - d(i, x1)).
    const int64_t b = 2, n = 3;
    const int64_t xi = xt[b][n].item<int64_t>(), ti = x1[b][n].item<int64_t>();
    double beta = c * std::pow(t / (1 - t), a), dbeta = c * a * std::pow(t / (1 - t), a - 1) / std::pow(1 - t, 2);
    double z = 0;
    for (int64_t j = 0; j < K; ++j) z += std::exp(-beta * dist[ti][j].item<double>());
    for (int64_t i = 0; i < K; ++i) {
      double gain = dist[ti][xi].item<double>() - dist[ti][i].item<double>();
      double expect = i == xi ? 0.0 : std::exp(-beta * dist[ti][i].item<double>()) / z * dbeta * std::max(0.0, gain);
      CHECK(u[b][n][i].item<double>() == Approx(expect).margin(1e-12));
    }
  }
}

TEST_CASE("TMD jump and inverse-CDF draws with given uniforms", "[tmd]") {
  auto probs = torch::tensor({0.0, 0.5, 0.0, 0.5}, torch::kFloat64);
  auto pick = [&](double u) { return categorical_from_uniform(probs, torch::tensor(u, torch::kFloat64)).item<int64_t>(); };
  CHECK(pick(0.0) == 1);
  CHECK(pick(0.49) == 1);
  CHECK(pick(0.5) == 3);
  CHECK(pick(0.999) == 3);
  // Unnormalised weights work the same.
  CHECK(categorical_from_uniform(probs * 7, torch::tensor(0.6, torch::kFloat64)).item<int64_t>() == 3);

  // Rates only toward token 2, total 2: P(jump) = 1 - exp(-h 2).
  auto xt = torch::tensor({0, 0, 1}, torch::kInt64);
  auto rates = torch::zeros({3, 4}, torch::kFloat64);
  rates[0][2] = 2.0;
  rates[1][2] = 2.0;
  const double h = 0.1, p = 1 - std::exp(-0.2);
  auto u_jump = torch::tensor({p - 1e-6, p + 1e-6, 0.0}, torch::kFloat64);
  auto out = tmd_jump(xt, rates, h, u_jump, torch::full({3}, 0.3, torch::kFloat64));
  CHECK(out[0].item<int64_t>() == 2);  // below the jump probability: moves
  CHECK(out[1].item<int64_t>() == 0);  // above it: stays
  CHECK(out[2].item<int64_t>() == 1);  // no rate at all: stays, whatever the uniform
}

// ---------------------------------------------------------------- end to end

TEST_CASE("tokenizer + TMD + masked priors train, load, sample and generate deterministically", "[tmd][slow]") {
  auto t0 = std::chrono::steady_clock::now();
  TempDir tmp("tmd_e2e");
  const std::string data = (tmp.path / "fx.h5").string(), root = (tmp.path / "runs").string();
  std::vector<std::string> tok_ov = {"data.path=" + data, "run.root=" + root, "run.threads=1", "optim.steps=40",
                                     "optim.warmup=5", "run.log_every=10", "run.checkpoint_every=20",
                                     "model.width=32", "model.code_dim=32", "model.codebook_size=32"};
  // The fixture is built on demand by run_train (fixture.num_clips is not a train key,
  // so build the small one first through the tokenizer's own data.fixture path).
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data))
              .exit_code == 0);
  auto tok = run_train("configs/tokenizer/vq_tiny.yaml", tok_ov);
  std::string tok_ov_yaml = "[";
  for (size_t i = 0; i < tok_ov.size(); ++i) tok_ov_yaml += (i ? ", " : "") + tok_ov[i];
  tok_ov_yaml += "]";
  std::vector<std::string> prior_ov = {"data.path=" + data, "run.root=" + root, "run.threads=1", "optim.steps=40",
                                       "optim.warmup=5", "run.log_every=10", "run.checkpoint_every=20",
                                       "model.width=64", "model.heads=2", "model.text_width=32",
                                       "model.text_ff=64", "model.eval_t=[0.5]"};
  auto tmd_ov = prior_ov;
  tmd_ov.push_back("model.tokenizer_run=" + tok.run_dir.string());
  auto tmd_run = run_train("configs/tmd/tmd_tiny.yaml", tmd_ov);
  REQUIRE(fs::exists(tmd_run.run_dir / "checkpoints" / "final.pt"));
  CHECK(std::isfinite(tmd_run.summary.at("val_ce")));
  CHECK(tmd_run.summary.at("val_ce") < std::log(32.0));  // better than the uniform guess over 32 codes
  // The masked prior finds the same tokenizer run through its training config.
  auto masked_ov = prior_ov;
  masked_ov.push_back("model.tokenizer_overrides=" + tok_ov_yaml);
  auto masked_run = run_train("configs/masked/masked_tiny.yaml", masked_ov);
  CHECK(std::isfinite(masked_run.summary.at("val_ce")));

  TokenPrior tmd = TokenPrior::load(tmd_run.run_dir.string());
  CHECK(tmd.is_tmd());
  CHECK(tmd.codebook_size() == 32);
  CHECK(tmd.tokenizer().run_dir == tok.run_dir.string());
  TokenPrior masked = TokenPrior::load(masked_run.run_dir.string());
  CHECK_FALSE(masked.is_tmd());
  CHECK(masked.tokenizer().run_dir == tok.run_dir.string());

  std::vector<std::string> caps = {"a person walks forward", "a person jumps", "someone waves"};
  std::vector<int> lens = {40, 13, 61};
  TmdSamplerConfig tc;
  tc.steps = 12;
  tc.batch_size = 2;
  auto a = sample_tmd(tmd, caps, lens, tc, 7);
  REQUIRE(a.world.sizes().vec() == std::vector<int64_t>{3, 61, 22, 3});
  CHECK(torch::isfinite(a.world).all().item<bool>());
  CHECK(a.tokens[0].size(0) == 10);
  CHECK(a.tokens[1].size(0) == 4);  // ceil(13 / 4)
  CHECK(a.tokens[2].size(0) == 16);
  CHECK(a.world[1].narrow(0, 13, 48).abs().max().item<double>() == 0.0);
  CHECK(a.world[1].narrow(0, 0, 13).abs().max().item<double>() > 0.0);
  tc.batch_size = 3;  // batching does not change a sample
  auto b = sample_tmd(tmd, caps, lens, tc, 7);
  CHECK(torch::equal(a.world, b.world));
  for (int i = 0; i < 3; ++i) CHECK(torch::equal(a.tokens[i], b.tokens[i]));
  auto c = sample_tmd(tmd, caps, lens, tc, 8);
  bool differs = false;
  for (int i = 0; i < 3; ++i) differs |= !torch::equal(a.tokens[i], c.tokens[i]);
  CHECK(differs);
  // The decoded motion is the tokenizer's decode of the returned tokens, trimmed.
  auto dec = tmd.decode_world(a.tokens[0]);
  CHECK(torch::allclose(dec.narrow(0, 0, 40), a.world[0].narrow(0, 0, 40), 1e-5, 1e-5));

  MaskedSamplerConfig mc_;
  mc_.steps = 5;
  auto m1 = sample_masked(masked, caps, lens, mc_, 3);
  auto m2 = sample_masked(masked, caps, lens, mc_, 3);
  CHECK(torch::isfinite(m1.world).all().item<bool>());
  CHECK(torch::equal(m1.world, m2.world));
  for (auto& tkn : m1.tokens) CHECK(((tkn >= 0) & (tkn < 32)).all().item<bool>());  // no [MASK] left
  CHECK(user_error_of([&] { sample_masked(tmd, caps, lens, mc_, 3); }).find("TMD prior") != std::string::npos);
  CHECK(user_error_of([&] { sample_tmd(tmd, {"a"}, {197}, tc, 3); }).find("1..196") != std::string::npos);

  // The registered generators: tasks in, world motions of the tasks' lengths out.
  std::vector<ControlTask> tasks(2);
  tasks[0].caption = "a person walks";
  tasks[0].length = 30;
  tasks[1].caption = "a person jumps";
  tasks[1].length = 45;
  auto gcfg = make_component_config("generator", "tmd");
  parse_config(config_from_string(fmt::format("prior_run: {}\nsampler:\n  steps: 6\n", tmd_run.run_dir.string())),
               *gcfg);
  auto gen = dynamic_cast<GeneratorConfig&>(*gcfg).make({});
  auto g1 = gen->generate(tasks, 5), g2 = gen->generate(tasks, 5);
  CHECK(g1.world.sizes().vec() == std::vector<int64_t>{2, 45, 22, 3});
  CHECK(g1.lengths == std::vector<int>{30, 45});
  CHECK(torch::equal(g1.world, g2.world));
  auto mcfg = make_component_config("generator", "masked");
  parse_config(config_from_string(fmt::format("prior_run: {}\nsampler:\n  steps: 4\n", tmd_run.run_dir.string())),
               *mcfg);
  CHECK(user_error_of([&] { dynamic_cast<GeneratorConfig&>(*mcfg).make({}); }).find("tmd_prior run") !=
        std::string::npos);

  double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  WARN("tokenizer + TMD + masked end to end: " << secs << " s");
}

TEST_CASE("TokenPrior::load: clear errors for missing or foreign runs", "[tmd]") {
  TempDir t("tmd_load");
  CHECK(user_error_of([&] { TokenPrior::load((t.path / "nope").string()); }).find("does not exist") !=
        std::string::npos);
  fs::create_directories(t.path / "empty");
  CHECK(user_error_of([&] { TokenPrior::load((t.path / "empty").string()); }).find("config.yaml' is missing") !=
        std::string::npos);
}

TEST_CASE("token prior configs parse, with the paper's beta and the right model types", "[tmd]") {
  for (const char* f : {"configs/tmd/tmd_tiny.yaml", "configs/tmd/tmd_small.yaml", "configs/tmd/tmd_paper.yaml"}) {
    auto job = load_job<TrainJobConfig>(f, {});
    CHECK(job.model.type == "tmd_prior");
    auto& m = job.model.as<TmdPriorConfig>();
    CHECK(m.beta_c == 3.0);
    CHECK(m.beta_a == 0.9);
    CHECK(m.is_tmd());
  }
  for (const char* f :
       {"configs/masked/masked_tiny.yaml", "configs/masked/masked_small.yaml", "configs/masked/masked_paper.yaml"}) {
    auto job = load_job<TrainJobConfig>(f, {});
    CHECK(job.model.type == "masked_prior");
    CHECK_FALSE(job.model.as<MaskedPriorConfig>().is_tmd());
  }
  auto bad = user_error_of([] { load_job<TrainJobConfig>("configs/tmd/tmd_tiny.yaml", {"model.heads=3"}); });
  CHECK(bad.find("heads") != std::string::npos);
}

// ---------------------------------------------------------------- path calibration (issue 15)

namespace {

// Codes sharing one direction (what an EMA codebook over non-centred features looks
// like): mean m plus small per-code noise, in `clusters` tight groups.
torch::Tensor clustered_codebook(int64_t K, int64_t D, int64_t clusters, uint64_t seed) {
  torch::manual_seed(seed);
  auto m = torch::randn({1, D});
  auto centres = m + 0.2 * torch::randn({clusters, D});
  auto which = torch::arange(K) % clusters;
  return centres.index_select(0, which) + 0.03 * torch::randn({K, D});
}

}  // namespace

TEST_CASE("TMD path: the paper's table is eq. (17) on the raw codes, stats match eq. (18)", "[tmd][calibration]") {
  auto cb = clustered_codebook(64, 16, 8, 1);
  auto paper = tmd_path_table(cb, TmdPathConfig{}, 3.0, 0.9);
  CHECK(paper.scale == 1.0);
  auto n = torch::nn::functional::normalize(cb.to(torch::kFloat64), torch::nn::functional::NormalizeFuncOptions().dim(1));
  auto d = (2.0 - 2.0 * torch::matmul(n, n.t()).clamp(-1.0, 1.0)).pow(2);
  d.fill_diagonal_(0.0);
  CHECK(torch::allclose(paper.dist.to(torch::kFloat64), d, 1e-5, 1e-6));
  for (double t : {0.1, 0.5, 0.9}) {
    auto st = tmd_path_stats(paper.dist, t, 3.0, 0.9);
    auto beta = tmd_beta(torch::tensor(t, torch::kFloat64), 3.0, 0.9);
    auto q = tmd_path_probs(paper.dist.to(torch::kFloat64), torch::arange(64), beta.expand({64}));  // [64, 64]
    CHECK(st.q_self == Approx(q.diagonal().mean().item<double>()).epsilon(1e-6));
    auto h = -(q * q.clamp_min(1e-300).log()).sum(1);
    CHECK(st.effective_codes == Approx(h.exp().mean().item<double>()).epsilon(1e-6));
  }
  // Uniform at t = 0: every code equally likely.
  CHECK(tmd_path_stats(paper.dist, 0.0, 3.0, 0.9).effective_codes == Approx(64.0).epsilon(1e-9));
}

TEST_CASE("TMD path calibration reaches q_0.9(x1|x1) >= 0.5 on random and clustered codebooks", "[tmd][calibration]") {
  for (uint64_t seed : {1, 2}) {
    auto clustered = clustered_codebook(256, 64, 16, seed);
    torch::manual_seed(seed);
    auto random = torch::randn({256, 64});
    for (auto* cb : {&clustered, &random}) {
      for (const char* metric : {"cosine", "centered_cosine", "whitened_cosine"}) {
        TmdPathConfig p;
        p.metric = metric;
        p.calibration = "q_target";
        auto cal = tmd_path_table(*cb, p, 3.0, 0.9);
        INFO(metric << " seed " << seed << " scale " << cal.scale);
        CHECK(cal.scale >= 1.0);
        auto st = tmd_path_stats(cal.dist, 0.9, 3.0, 0.9);
        CHECK(st.q_self >= 0.5 - 1e-6);
        // Monotone in t, and still uniform at t = 0.
        CHECK(tmd_path_stats(cal.dist, 0.5, 3.0, 0.9).q_self <= st.q_self + 1e-12);
        CHECK(tmd_path_stats(cal.dist, 0.0, 3.0, 0.9).q_self == Approx(1.0 / 256).epsilon(1e-9));
        // Only the scale changes the table for a given metric (s = 1: the metric's own table).
        TmdPathConfig plain = p;
        plain.calibration = "none";
        CHECK(torch::allclose(cal.dist, tmd_path_table(*cb, plain, 3.0, 0.9).dist * cal.scale, 1e-4, 1e-5));
      }
    }
    // The paper's path does not concentrate on the clustered codebook; calibration does.
    auto paper = tmd_path_stats(tmd_path_table(clustered, TmdPathConfig{}, 3.0, 0.9).dist, 0.9, 3.0, 0.9);
    CHECK(paper.q_self < 0.5);
  }
}

TEST_CASE("TMD path configs: tiny keeps the paper's path (and hash), standard calibrates", "[tmd][calibration]") {
  auto tiny = load_job<TrainJobConfig>("configs/tmd/tmd_tiny.yaml", {});
  CHECK(dump_config(tiny).find("calibration") == std::string::npos);
  CHECK(tiny.model.as<TmdPriorConfig>().path.calibration == "none");
  auto standard = load_job<TrainJobConfig>("configs/tmd/tmd_standard.yaml", {});
  const auto& p = standard.model.as<TmdPriorConfig>().path;
  CHECK(p.calibration == "q_target");
  CHECK(p.target_q == 0.5);
  CHECK(p.target_t == 0.9);
  CHECK(standard.model.as<TmdPriorConfig>().beta_c == 3.0);
}
