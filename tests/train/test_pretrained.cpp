// Shipped components (train/pretrained.*): ship a finished run, install it in place
// of training, refuse a checkpoint whose bytes changed; every committed entry of
// pretrained/manifest.yaml matches its config's hash and loads.
#include <catch2/catch.hpp>

#include <cstdlib>

#include "core/atomic_file.h"
#include "core/error.h"
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
  PretrainedEntry e = ship_run(run, root, "configs/prior/flow_x.yaml", "motionctl train configs/prior/flow_x.yaml");
  CHECK(e.experiment == "prior");
  CHECK(e.name == "flow_x-0123456789ab");
  CHECK(e.sha1 == file_sha1(run / "checkpoints" / "final.pt"));
  CHECK(fs::exists(root / "prior" / e.name / "outputs" / "vocab.txt"));
  CHECK_FALSE(fs::exists(root / "prior" / e.name / "checkpoints" / "last.pt"));  // no optimiser state shipped
  auto entries = read_pretrained_manifest(root);
  REQUIRE(entries.size() == 1);
  CHECK(entries[0].retrain == "motionctl train configs/prior/flow_x.yaml");
  // Shipping again replaces the entry instead of adding one.
  ship_run(run, root, "configs/prior/flow_x.yaml", "again");
  REQUIRE(read_pretrained_manifest(root).size() == 1);

  ScopedEnv env("MOTIONCTL_PRETRAINED", root.string());
  const fs::path target = tmp.path / "fresh" / "prior" / e.name;
  CHECK_FALSE(install_pretrained("prior", "other-name", target, nullptr));
  CHECK_FALSE(fs::exists(target));
  REQUIRE(install_pretrained("prior", e.name, target, nullptr));
  CHECK(slurp(target / "checkpoints" / "final.pt") == "weights-bytes");
  CHECK(fs::exists(target / "DONE"));
  CHECK_FALSE(install_pretrained("prior", e.name, target, nullptr));  // an existing run is never overwritten

  // A shipped checkpoint whose bytes changed is refused with the entry named.
  write_file_atomic(root / "prior" / e.name / "checkpoints" / "final.pt", "tampered");
  const fs::path other = tmp.path / "fresh2" / "prior" / e.name;
  try {
    install_pretrained("prior", e.name, other, nullptr);
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

TEST_CASE("pretrained: every shipped component matches its config's run name and loads", "[pretrained]") {
  const fs::path root = fs::path(MOTIONCTL_SOURCE_DIR) / "pretrained";
  auto entries = read_pretrained_manifest(root);
  for (const auto& e : entries) {
    INFO(e.name);
    // The name run_train gives the config today: a changed config (or default) no longer matches.
    CHECK(run_dir_of(std::string(MOTIONCTL_SOURCE_DIR) + "/" + e.config, {}).filename().string() == e.name);
    REQUIRE(fs::exists(e.dir / "checkpoints" / "final.pt"));
    CHECK(file_sha1(e.dir / "checkpoints" / "final.pt") == e.sha1);
    CHECK(fs::exists(e.dir / "DONE"));
    if (slurp(e.dir / "config.yaml").find("type: flow_prior") != std::string::npos)
      CHECK_NOTHROW(FlowPrior::load(e.dir.string()));
  }
  SUCCEED(fmt::format("{} shipped components checked", entries.size()));
}
