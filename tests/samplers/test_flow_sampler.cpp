// Flow prior loading, classifier-free guidance, the Euler sampler and its step
// hook, non-finite detection, and `motionctl train` + `motionctl sample` end to end.
#include <catch2/catch.hpp>

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <random>

#include "core/atomic_file.h"
#include "core/config.h"
#include "core/error.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "samplers/flow_sampler.h"
#include "test_util.h"
#include "models/flow_prior_test_util.h"
#include "train/trainer.h"

using namespace mc;
using namespace mc::test;

namespace {

// Records what the sampler passes to each step, then takes the Euler step.
struct RecordingStepper : FlowStepper {
  std::vector<double> ts, t_nexts;
  int begins = 0;
  double max_hat_error = 0;
  torch::Tensor begin(const torch::Tensor& x0, const torch::Tensor& mask, const std::vector<int64_t>& ids) override {
    ++begins;
    (void)mask;
    (void)ids;
    return x0;
  }
  torch::Tensor step(const FlowStep& s) override {
    ts.push_back(s.t);
    t_nexts.push_back(s.t_next);
    // The straight path through x: x = t x1_hat + (1 - t) x0_hat.
    auto back = s.t * s.x1_hat() + (1 - s.t) * s.x0_hat();
    max_hat_error = std::max(max_hat_error, (back - s.x).abs().max().item<double>());
    return s.x + (s.t_next - s.t) * s.v;
  }
};

}  // namespace

TEST_CASE("FlowPrior::load: clear errors for missing, incomplete or foreign runs", "[flow]") {
  TempDir t("prior_load");
  auto missing = user_error_of([&] { FlowPrior::load((t.path / "nope").string()); });
  CHECK(missing.find("does not exist") != std::string::npos);
  fs::create_directories(t.path / "empty");
  auto incomplete = user_error_of([&] { FlowPrior::load((t.path / "empty").string()); });
  CHECK(incomplete.find("config.yaml' is missing") != std::string::npos);
  write_random_prior_run(t.path / "ok");
  fs::remove(t.path / "ok" / "checkpoints" / "final.pt");
  CHECK(user_error_of([&] { FlowPrior::load((t.path / "ok").string()); }).find("final.pt") != std::string::npos);
  write_random_prior_run(t.path / "ae", 40, "motion_autoencoder");
  CHECK(user_error_of([&] { FlowPrior::load((t.path / "ae").string()); }).find("not a flow prior") !=
        std::string::npos);
  write_random_prior_run(t.path / "good");
  FlowPrior p = FlowPrior::load((t.path / "good").string());
  CHECK(p.t_max() == 40);
  CHECK(p.num_joints() == 22);
  auto w = torch::randn({2, 5, 22, 3});
  CHECK(torch::allclose(p.denormalize(p.normalize(w)), w, 1e-5, 1e-5));
}

TEST_CASE("classifier-free guidance: scale 1 is the conditional, 0 the unconditional velocity", "[flow]") {
  TempDir t("prior_cfg");
  write_random_prior_run(t.path);
  FlowPrior p = FlowPrior::load(t.path.string());
  torch::manual_seed(6);
  auto x = torch::randn({3, 20, 22, 3});
  auto mask = torch::ones({3, 20}, torch::kBool);
  mask[1].narrow(0, 11, 9).fill_(false);
  auto tt = torch::tensor({0.1f, 0.5f, 0.9f});
  auto text = p.encode_texts({"a person walks forward", "a person jumps", "walks"});
  torch::NoGradGuard ng;
  auto vc = p.raw_velocity(x, tt, text, mask);
  auto vu = p.raw_velocity(x, tt, p.null_texts(3), mask);
  CHECK_FALSE(torch::allclose(vc, vu, 1e-4, 1e-4));  // the text matters
  // s = 1 skips the null-text half: the conditional call itself, bit for bit.
  CHECK(torch::equal(p.velocity(x, tt, text, mask, 1.0), vc));
  CHECK(torch::allclose(p.velocity(x, tt, text, mask, 0.0), vu, 1e-4, 1e-5));
  CHECK(torch::allclose(p.velocity(x, tt, text, mask, 2.5), vu + 2.5 * (vc - vu), 1e-4, 1e-4));
  // A scalar t broadcasts over the batch.
  CHECK(torch::allclose(p.velocity(x, torch::tensor(0.5f), text, mask, 1.0),
                        p.raw_velocity(x, torch::full({3}, 0.5f), text, mask), 1e-4, 1e-5));
}

