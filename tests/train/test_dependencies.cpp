// Declared dependencies (core/trained_runs.h, train/dependencies.h): which trained
// components a config names, that building a model or generator never trains one
// (an unresolved dependency is refused), and that the job layer's resolution finds a
// finished run and the component then loads it.
#include <catch2/catch.hpp>

#include <map>
#include <sstream>
#include <stdexcept>

#include <fmt/ranges.h>

#include "core/config.h"
#include "core/trained_runs.h"
#include "samplers/generator_test_util.h"
#include "samplers/motion_generator.h"
#include "test_util.h"
#include "train/dependencies.h"
#include "train/train_job.h"
#include "train/trainer.h"

using namespace mc;
using namespace mc::test;

namespace {

// What a config declares: what -> "run_dir|config|overrides".
struct Recorder : DependencyVisitor {
  std::map<std::string, std::string> seen;
  void operator()(const char* what, std::string& run_dir, std::string& config,
                  std::vector<std::string>& overrides) override {
    seen[what] = run_dir + "|" + config + "|" + fmt::format("{}", fmt::join(overrides, ","));
  }
};

template <class Cfg>
std::map<std::string, std::string> declared(Cfg& cfg) {
  Recorder r;
  for_each_dependency(cfg, r);
  return r.seen;
}

Component generator_of(const std::string& yaml) {
  GeneratorFile f;
  parse_config(config_from_string(yaml), f);
  return f.generator;
}

}  // namespace

