// Paired decisions: the papers' group-mean averaging against a hand-computed case,
// Table 2's lifting errors over both camera items, the three-way verdict on
// synthetic paired data (known effect, reversed effect, none), calibrated A/A tests
// with one or two tasks per group (per-sample and FID), FID/KID on resampled
// indices equal to the plain metrics, samples.h5 round trip, per-sample R-precision
// pooling to t2m_metrics, the power formula, and common initial noise across steppers.
#include <catch2/catch.hpp>

#include <cmath>
#include <numeric>
#include <random>

#include "control/camera.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "data/data_test_util.h"
#include "experiments/experiment.h"
#include "experiments/paired.h"
#include "experiments/report.h"
#include "samplers/flow_sampler.h"
#include "models/flow_prior_test_util.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

// A synthetic row: n tasks in `groups`, one replicate, per-sample values v(i).
RowSamples synthetic_row(const std::vector<std::string>& groups, const std::vector<double>& v,
                         const std::string& metric) {
  RowSamples s;
  for (size_t i = 0; i < groups.size(); ++i) s.task_ids.push_back("t" + std::to_string(i));
  s.groups = groups;
  s.metrics.push_back({{metric, v}});
  s.seeds.push_back(1);
  return s;
}

}  // namespace

TEST_CASE("headline averaging: mean over task groups of group means, pooled kept apart", "[experiments]") {
  // Density 1 has three tasks, density 100% one: the paper's mean of group means
  // weights both settings equally, the pooled mean weights tasks.
  std::vector<std::string> groups = {"joint=pelvis/density=1", "joint=pelvis/density=1", "joint=pelvis/density=1",
                                     "joint=pelvis/density=100%"};
  std::map<std::string, std::vector<double>> ps = {{"avg_err", {0.1, 0.2, 0.3, 1.0}},
                                                   {"matching", {1.0, 2.0, 3.0, 6.0}},
                                                   {"control_error", {0.1, 0.2, 0.3, 1.0}},
                                                   {"control_entries", {1, 1, 2, 4}}};
  CHECK(*headline_value(ps, groups, "avg_err") == Approx((0.2 + 1.0) / 2));  // 0.6
  CHECK(*headline_value(ps, groups, "avg_err", true) == Approx(1.6 / 4));    // pooled 0.4
  // T2M metrics pool over samples, as the T2M scripts.
  CHECK(*headline_value(ps, groups, "matching") == Approx(3.0));
  // control_error is entry-weighted inside a group: (0.1 + 0.2 + 0.6) / 4 = 0.225, then (0.225 + 1.0) / 2.
  CHECK(*headline_value(ps, groups, "control_error") == Approx((0.225 + 1.0) / 2));
  CHECK(*headline_value(ps, groups, "control_error", true) == Approx((0.1 + 0.2 + 0.6 + 4.0) / 8));
  // A filter is one group component: density=1 only.
  CHECK(*headline_value(ps, groups, "avg_err@density=1") == Approx(0.2));
  CHECK(!headline_value(ps, groups, "avg_err@density=10"));  // "density=1" does not match "density=10"-style parts
  // NaN = not applicable: left out of its group.
  ps["avg_err"][0] = std::nan("");
  CHECK(*headline_value(ps, groups, "avg_err") == Approx((0.25 + 1.0) / 2));
  // AnchorRoute: K = 2 and K = 32 weigh the same whatever their task counts.
  std::vector<std::string> k = {"family=root3d/K=2", "family=root3d/K=32", "family=root3d/K=32",
                                "family=root3d/K=32"};
  std::map<std::string, std::vector<double>> ck = {{"control_error", {0.4, 0.0, 0.0, 0.0}},
                                                   {"control_entries", {2, 32, 32, 32}}};
  CHECK(*headline_value(ck, k, "control_error") == Approx(0.2));
}