TEST_CASE("Euler sampler: time grid, step hook, seeding and lengths", "[flow]") {
  TempDir t("prior_euler");
  write_random_prior_run(t.path);
  FlowPrior p = FlowPrior::load(t.path.string());
  FlowSamplerConfig cfg;
  CHECK(cfg.steps == 99);  // reference-facts §3: 100 grid points
  CHECK(cfg.cfg_scale == 2.5);
  cfg.steps = 5;
  cfg.batch_size = 2;
  std::vector<std::string> caps = {"a person walks", "a person jumps", "forward"};
  std::vector<int> lens = {40, 13, 27};
  RecordingStepper rec;
  auto r = sample_flow(p, caps, lens, cfg, 9, &rec);
  CHECK(rec.begins == 2);  // batches of 2 + 1
  REQUIRE(rec.ts.size() == 10);
  CHECK(rec.ts[0] == 0.0);
  CHECK(rec.ts[1] == Approx(0.2));
  CHECK(rec.t_nexts[4] == 1.0);
  CHECK(rec.max_hat_error < 1e-4);
  CHECK(r.world.sizes().vec() == std::vector<int64_t>{3, 40, 22, 3});
  CHECK(torch::isfinite(r.world).all().item<bool>());
  CHECK(r.world[1].narrow(0, 13, 27).abs().max().item<double>() == 0.0);  // padding is zero
  // The default (Euler) path equals the recorded one; batching does not change samples.
  cfg.batch_size = 3;
  auto euler = sample_flow(p, caps, lens, cfg, 9);
  CHECK(torch::allclose(euler.world, r.world, 1e-4, 1e-4));
  auto other = sample_flow(p, caps, lens, cfg, 10);
  CHECK_FALSE(torch::allclose(other.world, r.world, 1e-3, 1e-3));
  CHECK(user_error_of([&] { sample_flow(p, {"a"}, {41}, cfg, 1); }).find("1..40") != std::string::npos);

  MotionSet m = to_motion_set(p, r, caps, {"s0", "s1", "s2"});
  m.check("samples");
  CHECK(m.t_max == 40);
  CHECK(m.splits[0] == "sample");
  CHECK(m.captions[2][0] == "forward");
}

namespace {
// Records the CFG scale of every step, then takes the Euler step.
struct ScaleRecorder : FlowStepper {
  std::vector<double> scales;
  torch::Tensor step(const FlowStep& s) override {
    scales.push_back(s.cfg_scale);
    return s.x + (s.t_next - s.t) * s.v;
  }
};
FlowSamplerConfig sampler_config(const std::vector<std::string>& overrides) {
  FlowSamplerConfig cfg;
  parse_config(config_from_string("{}", "sampler", overrides), cfg);
  return cfg;
}
}  // namespace

TEST_CASE("cfg_interval: CFG only on the steps that start inside the interval, the default guides every step",
          "[flow]") {
  FlowSamplerConfig plain;
  for (double t : {0.0, 0.3, 0.7, 0.999}) CHECK(plain.scale_at(t) == 2.5);
  CHECK(dump_config(plain).find("cfg_interval") == std::string::npos);  // existing runs keep their hashes
  auto window = sampler_config({"cfg_interval.start=0.3", "cfg_interval.end=0.7"});
  CHECK(window.scale_at(0.29) == 1.0);
  CHECK(window.scale_at(0.3) == 2.5);
  CHECK(window.scale_at(0.69) == 2.5);
  CHECK(window.scale_at(0.7) == 1.0);
  CHECK(dump_config(window).find("cfg_interval") != std::string::npos);
  CHECK(window.describe_cfg() == "cfg 2.5 on t in [0.3, 0.7)");
  auto empty = user_error_of([] { sampler_config({"cfg_interval.start=0.6", "cfg_interval.end=0.6"}); });
  CHECK(empty.find("start (0.6) must be below end (0.6)") != std::string::npos);
  CHECK(user_error_of([] { sampler_config({"cfg_interval.end=1.5"}); }).find("cfg_interval.end") !=
        std::string::npos);

  TempDir t("prior_cfg_interval");
  write_random_prior_run(t.path);
  FlowPrior p = FlowPrior::load(t.path.string());
  std::vector<std::string> caps = {"a person walks", "a person jumps"};
  std::vector<int> lens = {40, 23};
  auto with = [&](std::vector<std::string> o) {
    o.push_back("steps=5");  // steps start at t = 0, 0.2, 0.4, 0.6, 0.8
    return sampler_config(o);
  };
  ScaleRecorder rec;
  auto windowed = sample_flow(p, caps, lens, with({"cfg_interval.start=0.5", "cfg_interval.end=0.7"}), 3, &rec);
  CHECK(rec.scales == std::vector<double>{1.0, 1.0, 1.0, 2.5, 1.0});
  // An interval no step starts in is the conditional sampler (s = 1) exactly.
  auto none = sample_flow(p, caps, lens, with({"cfg_interval.start=0.9"}), 3);
  auto conditional = sample_flow(p, caps, lens, with({"cfg_scale=1"}), 3);
  CHECK(torch::equal(none.world, conditional.world));
  // [0, 1) written out is the default; the window changes the sample.
  auto spelled = sample_flow(p, caps, lens, with({"cfg_interval.start=0", "cfg_interval.end=1"}), 3);
  auto guided = sample_flow(p, caps, lens, with({}), 3);
  CHECK(torch::equal(spelled.world, guided.world));
  CHECK_FALSE(torch::allclose(windowed.world, guided.world, 1e-4, 1e-4));
  CHECK_FALSE(torch::allclose(windowed.world, conditional.world, 1e-4, 1e-4));
}

