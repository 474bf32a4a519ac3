// The evaluator measures what it should on the fixture: FID of half vs half is
// small next to FID against corrupted copies, FID grows with joint noise and with
// time warping, R-precision of ground truth is far above chance, shuffled texts
// match worse than true pairs. Also eval/score command behaviour and bad input.
#include <catch2/catch.hpp>
#include <numeric>
#include <random>
#include <sstream>

#include "core/error.h"
#include "eval/eval_outputs.h"
#include "eval/evaluation.h"
#include "eval/t2m_evaluator.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

// One evaluator for the whole file, trained once (about a minute of CPU).
struct TrainedEvaluator {
  TempDir dir{"evaluator"};
  std::string data, run;
  MotionSet test;
  TrainedEvaluator() {
    data = (dir.path / "fx.h5").string();
    auto fx = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=1600", data));
    if (fx.exit_code != 0) throw std::runtime_error(fx.output);
    auto tr = run_motionctl(fmt::format(
        "train configs/eval/evaluator_smoke.yaml data.path={} run.root={} run.name=ev optim.steps=400 run.threads=1",
        data, dir.path.string()));
    if (tr.exit_code != 0) throw std::runtime_error(tr.output);
    run = (dir.path / "evaluator" / "ev").string();
    MotionSet all = read_motion_file(data);
    test = all.subset(all.indices_of_split("test"));
  }
};

TrainedEvaluator& trained() {
  static TrainedEvaluator t;
  return t;
}

MotionSet with_noise(const MotionSet& m, double sigma, uint64_t seed) {
  MotionSet out = m;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n(0.0, sigma);
  for (size_t i = 0; i < out.size(); ++i)
    for (int t = 0; t < out.lengths[i]; ++t)
      for (int j = 0; j < out.num_joints(); ++j)
        for (int c = 0; c < 3; ++c) out.at(i, t, j)[c] += static_cast<float>(n(rng));
  return out;
}

// Plays every clip `speed` times faster (linear interpolation), as a time warp.
MotionSet time_warped(const MotionSet& m, double speed) {
  MotionSet out = m;
  std::fill(out.joints.begin(), out.joints.end(), 0.0f);
  const int J = m.num_joints();
  for (size_t i = 0; i < m.size(); ++i) {
    int len = m.lengths[i];
    int new_len = std::max(10, static_cast<int>((len - 1) / speed) + 1);
    for (int t = 0; t < new_len; ++t) {
      double s = std::min<double>(t * speed, len - 1);
      int a = static_cast<int>(s), b = std::min(a + 1, len - 1);
      double w = s - a;
      for (int j = 0; j < J; ++j)
        for (int c = 0; c < 3; ++c)
          out.at(i, t, j)[c] = static_cast<float>((1 - w) * m.at(i, a, j)[c] + w * m.at(i, b, j)[c]);
    }
    out.lengths[i] = new_len;
  }
  return out;
}

double fid_between(const T2MEvaluator& ev, const MotionSet& a, const MotionSet& b) {
  return fid(ev.embed_motions(a, "a"), ev.embed_motions(b, "b"));
}

}  // namespace