TEST_CASE("lifting: Avg.Err-2D/3D over both camera items (keypose and 2D trajectory)", "[experiments]") {
  MotionSet data = random_motion_set({30}, {"test"});
  const int T = 30, J = data.num_joints();
  ControlTask task;
  task.id = "0";
  task.length = T;
  task.caption = "a person walks";
  task.source.assign(data.clip(0), data.clip(0) + static_cast<size_t>(T) * J * 3);
  ConstraintItem kp;
  kp.type = "camera_2d";
  kp.frames.kind = FrameSelection::Kind::list;
  kp.frames.list = {0};
  kp.has_camera = true;
  kp.camera = CameraParams{1.0, 10.0, 20.0, 0.0};
  kp.from_source = true;
  ConstraintItem tr = kp;
  tr.frames.list = {5, 10};
  tr.joints = {JointRef{0, ""}};
  task.spec.items = {kp, tr};
  // The generated motion is the source except the root at frame 10 (a trajectory entry, not the keypose),
  // moved 0.24 m along the camera's depth axis (invisible in 2D) and 0.12 m along its x axis (visible).
  MotionSet gen = data.subset({0});
  OrthoCamera cam{1.0, 10.0 * M_PI / 180, 20.0 * M_PI / 180, 0.0};
  Eigen::Matrix<double, 2, 3> P = cam.matrix();
  Eigen::Vector3d depth = P.row(0).transpose().cross(P.row(1).transpose()).normalized();
  Eigen::Vector3d xdir = P.row(0).transpose().normalized();
  Eigen::Vector3d delta = 0.24 * depth + 0.12 * xdir;
  float* p = gen.joints.data() + (static_cast<size_t>(10) * J + 0) * 3;
  for (int a = 0; a < 3; ++a) p[a] += static_cast<float>(delta[a]);
  EvalEmbeddings emb;
  emb.motion = Embeddings::Random(1, 4);
  emb.text = Embeddings::Random(1, 4);
  EvalProtocol proto;
  auto ps = row_sample_metrics(gen, emb, {task}, proto, 1);
  // 22 keypose entries + 2 trajectory entries; one of them is off by |delta| in 3D and 0.12 * scale in 2D.
  const double n = J + 2;
  CHECK(ps.at("avg_err_3d")[0] == Approx(delta.norm() / n).epsilon(1e-4));
  CHECK(ps.at("avg_err_2d")[0] == Approx(0.12 / n).epsilon(1e-3));
  // MPJPE reads the keypose frame only, which is untouched.
  CHECK(ps.at("mpjpe_3d")[0] == Approx(0.0).margin(1e-6));
  CHECK(ps.at("mpjpe_2d")[0] == Approx(0.0).margin(1e-6));
}

