// Shipped components (train/pretrained.*): ship a finished run, install it in place
// of training, refuse a checkpoint whose bytes changed; every committed entry of
// pretrained/manifest.yaml matches its config's hash and loads.
#include <catch2/catch.hpp>

#include <cstdlib>

#include "core/atomic_file.h"
#include "core/error.h"
#include "eval/t2m_evaluator.h"
#include "models/vq_tokenizer.h"
#include "samplers/flow_sampler.h"
#include "test_util.h"
#include "train/pretrained.h"
#include "train/train_job.h"

using namespace mc;
using namespace mc::test;

namespace {
// Sets an environment variable for the scope of a test.
struct ScopedEnv {
  std::string key;
  ScopedEnv(const std::string& k, const std::string& v) : key(k) { ::setenv(k.c_str(), v.c_str(), 1); }
  ~ScopedEnv() { ::unsetenv(key.c_str()); }
};

void fake_finished_run(const fs::path& dir) {
  write_file_atomic(dir / "config.yaml", "run:\n  experiment: prior\n");
  write_file_atomic(dir / "summary.csv", "key,value\nsteps,10\n");
  write_file_atomic(dir / "DONE", "");
  write_file_atomic(dir / "checkpoints" / "final.pt", "weights-bytes");
  write_file_atomic(dir / "checkpoints" / "last.pt", "optimiser state: not shipped");
  write_file_atomic(dir / "outputs" / "vocab.txt", "<pad>\n");
}
}  // namespace

TEST_CASE("pretrained: ship, install instead of training, refuse changed bytes", "[pretrained]") {
  TempDir tmp("pretrained");
  const fs::path run = tmp.path / "runs" / "prior" / "flow_x-0123456789ab", root = tmp.path / "shipped";
  fake_finished_run(run);
  PretrainedEntry e =
      ship_run(run, root, "configs/prior/flow_x.yaml", {"model.smooth_weight=2"}, "0123456789ab", "motionctl train configs/prior/flow_x.yaml");
  CHECK(e.experiment == "prior");
  CHECK(e.name == "flow_x-0123456789ab");
  CHECK(e.sha1 == file_sha1(run / "checkpoints" / "final.pt"));
  CHECK(fs::exists(root / "prior" / e.name / "outputs" / "vocab.txt"));
  CHECK_FALSE(fs::exists(root / "prior" / e.name / "checkpoints" / "last.pt"));  // no optimiser state shipped
  auto entries = read_pretrained_manifest(root);
  REQUIRE(entries.size() == 1);
  CHECK(entries[0].retrain == "motionctl train configs/prior/flow_x.yaml");
  CHECK(entries[0].overrides == std::vector<std::string>{"model.smooth_weight=2"});
  // Shipping again replaces the entry instead of adding one.
  ship_run(run, root, "configs/prior/flow_x.yaml", {"model.smooth_weight=2"}, "0123456789ab", "again");
  REQUIRE(read_pretrained_manifest(root).size() == 1);
  {
    // A retraining of the same config under a new hash supersedes the old entry and its
    // files; another override set of the same config is a different component and stays.
    TempDir t2("pretrained_supersede");
    const fs::path a = t2.path / "runs" / "prior" / "flow_x-aaaaaaaaaaaa", b = t2.path / "runs" / "prior" / "flow_x-bbbbbbbbbbbb";
    const fs::path c = t2.path / "runs" / "prior" / "flow_x-cccccccccccc", r2 = t2.path / "shipped";
    fake_finished_run(a);
    fake_finished_run(b);
    fake_finished_run(c);
    ship_run(a, r2, "configs/prior/flow_x.yaml", {}, "aaaaaaaaaaaa", "r");
    ship_run(c, r2, "configs/prior/flow_x.yaml", {"model.smooth_weight=2"}, "cccccccccccc", "r");
    ship_run(b, r2, "configs/prior/flow_x.yaml", {}, "bbbbbbbbbbbb", "r");
    const auto left = read_pretrained_manifest(r2);
    REQUIRE(left.size() == 2);
    CHECK(left[0].name == "flow_x-cccccccccccc");
    CHECK(left[1].name == "flow_x-bbbbbbbbbbbb");
    CHECK_FALSE(fs::exists(r2 / "prior" / "flow_x-aaaaaaaaaaaa"));
    CHECK(fs::exists(r2 / "prior" / "flow_x-cccccccccccc" / "checkpoints" / "final.pt"));
  }

  ScopedEnv env("MOTIONCTL_PRETRAINED", root.string());
  const fs::path target = tmp.path / "fresh" / "prior" / e.name;
  CHECK_FALSE(install_pretrained("prior", "other-name", "0123456789ab", target, nullptr));
  CHECK_FALSE(fs::exists(target));
  // The same name trained from another config (a named run whose config changed) is not installed.
  CHECK_FALSE(install_pretrained("prior", e.name, "ffffffffffff", target, nullptr));
  CHECK_FALSE(fs::exists(target));
  REQUIRE(install_pretrained("prior", e.name, "0123456789ab", target, nullptr));
  CHECK(slurp(target / "checkpoints" / "final.pt") == "weights-bytes");
  CHECK(fs::exists(target / "DONE"));
  CHECK_FALSE(install_pretrained("prior", e.name, "0123456789ab", target, nullptr));  // an existing run is never overwritten

  // A shipped checkpoint whose bytes changed is refused with the entry named.
  write_file_atomic(root / "prior" / e.name / "checkpoints" / "final.pt", "tampered");
  const fs::path other = tmp.path / "fresh2" / "prior" / e.name;
  try {
    install_pretrained("prior", e.name, "0123456789ab", other, nullptr);
    FAIL("a changed checkpoint was installed");
  } catch (const UserError& err) {
    CHECK(std::string(err.what()).find(e.name) != std::string::npos);
    CHECK(std::string(err.what()).find("SHA-1") != std::string::npos);
  }
  CHECK_FALSE(fs::exists(other));

  // A malformed manifest names the file and the missing key.
  write_file_atomic(root / "manifest.yaml", "components:\n  - experiment: prior\n    name: x\n");
  CHECK_THROWS_WITH(read_pretrained_manifest(root), Catch::Contains("manifest.yaml") && Catch::Contains("config"));
}

