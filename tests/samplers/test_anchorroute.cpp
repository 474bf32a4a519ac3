// AnchorRoute end to end on a tiny tokenizer / TMD / AnchorKV trained in place: the
// `anchors` and `sparse_keyjoint` protocols, the `anchorroute` generator with and without
// the adapter, and RouteSolver's control error falling with its step count.
#include <catch2/catch.hpp>

#include <chrono>
#include <cmath>

#include "control/anchors.h"
#include "control/control_task.h"
#include "core/error.h"
#include "models/anchor_adapters.h"
#include "samplers/anchor_loss.h"
#include "samplers/motion_generator.h"
#include "samplers/tmd_sampler.h"
#include "test_util.h"
#include "train/motion_dataset.h"
#include "train/train_job.h"

using namespace mc;
using namespace mc::test;

namespace {

// type: the protocol type; yaml: its other keys.
std::vector<ControlTask> protocol_tasks(const std::string& type, const std::string& yaml, const MotionSet& set,
                                        const std::vector<size_t>& clips, uint64_t seed) {
  auto cfg = make_component_config("protocol", type);
  parse_config(config_from_string(yaml), *cfg);
  return dynamic_cast<ControlProtocol&>(*cfg).make_tasks(set, clips, seed);
}

std::unique_ptr<MotionGenerator> make_generator(const std::string& yaml) {
  auto cfg = make_component_config("generator", "anchorroute");
  parse_config(config_from_string(yaml), *cfg);
  return dynamic_cast<GeneratorConfig&>(*cfg).make({});
}

double control_error(const GeneratedMotions& g, const std::vector<ControlTask>& tasks, const Skeleton& sk) {
  std::vector<AnchorSet> sets;
  for (auto& t : tasks) sets.push_back(anchors_from_spec(t.spec, t.length, sk, t.source.data()));
  return mean_control_error(g.world, make_anchor_batch(sets)).item<double>();
}

}  // namespace

TEST_CASE("anchors protocol: family x K cells, values from the clip, specs every method reads", "[anchorkv]") {
  TempDir tmp("anchors_proto");
  const std::string data = (tmp.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=12", data))
              .exit_code == 0);
  auto ds = MotionDataset::load(data);
  const MotionSet& set = ds->set();
  std::vector<size_t> clips = {0, 1, 2, 3, 4, 5};
  auto tasks = protocol_tasks("anchors", "families: [root_3d, planar_root, body_point]\nanchor_counts: [2, 8]\n",
                              set, clips, 7);
  REQUIRE(tasks.size() == 6);  // cycle: one combination per clip
  CHECK(tasks[0].group == "family=root_3d/K=2");
  CHECK(tasks[1].group == "family=root_3d/K=8");
  CHECK(tasks[2].group == "family=planar_root/K=2");
  CHECK(tasks[5].group == "family=body_point/K=8");
  for (auto& t : tasks) {
    auto a = anchors_from_spec(t.spec, t.length, set.skeleton, t.source.data());
    CHECK(a.size() == (t.group.find("K=2") != std::string::npos ? 2 : 8));
    // Anchors hold the clip's own values: zero error on the ground truth.
    for (double e : anchor_errors(a, t.source.data(), set.num_joints())) CHECK(e < 1e-5);
  }
  auto again = protocol_tasks("anchors", "families: [root_3d, planar_root, body_point]\nanchor_counts: [2, 8]\n",
                              set, clips, 7);
  for (size_t i = 0; i < tasks.size(); ++i)
    CHECK(anchors_from_spec(tasks[i].spec, tasks[i].length, set.skeleton, tasks[i].source.data()) ==
          anchors_from_spec(again[i].spec, again[i].length, set.skeleton, again[i].source.data()));
  auto all = protocol_tasks("anchors", "families: [planar_root]\nanchor_counts: [2, 4, 8]\nassignment: all\n", set,
                            {0, 1}, 7);
  CHECK(all.size() == 6);
  auto sk = protocol_tasks("sparse_keyjoint", "ratio: 0.3\n", set, {0, 1}, 3);
  REQUIRE(sk.size() == 2);
  auto a = anchors_from_spec(sk[0].spec, sk[0].length, set.skeleton, sk[0].source.data());
  CHECK(a.joints() == std::vector<int>{0, 10, 11, 15, 20, 21});
  CHECK(static_cast<int>(a.times().size()) == std::max(1, static_cast<int>(std::lround(0.3 * sk[0].length))));
  CHECK_THROWS_AS(protocol_tasks("anchors", "anchor_counts: [500]\n", set, {0}, 1), UserError);
}