TEST_CASE("paired bootstrap: three-way verdicts on synthetic paired data", "[experiments]") {
  // 40 tasks in 4 groups; a large per-task spread shared by both rows (the task is hard
  // or easy for every method) and a small method effect: only pairing sees it.
  std::mt19937_64 rng(3);
  std::normal_distribution<double> task_sd(0.0, 1.0), noise(0.0, 0.02);
  std::vector<std::string> groups;
  std::vector<double> base, better, worse, same;
  for (int i = 0; i < 40; ++i) {
    groups.push_back("density=" + std::to_string(i % 4));
    const double b = 5.0 + task_sd(rng);
    base.push_back(b);
    better.push_back(b - 0.1 + noise(rng));
    worse.push_back(b + 0.1 + noise(rng));
    same.push_back(b + noise(rng));
  }
  RowSamples rb = synthetic_row(groups, base, "avg_err"), r_better = synthetic_row(groups, better, "avg_err"),
             r_worse = synthetic_row(groups, worse, "avg_err"), r_same = synthetic_row(groups, same, "avg_err");
  EvalProtocol p;
  BootstrapOptions o;
  auto holds = bootstrap_difference(r_better, &rb, "avg_err", nullptr, p, o);
  auto contra = bootstrap_difference(r_worse, &rb, "avg_err", nullptr, p, o);
  auto none = bootstrap_difference(r_same, &rb, "avg_err", nullptr, p, o);
  REQUIRE(holds);
  REQUIRE(contra);
  REQUIRE(none);
  CHECK(holds->paired);
  CHECK(holds->estimate == Approx(-0.1).margin(0.02));
  CHECK(better_verdict(*holds, "lower") == "holds");
  CHECK(better_verdict(*contra, "lower") == "contradicted");
  CHECK(better_verdict(*none, "lower") == "undecided");
  CHECK(better_verdict(*holds, "higher") == "contradicted");
  // Deterministic: the same seed draws the same interval.
  auto again = bootstrap_difference(r_better, &rb, "avg_err", nullptr, p, o);
  CHECK(again->lo == holds->lo);
  CHECK(again->hi == holds->hi);
  // Unpaired (the rows' tasks differ) the task spread swamps the effect: undecided.
  RowSamples shuffled = r_better;
  shuffled.task_ids[0] = "other";
  auto unpaired = bootstrap_difference(shuffled, &rb, "avg_err", nullptr, p, o);
  REQUIRE(unpaired);
  CHECK_FALSE(unpaired->paired);
  CHECK(better_verdict(*unpaired, "lower") == "undecided");
  CHECK(unpaired->hi - unpaired->lo > 5 * (holds->hi - holds->lo));
  // Undecided: the power formula from the paired SD, n = ((1.96 + 0.84) sd / effect)^2.
  const double n_needed = samples_to_decide(*none);
  const double sd = none->se * std::sqrt(40.0);
  CHECK(n_needed == Approx(std::ceil(std::pow(2.8 * sd / std::fabs(none->estimate), 2))));
  // Zero claims: against the tolerance.
  RowSamples exact = synthetic_row(groups, std::vector<double>(40, 1e-7), "avg_err");
  auto z = bootstrap_difference(exact, nullptr, "avg_err", nullptr, p, o);
  REQUIRE(z);
  CHECK(zero_verdict(*z, 1e-4) == "holds");
  CHECK(zero_verdict(*bootstrap_difference(rb, nullptr, "avg_err", nullptr, p, o), 1e-4) == "contradicted");
  // Replicate fallback: constant replicates (parameter counts) decide exactly.
  std::vector<double> pa = {100, 100, 100}, pb = {200, 200, 200};
  CHECK(better_verdict(replicate_difference(pa, &pb), "lower") == "holds");
  std::vector<double> ta = {1.0, 1.2, 0.9}, tb = {1.1, 0.95, 1.05};
  CHECK(better_verdict(replicate_difference(ta, &tb), "lower") == "undecided");
}

namespace {

// The groups of a ProjFlow table: 6 joints x 5 densities, tasks cycling through them.
std::vector<std::string> omni_groups(int n) {
  static const char* joints[] = {"pelvis", "l_foot", "r_foot", "head", "l_wrist", "r_wrist"};
  static const char* dens[] = {"1", "2", "5", "25%", "100%"};
  std::vector<std::string> g;
  for (int i = 0; i < n; ++i)
    g.push_back(fmt::format("joint={}/density={}", joints[i % 6], dens[(i / 6) % 5]));
  return g;
}

struct Calibration {
  double decided_rate = 0;  // A/A tests whose 95% interval excludes 0
  double se_ratio = 0;      // mean bootstrap SE / spread of the estimate over simulated datasets
};

// Repeated A/A experiments: `make(rng)` draws one dataset's two paired rows, equal in
// distribution (no effect), and the bootstrap tests their difference on `metric`.
template <class Make>
Calibration calibrate(int sims, const std::string& metric, const RealismReference* ref, Make make) {
  std::mt19937_64 rng(11);
  EvalProtocol p;
  BootstrapOptions o;
  o.draws = o.set_level_draws = 300;
  int decided = 0;
  std::vector<double> est, se;
  for (int k = 0; k < sims; ++k) {
    auto [a, b] = make(rng);
    o.seed = 1000 + k;
    auto t = bootstrap_difference(a, &b, metric, ref, p, o);
    REQUIRE(t);
    REQUIRE(t->paired);
    decided += better_verdict(*t, "lower") != "undecided";
    est.push_back(t->estimate);
    se.push_back(t->se);
  }
  const double m = std::accumulate(est.begin(), est.end(), 0.0) / sims;
  double ss = 0;
  for (double e : est) ss += (e - m) * (e - m);
  Calibration c;
  c.decided_rate = static_cast<double>(decided) / sims;
  c.se_ratio = std::accumulate(se.begin(), se.end(), 0.0) / sims / std::sqrt(ss / (sims - 1));
  return c;
}

}  // namespace