// One test case (one process under ctest) so the evaluator is trained once.
TEST_CASE("evaluator on the fixture: metrics respond as they should, motionctl eval, bad inputs", "[eval][slow]") {
  auto& tr = trained();
  SECTION("FID, R-precision and matching") {
    T2MEvaluator ev = T2MEvaluator::load(tr.run);
    const MotionSet& test = tr.test;
    REQUIRE(test.size() >= 80);

    // Half vs half of the test split, against the first half corrupted.
    std::vector<size_t> first, second;
    for (size_t i = 0; i < test.size(); ++i) (i % 2 ? second : first).push_back(i);
    MotionSet a = test.subset(first), b = test.subset(second);
    double fid_halves = fid_between(ev, a, b);
    // Monotone in the corruption level, each against the untouched test split.
    std::vector<double> noise_fid, warp_fid;
    for (double sigma : {0.02, 0.06, 0.15}) noise_fid.push_back(fid_between(ev, test, with_noise(test, sigma, 5)));
    for (double speed : {1.5, 2.5, 4.0}) warp_fid.push_back(fid_between(ev, test, time_warped(test, speed)));
    // Half vs half is small next to half vs the other half corrupted.
    double fid_noisy_half = fid_between(ev, a, with_noise(b, 0.15, 9));
    double fid_warped_half = fid_between(ev, a, time_warped(b, 4.0));
    INFO("FID halves " << fid_halves << " vs noisy half " << fid_noisy_half << ", warped half " << fid_warped_half
                       << "; noise " << noise_fid[0] << " " << noise_fid[1] << " " << noise_fid[2] << "; warp "
                       << warp_fid[0] << " " << warp_fid[1] << " " << warp_fid[2]);
    CHECK(fid_halves < fid_noisy_half / 3);
    CHECK(fid_halves < fid_warped_half / 2);  // time warps move mc67 less than noise does
    CHECK(noise_fid[0] < noise_fid[1]);
    CHECK(noise_fid[1] < noise_fid[2]);
    CHECK(warp_fid[0] < warp_fid[1]);
    CHECK(warp_fid[1] < warp_fid[2]);

    // Ground truth retrieval: far above chance (3/32); shuffled texts match worse.
    EvalEmbeddings e = embed_for_eval(ev, test, "test", test, "test");
    EvalProtocol p;
    auto m = t2m_metrics(e, p, 1);
    INFO("R-precision top-3 " << m["r_precision_top3"] << ", matching " << m["matching"]);
    CHECK(m["r_precision_top3"] > 0.4);
    CHECK(m["r_precision_top1"] <= m["r_precision_top2"]);
    CHECK(m["r_precision_top2"] <= m["r_precision_top3"]);
    EvalEmbeddings shuffled = e;
    for (Eigen::Index i = 0; i < e.text.rows(); ++i) shuffled.text.row(i) = e.text.row((i + 7) % e.text.rows());
    auto ms = t2m_metrics(shuffled, p, 1);
    CHECK(ms["matching"] > m["matching"] + 0.5);
    CHECK(ms["r_precision_top3"] < m["r_precision_top3"]);
  }
  SECTION("motionctl eval writes replicated metrics; bad inputs exit 2") {
    TempDir t("evalcli");
    auto ev_cfg = t.path / "ev.yaml";
    // Point the eval job at the already trained evaluator run via its config.
    std::ofstream(ev_cfg) << slurp(fs::path(tr.run) / "config.yaml");
    std::string base = fmt::format("eval configs/eval/t2m_smoke.yaml eval.evaluator={} eval.reference={} run.root={}",
                                   ev_cfg.string(), tr.data, t.path.string());
    auto r = run_motionctl(base + " protocol.repeats=3");
    REQUIRE(r.exit_code == 0);
    CHECK(r.output.find("r_precision_top3") != std::string::npos);
    auto runs = fs::directory_iterator(t.path / "eval");
    fs::path run = runs->path();
    std::string csv = slurp(run / "metrics.csv");
    CHECK(csv.find("fid,") != std::string::npos);
    CHECK(csv.find(",3\n") != std::string::npos);  // n = 3 bootstrap resamples
    CHECK(fs::exists(run / "metrics.h5"));
    // The ground-truth row against itself: the reported FID is the full set's (0), its
    // spread comes from resamples (each > 0), so the interval is not +- 0; nor is
    // R-precision's, which on one pool of 32 used to repeat the same value.
    std::map<std::string, std::vector<double>> rows;
    {
      std::stringstream ss(csv);
      std::string line;
      std::getline(ss, line);
      while (std::getline(ss, line)) {
        std::vector<std::string> f;
        std::stringstream ls(line);
        for (std::string x; std::getline(ls, x, ',');) f.push_back(x);
        REQUIRE(f.size() == 5);
        rows[f[0]] = {std::stod(f[1]), std::stod(f[2]), std::stod(f[3]), std::stod(f[4])};
      }
    }
    CHECK(rows.at("fid")[0] == Approx(0.0).margin(1e-4));
    CHECK(rows.at("fid")[2] > 0.0);
    CHECK(rows.at("r_precision_top3")[2] > 0.0);
    CHECK(rows.at("matching")[2] > 0.0);
    // The per-resample values in metrics.h5 are what the spread summarises.
    auto reps = read_metric_results(run.string());
    REQUIRE(reps.at("fid").size() == 3);
    for (double v : reps.at("fid")) CHECK(v > rows.at("fid")[0]);

    // Wrong fps, NaN motions, missing evaluator, wrong shapes: exit 2, clear message.
    MotionSet bad = tr.test;
    bad.fps = 30;
    write_motion_file((t.path / "fps.h5").string(), bad);
    auto e1 = run_motionctl(base + fmt::format(" eval.motions={} run.name=x1", (t.path / "fps.h5").string()));
    CHECK(e1.exit_code == 2);
    CHECK(e1.output.find("fps") != std::string::npos);
    auto e2 = run_motionctl(base + " eval.evaluator=configs/eval/nope.yaml run.name=x2");
    CHECK(e2.exit_code == 2);
    CHECK(e2.output.find("nope.yaml") != std::string::npos);
    std::ofstream(t.path / "nan.h5") << "not hdf5";
    auto e3 = run_motionctl(base + fmt::format(" eval.motions={} run.name=x3", (t.path / "nan.h5").string()));
    CHECK(e3.exit_code == 2);
    CHECK(e3.output.find("nan.h5") != std::string::npos);
    auto e4 = run_motionctl(base + " eval.split=tset run.name=x4");
    CHECK(e4.exit_code == 2);
    CHECK(e4.output.find("did you mean 'test'") != std::string::npos);
  }
}

