// What a run was built on (train/dependency_record.*): the record, the comparison
// with the dependencies resolved now, and make-like retraining of stale dependents
// by train() (transitively, on the finished, resolver and resume paths); a legacy run
// without a record is accepted once with a warning, then tracked.
#include <catch2/catch.hpp>

#include <yaml-cpp/yaml.h>

#include <sstream>

#include <fmt/ranges.h>

#include "core/atomic_file.h"
#include "data/fixture/fixture_build.h"
#include "samplers/generator_test_util.h"
#include "test_util.h"
#include "train/dependencies.h"
#include "train/dependency_record.h"
#include "train/pretrained.h"
#include "train/train_job.h"

using namespace mc;
using namespace mc::test;

namespace {

ResolvedDependency dep(const std::string& what, const std::string& run, const std::string& sha1) {
  return ResolvedDependency{what, run, "configs/x.yaml", {"optim.steps=2"}, sha1};
}

// How many times `needle` occurs in `hay`.
int count_of(const std::string& hay, const std::string& needle) {
  int n = 0;
  for (size_t at = hay.find(needle); at != std::string::npos; at = hay.find(needle, at + 1)) ++n;
  return n;
}

// A copy of a repository training config with `set` applied (dotted keys), written to
// `to`: a dependency whose file the test edits, as a researcher edits a config.
void write_config(const std::string& from, const fs::path& to, const std::vector<std::pair<std::string, std::string>>& set) {
  YAML::Node root = YAML::LoadFile(std::string(MOTIONCTL_SOURCE_DIR) + "/" + from);
  for (const auto& [key, value] : set) {
    const auto dot = key.find('.');
    YAML::Node section = root[key.substr(0, dot)];
    section[key.substr(dot + 1)] = YAML::Load(value);
  }
  YAML::Emitter e;
  e << root;
  write_file_atomic(to, std::string(e.c_str()) + "\n");
}

}  // namespace

TEST_CASE("dependency record: written and read back, changes named by run, then by what", "[train]") {
  TempDir t("deprec");
  const std::vector<ResolvedDependency> deps = {dep("prior", "runs/prior/flow_tiny-aaaaaaaaaaaa", std::string(40, 'a')),
                                                dep("model.text_encoder", "/x/y/text/clip", std::string(40, 'b'))};
  CHECK_FALSE(read_dependency_record(t.path).has_value());
  write_dependency_record(t.path, deps, "a note");
  auto back = read_dependency_record(t.path);
  REQUIRE(back.has_value());
  REQUIRE(back->size() == 2);
  CHECK((*back)[0].what == "prior");
  CHECK((*back)[0].run == deps[0].run);
  CHECK((*back)[0].config == "configs/x.yaml");
  CHECK((*back)[0].overrides == std::vector<std::string>{"optim.steps=2"});
  CHECK((*back)[1].sha1 == std::string(40, 'b'));
  CHECK(changed_dependencies(*back, deps).empty());
  // The runs root is no part of a dependency's identity.
  CHECK(run_key("runs/prior/flow_tiny-aaaaaaaaaaaa") == "prior/flow_tiny-aaaaaaaaaaaa");
  CHECK(run_key("/elsewhere/prior/flow_tiny-aaaaaaaaaaaa/") == "prior/flow_tiny-aaaaaaaaaaaa");
  auto moved = deps;
  moved[0].run = "/elsewhere/prior/flow_tiny-aaaaaaaaaaaa";
  CHECK(changed_dependencies(*back, moved).empty());
  CHECK(check_dependencies(t.path, moved).state == DependencyCheck::State::fresh);
  // Retrained in place: the same run, other weights.
  auto retrained = deps;
  retrained[1].sha1 = std::string(40, 'c');
  auto why = changed_dependencies(*back, retrained);
  REQUIRE(why.size() == 1);
  CHECK(why[0] == "model.text_encoder /x/y/text/clip bbbbbbbbbbbb, which is now cccccccccccc");
  CHECK(check_dependencies(t.path, retrained).state == DependencyCheck::State::stale);
  // Its config changed: another run of the same dependency.
  auto other = deps;
  other[0] = dep("prior", "runs/prior/flow_tiny-dddddddddddd", std::string(40, 'd'));
  why = changed_dependencies(*back, other);
  REQUIRE(why.size() == 1);
  CHECK(why[0].find("runs/prior/flow_tiny-aaaaaaaaaaaa aaaaaaaaaaaa, which is now runs/prior/flow_tiny-dddddddddddd "
                    "dddddddddddd") != std::string::npos);
  // A record that does not parse is a UserError naming the file and the way out.
  write_file_atomic(t.path / kDependencyRecord, "dependencies: [{what: prior}]\n");
  expect_user_error([&] { read_dependency_record(t.path); }, {kDependencyRecord, "run", "run.force=true"});
  write_file_atomic(t.path / kDependencyRecord, "dependencies: {a: [\n");
  expect_user_error([&] { check_dependencies(t.path, deps); }, {kDependencyRecord, "corrupt"});
}