TEST_CASE("paired bootstrap: calibrated A/A tests with one or two tasks per group", "[experiments]") {
  // 30 task groups (joint x density) with 1-2 tasks each, as ProjFlow's tables at 32 or 60
  // tasks: resampling within groups of one task has no variance to draw from. The rows share
  // a large per-task effect (common random numbers) and differ by i.i.d. noise only.
  for (int n : {32, 60}) {
    CAPTURE(n);
    auto c = calibrate(300, "avg_err", nullptr, [n](std::mt19937_64& rng) {
      std::normal_distribution<double> g(0.0, 1.0);
      std::vector<double> va, vb;
      for (int i = 0; i < n; ++i) {
        const double task = 5.0 + 2.0 * g(rng);
        va.push_back(task + 0.1 * g(rng));
        vb.push_back(task + 0.1 * g(rng));
      }
      const auto groups = omni_groups(n);
      return std::make_pair(synthetic_row(groups, va, "avg_err"), synthetic_row(groups, vb, "avg_err"));
    });
    // Nominal 5% of A/A tests decided; drawing n_h of n_h tasks decided 84% at n = 32, 16% at 60.
    CHECK(c.decided_rate <= 0.10);
    CHECK(c.se_ratio > 0.8);
    CHECK(c.se_ratio < 1.4);
  }
  // FID under common random numbers: b = 0.8 a + 0.6 e is distributed as a, so E FID(a) = E FID(b).
  std::mt19937_64 rr(7);
  std::normal_distribution<double> g(0.0, 1.0);
  Embeddings ref(400, 6);
  for (int i = 0; i < ref.size(); ++i) ref.data()[i] = g(rr);
  RealismReference reference(ref);
  auto c = calibrate(150, "fid", &reference, [](std::mt19937_64& rng) {
    std::normal_distribution<double> g(0.0, 1.0);
    const int n = 32;
    Embeddings xa(n, 6), xb(n, 6);
    for (int i = 0; i < xa.size(); ++i) {  // both off the reference, as every generator is
      const double z = g(rng);
      xa.data()[i] = 0.5 + 1.3 * z;
      xb.data()[i] = 0.5 + 1.3 * (0.8 * z + 0.6 * g(rng));
    }
    const auto groups = omni_groups(n);
    RowSamples a = synthetic_row(groups, std::vector<double>(n, 0.0), "avg_err"), b = a;
    a.motion.push_back(xa);
    b.motion.push_back(xb);
    return std::make_pair(a, b);
  });
  CHECK(c.decided_rate <= 0.12);
  CHECK(c.se_ratio > 0.7);
  CHECK(c.se_ratio < 1.6);
}