TEST_CASE("AnchorRoute end to end: AnchorKV beats the frozen TMD on control error, RouteSolver falls with steps",
          "[anchorkv][slow]") {
  auto t0 = std::chrono::steady_clock::now();
  TempDir tmp("anchorroute_e2e");
  const std::string data = (tmp.path / "fx.h5").string(), root = (tmp.path / "runs").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data))
              .exit_code == 0);
  std::vector<std::string> common = {"data.path=" + data, "run.root=" + root, "run.threads=1", "run.log_every=20",
                                     "run.checkpoint_every=1000"};
  auto ov = [&](std::vector<std::string> more) {
    auto v = common;
    v.insert(v.end(), more.begin(), more.end());
    return v;
  };
  auto tok = run_train("configs/tokenizer/vq_tiny.yaml",
                       ov({"optim.steps=60", "optim.warmup=5", "model.width=32", "model.code_dim=32",
                           "model.codebook_size=32"}));
  auto tmd = run_train("configs/tmd/tmd_tiny.yaml",
                       ov({"optim.steps=40", "optim.warmup=5", "model.width=64", "model.heads=2",
                           "model.text_width=32", "model.text_ff=64", "model.eval_t=[0.5]",
                           "model.tokenizer_run=" + tok.run_dir.string()}));
  auto adapter = run_train("configs/adapter/anchorkv_tiny.yaml",
                           ov({"optim.steps=400", "optim.warmup=20", "optim.batch_size=16", "optim.lr=2e-3", "model.rank=8",
                               "model.families=[root_3d]", "model.anchor_counts=[4, 8]",
                               "model.tmd_run=" + tmd.run_dir.string()}));
  REQUIRE(fs::exists(adapter.run_dir / "outputs" / "adapter_meta.yaml"));
  const double n_params = adapter.summary.at("trainable_params");
  CHECK(n_params > 0);
  CHECK(slurp(adapter.run_dir / "outputs" / "trainable_parameters.txt") == fmt::format("{}\n", int64_t(n_params)));
  auto loaded = load_anchor_adapter(adapter.run_dir.string());
  CHECK(loaded.trainable_parameters == int64_t(n_params));
  CHECK(loaded.prior->run_dir() == tmd.run_dir.string());

  auto ds = MotionDataset::load(data);
  const MotionSet& set = ds->set();
  std::vector<size_t> clips;
  for (int64_t i : ds->split("train")) {
    if (clips.size() == 8) break;
    clips.push_back(static_cast<size_t>(i));
  }
  auto tasks = protocol_tasks("anchors", "families: [root_3d]\nanchor_counts: [4, 8]\n", set, clips, 11);
  const std::string sampler = "sampler:\n  steps: 8\n  batch_size: 8\n";
  auto frozen = make_generator(fmt::format("prior_run: {}\n{}route:\n  steps: 0\n", tmd.run_dir.string(), sampler));
  auto g_frozen = frozen->generate(tasks, 3);
  std::vector<double> errs;
  GeneratedMotions g0;
  for (int steps : {0, 100, 200, 500}) {
    auto gen = make_generator(
        fmt::format("adapter_run: {}\n{}route:\n  steps: {}\n", adapter.run_dir.string(), sampler, steps));
    auto g = gen->generate(tasks, 3);
    REQUIRE(g.world.size(0) == 8);
    CHECK(g.lengths == std::vector<int>(g_frozen.lengths));
    bool noted = false;
    for (auto& n : g.notes) noted |= n == fmt::format("trainable parameters: {}", int64_t(n_params));
    CHECK(noted);
    errs.push_back(control_error(g, tasks, set.skeleton));
    if (steps == 0) g0 = g;
  }
  const double frozen_err = control_error(g_frozen, tasks, set.skeleton);
  WARN("control error: frozen TMD " << frozen_err << ", AnchorKV RS0 " << errs[0] << ", RS100 " << errs[1]
                                    << ", RS200 " << errs[2] << ", RS500 " << errs[3]);
  CHECK(errs[0] < frozen_err);
  CHECK(errs[0] > errs[1]);
  CHECK(errs[1] > errs[2]);
  CHECK(errs[2] > errs[3]);
  // Deterministic, and past each task's length the motion is zero.
  auto again = make_generator(fmt::format("adapter_run: {}\n{}route:\n  steps: 0\n", adapter.run_dir.string(), sampler))
                   ->generate(tasks, 3);
  CHECK(torch::equal(again.world, g0.world));
  // A task whose constraint anchors cannot express is refused by name.
  auto bad = tasks;
  bad[0].spec.items[0].type = "loop";
  try {
    frozen->generate(bad, 3);
    FAIL("expected a UserError");
  } catch (const UserError& e) {
    CHECK(std::string(e.what()).find(bad[0].id) != std::string::npos);
  }
  double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  WARN("AnchorRoute end to end: " << secs << " s");
}