TEST_CASE("dependencies: sections and components declare the trained components they name", "[train]") {
  // A ControlNet's frozen base: a section inside the model component.
  auto cn = load_job<TrainJobConfig>(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/prior/flow_controlnet_tiny.yaml",
                                     {"model.base.overrides=[optim.steps=3]"});
  auto d = declared(cn);
  REQUIRE(d.count("prior"));
  CHECK(d["prior"] == "|configs/prior/flow_tiny.yaml|optim.steps=3");
  // A token prior's tokenizer and an adapter's TMD prior.
  auto tmd = load_job<TrainJobConfig>(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/tmd/tmd_tiny.yaml", {});
  CHECK(declared(tmd).count("model.tokenizer"));
  auto ad = load_job<TrainJobConfig>(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/adapter/anchorkv_tiny.yaml", {});
  CHECK(declared(ad).count("model.tmd"));
  // A flow prior declares its text encoder; off, the declaration is empty (nothing to train).
  auto flow = load_job<TrainJobConfig>(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/prior/flow_tiny.yaml", {});
  CHECK(declared(flow)["model.text_encoder"] == "||");
  // Generators: an AnchorRoute generator with an adapter does not use (or train) its
  // default TMD prior; without one it does.
  auto with_adapter = generator_of("generator: {type: anchorroute, adapter_config: configs/adapter/anchorkv_tiny.yaml}");
  auto w = declared(*with_adapter.cfg);
  CHECK(w.count("adapter"));
  CHECK_FALSE(w.count("prior"));
  auto frozen = generator_of("generator: {type: anchorroute}");
  CHECK(declared(*frozen.cfg)["prior"] == "|configs/tmd/tmd_tiny.yaml|");
  CHECK(declared(*generator_of("generator: {type: tmd}").cfg).count("prior"));
  CHECK(declared(*generator_of("generator: {type: vq_reconstruction}").cfg).count("tokenizer"));
  CHECK(declared(*generator_of("generator: {type: flow, prior: {config: configs/prior/flow_tiny.yaml}}").cfg)
            .count("prior"));
  CHECK(declared(*generator_of("generator: {type: flow_controlnet, controlnet: {run_dir: x}}").cfg)["controlnet"] ==
        "x||");
}

TEST_CASE("dependencies: the run table gives a named run, the noted one, and refuses an unresolved one",
          "[train]") {
  CHECK(trained_run("x", "runs/given", "configs/a.yaml", {}) == "runs/given");
  const std::vector<std::string> ov = {"run.root=/tmp/nowhere-" + std::to_string(::getpid())};
  try {
    trained_run("model.tokenizer", "", "configs/never_resolved.yaml", ov);
    FAIL("an unresolved dependency was not refused");
  } catch (const std::logic_error& e) {
    const std::string msg = e.what();
    CHECK(msg.find("model.tokenizer") != std::string::npos);
    CHECK(msg.find("configs/never_resolved.yaml") != std::string::npos);
    CHECK(msg.find("resolve_dependencies") != std::string::npos);
  }
  note_trained_run("configs/never_resolved.yaml", ov, "runs/first");
  CHECK(trained_run("t", "", "configs/never_resolved.yaml", ov) == "runs/first");
  CHECK_THROWS_AS(trained_run("t", "", "configs/never_resolved.yaml", {}), std::logic_error);  // other overrides
  note_trained_run("configs/never_resolved.yaml", ov, "runs/second");  // the latest resolution wins
  CHECK(trained_run("t", "", "configs/never_resolved.yaml", ov) == "runs/second");
}

TEST_CASE("dependencies: a generator never trains its prior, the job's resolution installs it, then it loads",
          "[train][pretrained]") {
  TempDir t("deps");
  // flow_tiny is shipped in pretrained/: resolving it under a fresh runs root installs
  // the shipped run there (nothing is trained).
  Component g = generator_of(fmt::format(
      "generator: {{type: flow, prior: {{config: configs/prior/flow_tiny.yaml, overrides: [run.root={}]}}, "
      "sampler: {{steps: 2}}}}",
      t.path.string()));
  CHECK_THROWS_AS(as_generator(g).make(GeneratorContext{}), std::logic_error);
  CHECK(fs::is_empty(t.path));  // building refused, nothing trained or installed
  std::ostringstream log;
  resolve_dependencies(g, &log);
  INFO(log.str());
  CHECK(log.str().find("prior: " + t.path.string()) == 0);
  CHECK(log.str().find("(already trained)") != std::string::npos);
  auto gen = as_generator(g).make(GeneratorContext{});
  CHECK(gen->describe().find(t.path.string()) != std::string::npos);
  std::vector<ControlTask> tasks = {make_task("a", 12, "", 1)};
  auto out = gen->generate(tasks, 3);
  CHECK(out.world.size(0) == 1);
  CHECK(torch::isfinite(out.world).all().item<bool>());
}

TEST_CASE("lengthened training off: a longer job is named, hashed and trained as the config's own, shorter ones untouched",
          "[train]") {
  const std::string cfg = "configs/adapter/anchorkv_tiny.yaml";  // 75 steps, warm-up 30
  const std::vector<std::string> longer = {"optim.steps=4500"};
  const std::string plain_hash = run_config_hash(cfg, {}), longer_hash = run_config_hash(cfg, longer);
  const std::string shorter_hash = run_config_hash(cfg, {"optim.steps=30"});
  const fs::path plain_dir = run_dir_of(cfg, {}), longer_dir = run_dir_of(cfg, longer);
  REQUIRE(plain_hash != longer_hash);
  struct Reset {
    ~Reset() { set_lengthened_training(true); }
  } reset;
  set_lengthened_training(false);
  // Asking for 4,500 steps is the config's own 75-step run: same hash and directory.
  CHECK(run_config_hash(cfg, longer) == plain_hash);
  CHECK(run_dir_of(cfg, longer) == plain_dir);
  CHECK(run_dir_of(cfg, longer) != longer_dir);
  // Shorter runs and other overrides are untouched.
  CHECK(run_config_hash(cfg, {"optim.steps=30"}) != plain_hash);
  CHECK(run_config_hash(cfg, {"optim.steps=30"}) == shorter_hash);
  CHECK(run_config_hash(cfg, {"optim.lr=1e-4", "optim.steps=900"}) == run_config_hash(cfg, {"optim.lr=1e-4"}));
  // A warm-up at least as long as the config's steps is shortened with the cap (steps / 10).
  CHECK(run_config_hash(cfg, {"optim.steps=900", "optim.warmup=80"}) == run_config_hash(cfg, {"optim.warmup=7"}));
  set_lengthened_training(true);
  CHECK(run_config_hash(cfg, longer) == longer_hash);
}