TEST_CASE("FID and KID on resampled indices equal the plain metrics", "[experiments]") {
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 1.0);
  Embeddings ref(60, 6), x(25, 6);
  for (int i = 0; i < ref.size(); ++i) ref.data()[i] = g(rng);
  for (int i = 0; i < x.size(); ++i) x.data()[i] = 0.3 + 1.2 * g(rng);
  RealismReference rr(ref);
  CHECK(rr.fid(x) == Approx(fid(x, ref)).epsilon(1e-6));
  CHECK(rr.kid(x) == Approx(kid(x, ref)).epsilon(1e-6));
  // The bootstrap draws work through the same path: a draw of all rows is the plain value.
  RowSamples s;
  for (int i = 0; i < 25; ++i) s.task_ids.push_back(std::to_string(i)), s.groups.push_back("");
  s.motion.push_back(x);
  s.text.push_back(x);
  s.seeds.push_back(1);
  s.metrics.push_back({});
  std::vector<int> all(25);
  for (int i = 0; i < 25; ++i) all[i] = i;
  EvalProtocol p;
  CHECK(*sample_statistic(s, 0, "fid", all, &rr, p) == Approx(fid(x, ref)).epsilon(1e-6));
  CHECK(*sample_statistic(s, 0, "kid", all, &rr, p) == Approx(kid(x, ref)).epsilon(1e-6));
}

TEST_CASE("per-sample R-precision and matching pool to t2m_metrics' values", "[experiments]") {
  std::mt19937_64 rng(9);
  std::normal_distribution<double> g(0.0, 1.0);
  const int n = 20;
  EvalEmbeddings e;
  e.motion = Embeddings(n, 5);
  e.text = Embeddings(n, 5);
  for (int i = 0; i < e.motion.size(); ++i) e.motion.data()[i] = g(rng);
  for (int i = 0; i < e.text.size(); ++i) e.text.data()[i] = e.motion.data()[i] + 0.8 * g(rng);
  e.gt_motion = e.motion;
  for (int i = 0; i < n; ++i) e.captions.push_back("c" + std::to_string(i));
  EvalProtocol p;
  p.r_precision_pool = 8;  // two full pools, 4 samples outside
  p.diversity_pairs = 5;
  for (uint64_t seed : {1u, 2u, 3u}) {
    auto ref = t2m_metrics(e, p, seed);
    auto ps = per_sample_t2m(e.text, e.motion, p.r_precision_pool, seed);
    std::vector<std::string> groups(n, "");
    for (int k = 1; k <= 3; ++k) {
      const std::string key = "r_precision_top" + std::to_string(k);
      CHECK(*headline_value(ps, groups, key) == Approx(ref.at(key)));
    }
    CHECK(*headline_value(ps, groups, "matching") == Approx(ref.at("matching")));
  }
}

TEST_CASE("samples.h5 round trip", "[experiments]") {
  TempDir dir("paired_io");
  RowSamples s;
  s.task_ids = {"0|a", "1|b", "2|c"};
  s.groups = {"K=2", "family=x/K=8", ""};
  for (int r = 0; r < 2; ++r) {
    s.motion.push_back(Embeddings::Random(3, 4));
    s.text.push_back(Embeddings::Random(3, 4));
    s.seeds.push_back(1 + 1000 * r);
    s.metrics.push_back({{"avg_err", {0.1, std::nan(""), 0.3 + r}}, {"control_error@K=2", {1, 2, 3}}});
  }
  const std::string path = (dir.path / "samples.h5").string();
  write_row_samples(path, s);
  RowSamples b = read_row_samples(path);
  CHECK(b.task_ids == s.task_ids);
  CHECK(b.groups == s.groups);
  REQUIRE(b.replicates() == 2);
  CHECK(b.seeds == s.seeds);
  CHECK(b.motion[1].isApprox(s.motion[1]));
  CHECK(b.text[0].isApprox(s.text[0]));
  CHECK(std::isnan(b.metrics[0].at("avg_err")[1]));
  CHECK(b.metrics[1].at("avg_err")[2] == 1.3);
  CHECK(b.metrics[1].count("control_error@K=2") == 1);
  CHECK_THROWS_AS(read_row_samples((dir.path / "missing.h5").string()), UserError);
}