TEST_CASE("motionctl score: foot skating and control errors from a constraint spec", "[eval]") {
  TempDir t("score");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(
      run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=30", data)).exit_code ==
      0);
  // Pelvis keyframes taken from the clip itself: zero error; shifted by 0.3 m in x: 0.3 m.
  std::ofstream(t.path / "self.yaml")
      << "constraints:\n  - {type: keyframe, name: pelvis, joints: [pelvis], frames: [0, 5, "
         "10], from_source: true}\n";
  auto r = run_motionctl(
      fmt::format("score {} --constraints {} --source {} --csv", data, (t.path / "self.yaml").string(), data));
  INFO(r.output);
  REQUIRE(r.exit_code == 0);
  CHECK(r.output.find("avg_err,0\n") != std::string::npos);
  CHECK(r.output.find("foot_skating,") != std::string::npos);
  MotionSet m = read_motion_file(data);
  for (size_t i = 0; i < m.size(); ++i)
    for (int f : {0, 5, 10}) m.at(i, f, 0)[0] += 0.3f;
  write_motion_file((t.path / "shifted.h5").string(), m);
  auto s = run_motionctl(fmt::format("score {} --constraints {} --source {} --csv", (t.path / "shifted.h5").string(),
                                     (t.path / "self.yaml").string(), data));
  REQUIRE(s.exit_code == 0);
  CHECK(s.output.find("avg_err,0.3") != std::string::npos);
  CHECK(s.output.find("traj_err@0.2,1") != std::string::npos);
  CHECK(s.output.find("traj_err@0.5,0") != std::string::npos);
  auto bad = run_motionctl(fmt::format("score {} --constraints {}", data, (t.path / "missing.yaml").string()));
  CHECK(bad.exit_code == 2);

  // The bootstrap of `motionctl eval` scores selections without recompiling: the
  // identity selection gives evaluator_free_metrics; a selection equals the metrics of
  // the subset it names, repeats included.
  MotionSet src = read_motion_file(data);
  const std::string spec = (t.path / "self.yaml").string();
  EvalProtocol p;
  auto errors = control_entry_errors(m, "shifted", spec, &src);
  std::vector<JointsView> clips;
  for (size_t i = 0; i < m.size(); ++i) clips.push_back(joints_view(m, i));
  std::vector<size_t> all(m.size());
  std::iota(all.begin(), all.end(), 0);
  auto whole = evaluator_free_metrics(m, "shifted", p, spec, &src);
  auto sel = free_metrics_of_selection(clips, &errors, all, m.skeleton, m.fps, p);
  REQUIRE(sel.size() == whole.size());
  for (auto& [k, v] : whole) CHECK(sel.at(k) == Approx(v).margin(1e-12));
  const std::vector<size_t> pick = {3, 3, 7, 0, 12};
  auto picked = free_metrics_of_selection(clips, &errors, pick, m.skeleton, m.fps, p);
  std::vector<JointsView> sub_clips = {clips[3], clips[3], clips[7], clips[0], clips[12]};
  FootSkatingOptions fo;
  fo.fps = m.fps;
  CHECK(picked.at("foot_skating") == Approx(foot_skating_ratio(sub_clips, m.skeleton, fo)));
  CHECK(picked.at("avg_err") == Approx(0.3).margin(1e-5));
  CHECK_THROWS_AS(free_metrics_of_selection(clips, &errors, {m.size()}, m.skeleton, m.fps, p), mc::UserError);
  CHECK_THROWS_AS(free_metrics_of_selection(clips, &errors, {}, m.skeleton, m.fps, p), mc::UserError);
}

TEST_CASE("t2m_metrics: multimodality over caption groups cut to equal size, pools", "[eval]") {
  // 6 captions x (3 or 4) generations: groups are cut to 3 each; embeddings of a
  // text's generations differ by a known amount, so multimodality is known.
  EvalEmbeddings e;
  const int D = 4;
  std::vector<int> sizes = {3, 4, 3, 3, 4, 3};
  int n = 0;
  for (int s : sizes) n += s;
  e.motion = Embeddings::Zero(n, D);
  e.text = Embeddings::Zero(n, D);
  int row = 0;
  for (size_t c = 0; c < sizes.size(); ++c)
    for (int g = 0; g < sizes[c]; ++g, ++row) {
      e.motion(row, 0) = 10.0 * c;
      e.motion(row, 1) = g == 0 ? 0.0 : 2.0;  // first generation differs from the rest by 2
      e.text.row(row) = e.motion.row(row);
      e.captions.push_back(fmt::format("caption {}", c));
    }
  e.gt_motion = e.motion;
  EvalProtocol p;
  p.multimodality_pairs = 3;
  p.diversity_pairs = 10;
  auto m = t2m_metrics(e, p, 3);
  REQUIRE(m.count("multimodality"));
  CHECK(m["multimodality"] >= 0.0);
  CHECK(m["multimodality"] <= 2.0 + 1e-9);
  CHECK(m.count("r_precision_top1") == 0);  // fewer motions than one pool of 32
  CHECK(m["fid"] == Approx(0.0).margin(1e-6));
}