TEST_CASE("non-finite network output is a UserError, never a file", "[flow]") {
  TempDir t("prior_nan");
  write_random_prior_run(t.path);
  FlowPrior p = FlowPrior::load(t.path.string());
  {
    torch::NoGradGuard ng;
    p.net()->transformer->head->bias.fill_(std::numeric_limits<float>::quiet_NaN());
  }
  FlowSamplerConfig cfg;
  cfg.steps = 3;
  auto msg = user_error_of([&] { sample_flow(p, {"a person walks"}, {10}, cfg, 1); });
  CHECK(msg.find("non-finite") != std::string::npos);
}

namespace {
double csv_column(const std::string& header, const std::string& row, const std::string& name) {
  std::stringstream hs(header), rs(row);
  std::string h, v;
  while (std::getline(hs, h, ',') && std::getline(rs, v, ','))
    if (h == name) return std::stod(v);
  return NAN;
}
}  // namespace

TEST_CASE("motionctl train flow_tiny then motionctl sample writes plausible motions", "[flow][slow]") {
  TempDir t("flow_e2e");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data)).exit_code ==
          0);
  auto tr = run_motionctl(fmt::format(
      "train configs/prior/flow_tiny.yaml data.path={} optim.steps=150 optim.batch_size=8 optim.warmup=20 run.log_every=10 "
      "run.checkpoint_every=50 run.root={} run.name=tiny run.threads=1",
      data, t.path.string()));
  INFO(tr.output);
  REQUIRE(tr.exit_code == 0);
  fs::path run = t.path / "prior" / "tiny";
  for (auto f : {"checkpoints/final.pt", "outputs/vocab.txt", "outputs/prior_meta.yaml", "DONE"})
    CHECK(fs::exists(run / f));
  std::stringstream metrics(slurp(run / "metrics.csv"));
  std::string header, first, line, last;
  std::getline(metrics, header);
  std::getline(metrics, first);
  while (std::getline(metrics, line))
    if (!line.empty()) last = line;
  double l0 = csv_column(header, first, "loss"), l1 = csv_column(header, last, "loss");
  INFO("loss " << l0 << " -> " << l1);
  CHECK(l1 < 0.8 * l0);
  CHECK(slurp(run / "summary.csv").find("val_fm") != std::string::npos);

  std::string out = (t.path / "samples.h5").string();
  auto s = run_motionctl(fmt::format("sample configs/sample/t2m_smoke.yaml prior.run_dir={} output={} "
                                     "texts.num_samples=4 sampler.steps=20 run.threads=1",
                                     run.string(), out));
  INFO(s.output);
  REQUIRE(s.exit_code == 0);
  MotionSet m = read_motion_file(out);
  REQUIRE(m.size() == 4);
  CHECK(m.provenance.generator == "motionctl sample");
  CHECK(m.provenance.seed == 11);
  CHECK(m.provenance.config.find("run_dir: \"" + run.string() + "\"") != std::string::npos);
  MotionSet src = read_motion_file(data);
  auto test_idx = src.indices_of_split("test");
  for (size_t i = 0; i < m.size(); ++i) {
    CHECK(m.splits[i] == "sample");
    CHECK(m.captions[i][0] == src.captions[test_idx[i]][0]);
    CHECK(m.lengths[i] == src.lengths[test_idx[i]]);
  }
  // Bone lengths relative to the skeleton's. 150 steps (batch 8: 24 s, where flow_tiny's
  // batch 32 took 173 s and measured the same ratio) of a tiny prior on joints
  // whose per-axis std is metres (the fixture walks up to 20 m) do not yet resolve
  // 5-50 cm bones: the bar is "far closer to a body than the prior's noise
  // denormalised" (the noise ratio is ~27 on the smoke fixture; the run measured ~5,
  // flow_tiny's 1000 steps reach ~1.5, see docs/choices.md).
  const Skeleton& sk = m.skeleton;
  auto bone_ratio = [&](auto&& pos, size_t clips, auto&& len) {
    double sum = 0;
    int n = 0;
    for (size_t i = 0; i < clips; ++i)
      for (int f = 0; f < len(i); ++f)
        for (int j = 1; j < sk.num_joints(); ++j) {
          const float *a = pos(i, f, j), *b = pos(i, f, sk.parents[j]);
          double d = 0;
          for (int k = 0; k < 3; ++k) d += (a[k] - b[k]) * (a[k] - b[k]);
          sum += std::sqrt(d) / sk.bone_lengths[j];
          ++n;
        }
    return sum / n;
  };
  CHECK(std::all_of(m.joints.begin(), m.joints.end(), [](float v) { return std::isfinite(v); }));
  double sample_ratio = bone_ratio([&](size_t i, int f, int j) { return m.at(i, f, j); }, m.size(),
                                   [&](size_t i) { return m.lengths[i]; });
  REQUIRE(m.stats.has_value());
  std::mt19937 rng(1);
  std::normal_distribution<float> normal;
  std::vector<float> noise(40 * 22 * 3);
  for (size_t k = 0; k < noise.size(); ++k) noise[k] = m.stats->joint_mean[k % 3] + m.stats->joint_std[k % 3] * normal(rng);
  double noise_ratio = bone_ratio([&](size_t, int f, int j) { return noise.data() + (f * 22 + j) * 3; }, 1,
                                  [](size_t) { return 40; });
  INFO("mean bone length / skeleton bone length: samples " << sample_ratio << ", denormalised noise " << noise_ratio);
  CHECK(sample_ratio > 0.3);
  CHECK(sample_ratio < 0.4 * noise_ratio);

  // prior.config: the prior is trained on demand through `motionctl train`'s path, once.
  std::string cfg_run = fmt::format(
      "sample configs/sample/t2m_smoke.yaml \"prior.overrides=[optim.steps=4, data.path={}, run.root={}, "
      "run.name=ondemand, run.threads=1]\" output={} texts.num_samples=2 sampler.steps=3 run.threads=1",
      data, (t.path / "od").string(), (t.path / "od.h5").string());
  auto od = run_motionctl(cfg_run);
  INFO(od.output);
  REQUIRE(od.exit_code == 0);
  CHECK(od.output.find("(trained)") != std::string::npos);
  CHECK(fs::exists(t.path / "od" / "prior" / "ondemand" / "DONE"));
  CHECK(read_motion_file((t.path / "od.h5").string()).size() == 2);
  auto again = run_motionctl(cfg_run);
  CHECK(again.exit_code == 0);
  CHECK(again.output.find("(already trained)") != std::string::npos);

}

TEST_CASE("motionctl sample: a missing prior run directory is exit 2 with a clear message", "[flow]") {
  TempDir t("flow_bad");
  auto bad = run_motionctl(fmt::format("sample configs/sample/t2m_smoke.yaml prior.run_dir={}/nope output={}/x.h5",
                                       t.path.string(), t.path.string()));
  CHECK(bad.exit_code == 2);
  CHECK(bad.output.find("does not exist") != std::string::npos);
  CHECK(bad.output.find("nope") != std::string::npos);
  CHECK_FALSE(fs::exists(t.path / "x.h5"));
  auto neither = run_motionctl(fmt::format("sample configs/sample/t2m_smoke.yaml prior.config=\\\"\\\" output={}/x.h5",
                                           t.path.string()));
  CHECK(neither.exit_code == 2);
  CHECK(neither.output.find("prior.run_dir") != std::string::npos);
}