TEST_CASE("common random numbers: every flow step rule starts from the same initial noise", "[experiments]") {
  // Flow, ProjFlow, imputation and guidance rows all sample through sample_flow with the
  // replicate's seed: the initial noise x_0 of sample i is the same whatever the step rule
  // and caption, and the same as the seed's draw (DNO and the ControlNet draw the same
  // torch::randn({N, T, J, 3}) from that seed).
  TempDir t("paired_noise");
  write_random_prior_run(t.path);
  FlowPrior prior = FlowPrior::load(t.path.string());
  struct Recorder : FlowStepper {
    torch::Tensor x0;
    double scale = 1.0;
    torch::Tensor begin(const torch::Tensor& x, const torch::Tensor&, const std::vector<int64_t>&) override {
      x0 = x0.defined() ? torch::cat({x0, x.clone()}) : x.clone();
      return x;
    }
    torch::Tensor step(const FlowStep& s) override { return s.x + scale * (s.t_next - s.t) * s.v; }
  };
  FlowSamplerConfig cfg;
  cfg.steps = 2;
  cfg.batch_size = 2;
  Recorder a, b;
  b.scale = 0.5;  // a different step rule
  std::vector<int> lens = {20, 13, 17};
  sample_flow(prior, {"a person walks", "a person jumps", "forward"}, lens, cfg, 11, &a);
  cfg.cfg_scale = 1.0;
  sample_flow(prior, {"forward", "walks", "a person"}, lens, cfg, 11, &b);
  REQUIRE(a.x0.defined());
  CHECK(torch::equal(a.x0, b.x0));
  auto gen = at::make_generator<at::CPUGeneratorImpl>(11);
  CHECK(torch::equal(a.x0, torch::randn({3, 20, 22, 3}, gen, torch::TensorOptions())));
}

TEST_CASE("claims: a metrics list tests every per-group key, and all must hold", "[experiments]") {
  // 40 tasks over densities 1 and 2: row "a" beats "b" by 0.1 at density 1 and loses by
  // 0.1 at density 2; a shared per-task spread that only pairing removes.
  std::mt19937_64 rng(5);
  std::normal_distribution<double> task_sd(0.0, 1.0), noise(0.0, 0.01);
  std::vector<std::string> groups;
  std::vector<double> va, vb;
  for (int i = 0; i < 40; ++i) {
    const bool d1 = i % 2 == 0;
    groups.push_back(std::string("joint=pelvis/density=") + (d1 ? "1" : "2"));
    const double base = 3.0 + task_sd(rng);
    vb.push_back(base);
    va.push_back(base + (d1 ? -0.1 : 0.1) + noise(rng));
  }
  TableResult t;
  t.spec.table.id = "synthetic/table";
  RowResult a, b;
  a.row_id = "a";
  b.row_id = "b";
  a.samples = synthetic_row(groups, va, "avg_err");
  b.samples = synthetic_row(groups, vb, "avg_err");
  t.rows = {a, b};
  TempDir dir{"claims"};
  const std::string file = (dir.path / "claims.yaml").string();
  write_file_atomic(file,
             "claims:\n"
             "  - {id: d1, table: synthetic/table, kind: better, row: a, than: b, metrics: [\"avg_err@density=1\"],"
             " text: one}\n"
             "  - {id: both, table: synthetic/table, kind: better, row: a, than: b,"
             " metrics: [\"avg_err@density=1\", \"avg_err@density=2\"], text: both}\n"
             "  - {id: absent, table: synthetic/table, kind: better, row: a, than: b,"
             " metrics: [\"avg_err@density=1\", \"avg_err@density=7\"], text: a group no task has}\n");
  auto c = check_claims(file, {t});
  REQUIRE(c.size() == 3);
  CHECK(c[0].verdict == "holds");
  CHECK(c[1].verdict == "contradicted");  // holds at density 1, contradicted at density 2
  CHECK(c[1].evidence.find("avg_err@density=2 a − b") != std::string::npos);
  CHECK(c[2].verdict == "not run");
  CHECK(c[2].evidence.find("avg_err@density=7") != std::string::npos);
  // Both keys, or a list on a zero claim, are refused naming the claim.
  write_file_atomic(file,
             "claims:\n  - {id: twice, table: synthetic/table, kind: better, row: a, than: b, metric: avg_err,"
             " metrics: [avg_err], text: x}\n");
  CHECK_THROWS_WITH(check_claims(file, {t}), Catch::Contains("twice") && Catch::Contains("metrics"));
  write_file_atomic(file, "claims:\n  - {id: z, table: synthetic/table, kind: zero, row: a, metrics: [avg_err], text: x}\n");
  CHECK_THROWS_WITH(check_claims(file, {t}), Catch::Contains("'z'"));
}