TEST_CASE("pretrained: installing a run installs the shipped runs it was trained on", "[pretrained]") {
  TempDir tmp("pretrained_deps");
  const fs::path root = tmp.path / "shipped";
  const fs::path base = tmp.path / "runs" / "prior" / "flow_b-aaaaaaaaaaaa";
  const fs::path cnet = tmp.path / "runs" / "prior" / "flow_controlnet_b-bbbbbbbbbbbb";
  fake_finished_run(base);
  fake_finished_run(cnet);
  const fs::path base_target = tmp.path / "fresh" / "prior" / "flow_b-aaaaaaaaaaaa";
  write_file_atomic(cnet / "outputs" / "controlnet_meta.yaml", fmt::format("base_run: {}\n", base_target.string()));
  CHECK(run_dependencies(cnet) == std::vector<std::string>{base_target.string()});
  CHECK(run_dependencies(base).empty());
  ship_run(base, root, "configs/prior/flow_b.yaml", {}, "aaaaaaaaaaaa", "retrain b");
  ship_run(cnet, root, "configs/prior/flow_controlnet_b.yaml", {}, "bbbbbbbbbbbb", "retrain c");
  ScopedEnv env("MOTIONCTL_PRETRAINED", root.string());
  const fs::path target = tmp.path / "fresh" / "prior" / "flow_controlnet_b-bbbbbbbbbbbb";
  REQUIRE(install_pretrained("prior", "flow_controlnet_b-bbbbbbbbbbbb", "bbbbbbbbbbbb", target, nullptr));
  CHECK(fs::exists(target / "DONE"));
  CHECK(fs::exists(base_target / "DONE"));  // the base came with it
}

TEST_CASE("pretrained: every shipped component matches its config's hash, loads, and ships what it needs",
          "[pretrained]") {
  const fs::path root = fs::path(MOTIONCTL_SOURCE_DIR) / "pretrained";
  auto entries = read_pretrained_manifest(root);
  for (const auto& e : entries) {
    INFO(e.name);
    const std::string config = std::string(MOTIONCTL_SOURCE_DIR) + "/" + e.config;
    // The run name and hash run_train gives the config today: a changed config (or default) no longer matches.
    CHECK(run_dir_of(config, e.overrides).filename().string() == e.name);
    CHECK(run_config_hash(config, e.overrides) == e.config_hash);
    REQUIRE(fs::exists(e.dir / "checkpoints" / "final.pt"));
    CHECK(file_sha1(e.dir / "checkpoints" / "final.pt") == e.sha1);
    CHECK(fs::exists(e.dir / "DONE"));
    // Every run it was trained on is shipped too, so installing it is enough to use it.
    for (const std::string& dep : run_dependencies(e.dir)) {
      INFO(dep);
      const fs::path d(dep);
      CHECK(find_pretrained(root, d.parent_path().filename().string(), d.filename().string()).has_value());
    }
    const std::string cfg = slurp(e.dir / "config.yaml");
    if (cfg.find("type: flow_prior") != std::string::npos) CHECK_NOTHROW(FlowPrior::load(e.dir.string()));
    if (cfg.find("type: vq_tokenizer") != std::string::npos) CHECK_NOTHROW(load_vq_tokenizer(e.dir.string()));
    if (cfg.find("type: t2m_evaluator") != std::string::npos) CHECK_NOTHROW(T2MEvaluator::load(e.dir.string()));
  }
  SUCCEED(fmt::format("{} shipped components checked", entries.size()));
}