TEST_CASE("dependency record: a legacy run is stale when its outputs name another run of a dependency, or a "
          "dependency finished after it",
          "[train]") {
  TempDir t("deprec_legacy");
  const auto now = std::vector<ResolvedDependency>{dep("prior", "runs/prior/flow_standard-2222", std::string(40, '2'))};
  CHECK(check_dependencies(t.path, {}).state == DependencyCheck::State::fresh);  // no dependency: nothing to check
  CHECK(check_dependencies(t.path, now).state == DependencyCheck::State::unrecorded);  // names nothing
  write_file_atomic(t.path / "outputs" / "controlnet_meta.yaml", "base_run: runs/prior/flow_standard-2222\n");
  CHECK(check_dependencies(t.path, now).state == DependencyCheck::State::unrecorded);  // the same run: unknown weights
  write_file_atomic(t.path / "outputs" / "controlnet_meta.yaml", "base_run: /old/root/prior/flow_standard-1111\n");
  const DependencyCheck c = check_dependencies(t.path, now);
  CHECK(c.state == DependencyCheck::State::stale);
  REQUIRE(c.reasons.size() == 1);
  CHECK(c.reasons[0].find("/old/root/prior/flow_standard-1111, which is now runs/prior/flow_standard-2222") !=
        std::string::npos);
  // A run of another experiment (a text encoder the outputs do not name) decides nothing.
  write_file_atomic(t.path / "outputs" / "controlnet_meta.yaml", "base_run: runs/text/clip\n");
  CHECK(check_dependencies(t.path, now).state == DependencyCheck::State::unrecorded);

  // make's rule on the finishing times DONE records: a dependency that finished after
  // the run did was trained again since; one that finished before (or a DONE that holds
  // no time) decides nothing.
  TempDir d("deprec_legacy_dep");
  const auto at = std::vector<ResolvedDependency>{dep("prior", d.path.string(), std::string(40, '2'))};
  write_file_atomic(t.path / "DONE", "2026-11-24T01:58:37Z\n");
  write_file_atomic(d.path / "DONE", "2026-11-23T22:51:29Z\n");
  CHECK(check_dependencies(t.path, at).state == DependencyCheck::State::unrecorded);
  write_file_atomic(d.path / "DONE", "2026-11-24T01:58:37Z\n");  // the same second: not after
  CHECK(check_dependencies(t.path, at).state == DependencyCheck::State::unrecorded);
  write_file_atomic(d.path / "DONE", "2026-11-24T02:10:00Z\n");
  const DependencyCheck later = check_dependencies(t.path, at);
  CHECK(later.state == DependencyCheck::State::stale);
  REQUIRE(later.reasons.size() == 1);
  CHECK(later.reasons[0].find("as it was before 2026-11-24T01:58:37Z, which was trained again at "
                              "2026-11-24T02:10:00Z") != std::string::npos);
  write_file_atomic(t.path / "DONE", "");
  CHECK(check_dependencies(t.path, at).state == DependencyCheck::State::unrecorded);
}

TEST_CASE("dependency record: the weights' fingerprint is final.pt's SHA-1 and follows a replaced file", "[train]") {
  TempDir t("deprec_sha");
  CHECK(weights_sha1(t.path).empty());
  write_file_atomic(t.path / "checkpoints" / "final.pt", "first weights");
  const std::string a = weights_sha1(t.path);
  CHECK(a == file_sha1(t.path / "checkpoints" / "final.pt"));
  CHECK(weights_sha1(t.path) == a);  // cached
  write_file_atomic(t.path / "checkpoints" / "final.pt", "other weights");  // atomic replace, as the trainer writes
  CHECK(weights_sha1(t.path) == file_sha1(t.path / "checkpoints" / "final.pt"));
  CHECK(weights_sha1(t.path) != a);
}