TEST_CASE("claims: factor tests a <= f x b on the paired a - f b", "[experiments]") {
  // 40 tasks with a shared per-task spread; a = 0.6 b on every task, plus small noise.
  std::mt19937_64 rng(9);
  std::normal_distribution<double> task_sd(0.0, 0.3), noise(0.0, 0.01);
  std::vector<std::string> groups;
  std::vector<double> va, vb;
  for (int i = 0; i < 40; ++i) {
    groups.push_back(std::string("family=root_3d/K=") + (i % 2 ? "2" : "4"));
    const double base = 1.3 + task_sd(rng);
    vb.push_back(base);
    va.push_back(0.6 * base + noise(rng));
  }
  TableResult t;
  t.spec.table.id = "synthetic/table";
  RowResult a, b;
  a.row_id = "a";
  b.row_id = "b";
  a.samples = synthetic_row(groups, va, "control_error");
  b.samples = synthetic_row(groups, vb, "control_error");
  t.rows = {a, b};
  TempDir dir{"claims_factor"};
  const std::string file = (dir.path / "claims.yaml").string();
  write_file_atomic(file,
                    "claims:\n"
                    "  - {id: two_thirds, table: synthetic/table, kind: better, row: a, than: b, metric: control_error,"
                    " factor: 0.67, direction: lower, text: x}\n"
                    "  - {id: half, table: synthetic/table, kind: better, row: a, than: b, metric: control_error,"
                    " factor: 0.5, direction: lower, text: x}\n"
                    "  - {id: plain, table: synthetic/table, kind: better, row: a, than: b, metric: control_error,"
                    " direction: lower, text: x}\n");
  auto c = check_claims(file, {t});
  REQUIRE(c.size() == 3);
  CHECK(c[0].verdict == "holds");         // 0.6 b <= 0.67 b
  CHECK(c[1].verdict == "contradicted");  // 0.6 b > 0.5 b
  CHECK(c[1].evidence.find("control_error a − 0.5 × b") != std::string::npos);
  CHECK(c[2].verdict == "holds");
  CHECK(c[2].evidence.find("a − b") != std::string::npos);
  // The estimate is the mean of a - f b.
  double ma = 0, mb = 0;
  for (int i = 0; i < 40; ++i) ma += va[i] / 40, mb += vb[i] / 40;
  CHECK(c[1].evidence.find(fmt::format("{:.4g}", ma - 0.5 * mb)) != std::string::npos);
  // A factor on a higher-is-better claim, or a non-positive one, is refused naming the claim.
  write_file_atomic(file, "claims:\n  - {id: up, table: synthetic/table, kind: better, row: a, than: b,"
                          " metric: control_error, factor: 0.5, direction: higher, text: x}\n");
  CHECK_THROWS_WITH(check_claims(file, {t}), Catch::Contains("'up'") && Catch::Contains("factor"));
  write_file_atomic(file, "claims:\n  - {id: neg, table: synthetic/table, kind: better, row: a, than: b,"
                          " metric: control_error, factor: x, text: x}\n");
  CHECK_THROWS_WITH(check_claims(file, {t}), Catch::Contains("'neg'") && Catch::Contains("positive"));
}