TEST_CASE("stale dependents: retraining a dependency retrains what was built on it, transitively, nothing else",
          "[train]") {
  // text encoder -> flow prior (frozen text encoder) -> ControlNet, each 2 steps on a
  // 60-clip fixture. The text encoder and the prior are named runs whose config files the
  // test edits, as a researcher does; the ControlNet is reached through a generator, as
  // a table row reaches it (the resolver's path).
  TempDir t("stale");
  const std::string data = (t.path / "fx.h5").string();
  build_fixture(std::string(MOTIONCTL_SOURCE_DIR) + "/configs/data/smoke.yaml",
                {"output=" + data, "fixture.num_clips=60", "fixture.max_frames=48", "fixture.t_max=48"}, false);
  const fs::path text_cfg = t.path / "text.yaml", base_cfg = t.path / "base.yaml";
  const std::vector<std::pair<std::string, std::string>> tiny = {
      {"data.path", data},  {"optim.steps", "2"},     {"optim.batch_size", "4"}, {"optim.warmup", "0"},
      {"run.threads", "1"}, {"run.log_every", "1"}, {"run.checkpoint_every", "2"}};
  auto text_with_seed = [&](int seed) {
    auto set = tiny;
    set.insert(set.end(), {{"run.name", "clip"}, {"run.seed", std::to_string(seed)}, {"model.eval_pool", "4"}});
    write_config("configs/text/text_clip_tiny.yaml", text_cfg, set);
  };
  auto base_with_seed = [&](int seed) {
    auto set = tiny;
    set.insert(set.end(), {{"run.name", "base"},
                           {"run.seed", std::to_string(seed)},
                           {"model.text_encoder", fmt::format("{{config: {}}}", text_cfg.string())}});
    write_config("configs/prior/flow_tiny.yaml", base_cfg, set);
  };
  text_with_seed(29);
  base_with_seed(3);
  const std::vector<std::string> cn_ov = {"model.base.config=" + base_cfg.string(), "data.path=" + data,
                                          "run.root=" + t.path.string(), "optim.steps=2", "optim.batch_size=4",
                                          "optim.warmup=0", "run.threads=1", "run.log_every=1",
                                          "run.checkpoint_every=2"};
  const fs::path text_dir = t.path / "text" / "clip", base_dir = t.path / "prior" / "base";

  TrainResult first = run_train("configs/prior/flow_controlnet_tiny.yaml", cn_ov);
  REQUIRE_FALSE(first.skipped);
  const fs::path cn_dir = first.run_dir;
  // Each run records what it was built on: what, run and final.pt's SHA-1.
  auto cn_rec = read_dependency_record(cn_dir);
  REQUIRE(cn_rec.has_value());
  REQUIRE(cn_rec->size() == 1);
  CHECK((*cn_rec)[0].what == "prior");
  CHECK(fs::path((*cn_rec)[0].run) == base_dir);
  CHECK((*cn_rec)[0].sha1 == file_sha1(base_dir / "checkpoints" / "final.pt"));
  auto base_rec = read_dependency_record(base_dir);
  REQUIRE(base_rec.has_value());
  REQUIRE(base_rec->size() == 1);
  CHECK((*base_rec)[0].what == "model.text_encoder");
  CHECK((*base_rec)[0].sha1 == file_sha1(text_dir / "checkpoints" / "final.pt"));
  REQUIRE(read_dependency_record(text_dir).has_value());
  CHECK(read_dependency_record(text_dir)->empty());

  // Nothing changed: reused on every path, nothing retrained.
  const std::string cn_weights = slurp(cn_dir / "checkpoints" / "final.pt");
  CHECK(run_train("configs/prior/flow_controlnet_tiny.yaml", cn_ov).skipped);
  GeneratorFile gf;
  parse_config(config_from_string(fmt::format(
                   "generator: {{type: flow_controlnet, controlnet: {{config: configs/prior/flow_controlnet_tiny.yaml, "
                   "overrides: [{}]}}}}",
                   fmt::join(cn_ov, ", "))),
               gf);
  Component& g = gf.generator;
  {
    std::ostringstream log;
    resolve_dependencies(g, &log);
    INFO(log.str());
    CHECK(log.str().find("controlnet: " + cn_dir.string() + " (already trained)") != std::string::npos);
  }
  CHECK(slurp(cn_dir / "checkpoints" / "final.pt") == cn_weights);

  // The text encoder retrained in place with another seed (its file edited, run.force=true):
  // the prior built on it is stale, and so is the ControlNet built on the prior.
  const std::string old_text = file_sha1(text_dir / "checkpoints" / "final.pt");
  const std::string old_base = file_sha1(base_dir / "checkpoints" / "final.pt");
  text_with_seed(30);
  REQUIRE_FALSE(run_train(text_cfg.string(), {"run.root=" + t.path.string(), "run.force=true"}).skipped);
  const std::string new_text = file_sha1(text_dir / "checkpoints" / "final.pt");
  REQUIRE(new_text != old_text);
  {
    std::ostringstream log;
    const auto deps = resolve_dependencies(g, &log);
    INFO(log.str());
    CHECK(log.str().find("controlnet: " + cn_dir.string() + " (trained)") != std::string::npos);
    REQUIRE(deps.size() == 1);
    CHECK(deps[0].sha1 == file_sha1(cn_dir / "checkpoints" / "final.pt"));
  }
  const std::string base_log = slurp(base_dir / "log.txt");
  CHECK(base_log.find(fmt::format("was trained on model.text_encoder {} {}, which is now {}: retraining",
                                  text_dir.string(), old_text.substr(0, 12), new_text.substr(0, 12))) !=
        std::string::npos);
  const std::string new_base = file_sha1(base_dir / "checkpoints" / "final.pt");
  CHECK(new_base != old_base);
  CHECK(read_dependency_record(base_dir)->at(0).sha1 == new_text);
  CHECK(slurp(cn_dir / "log.txt").find(fmt::format("which is now {}: retraining", new_base.substr(0, 12))) !=
        std::string::npos);
  CHECK(read_dependency_record(cn_dir)->at(0).sha1 == new_base);
  CHECK(slurp(cn_dir / "checkpoints" / "final.pt") != cn_weights);
  // ... and once retrained, reused again.
  CHECK(run_train("configs/prior/flow_controlnet_tiny.yaml", cn_ov).skipped);

  // A legacy run (trained before records): accepted with one warning naming the run and
  // the command that retrains it; the record is written then, so the warning is once.
  fs::remove(cn_dir / kDependencyRecord);
  CHECK(run_train("configs/prior/flow_controlnet_tiny.yaml", cn_ov).skipped);
  const std::string warned = slurp(cn_dir / "log.txt");
  CHECK(count_of(warned, "has no record of the components it was built on") == 1);
  CHECK(warned.find("motionctl train configs/prior/flow_controlnet_tiny.yaml") != std::string::npos);
  CHECK(warned.find("run.force=true`") != std::string::npos);
  REQUIRE(read_dependency_record(cn_dir).has_value());
  CHECK(read_dependency_record(cn_dir)->at(0).sha1 == new_base);
  CHECK(run_train("configs/prior/flow_controlnet_tiny.yaml", cn_ov).skipped);
  CHECK(count_of(slurp(cn_dir / "log.txt"), "has no record") == 1);

  // A run stopped half way is not resumed on a dependency that changed meanwhile: it
  // starts again from scratch (its record written anew).
  std::vector<std::string> cn4 = cn_ov;
  cn4.push_back("optim.steps=4");
  TrainLoopOptions stop;
  stop.stop_after = 2;
  const fs::path cn4_dir = run_train("configs/prior/flow_controlnet_tiny.yaml", cn4, stop).run_dir;
  REQUIRE(fs::exists(cn4_dir / "checkpoints" / "last.pt"));
  REQUIRE_FALSE(fs::exists(cn4_dir / "DONE"));
  base_with_seed(4);
  REQUIRE_FALSE(run_train(base_cfg.string(), {"run.root=" + t.path.string(), "run.force=true"}).skipped);
  REQUIRE_FALSE(run_train("configs/prior/flow_controlnet_tiny.yaml", cn4).skipped);
  const std::string cn4_log = slurp(cn4_dir / "log.txt");
  CHECK(cn4_log.find("was being trained on prior") != std::string::npos);
  CHECK(cn4_log.find("starting it again from scratch") != std::string::npos);
  CHECK(read_dependency_record(cn4_dir)->at(0).sha1 == file_sha1(base_dir / "checkpoints" / "final.pt"));
  CHECK(read_summary_csv(cn4_dir / "summary.csv").at("steps") == 4);
}
