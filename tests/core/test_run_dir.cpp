// Run directories: one writer per run (a lock two processes contend for, stale
// locks of dead processes taken over), force redoing a run in its own directory,
// stale temporaries removed, the declared non-identity fields of `run:`, and the
// runs root a command hands to the components it trains.
#include <catch2/catch.hpp>

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <yaml-cpp/yaml.h>

#include "core/error.h"
#include "core/run_dir.h"
#include "test_util.h"
#include "train/train_job.h"
#include "train/trainer.h"

using namespace mc;
using namespace mc::test;

namespace {

// A child process that takes the lock of `dir`, reports on a pipe and waits to
// be killed.
pid_t hold_lock_in_child(const fs::path& dir) {
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  pid_t pid = ::fork();
  if (pid == 0) {
    ::close(fds[0]);
    int ok = 0;
    try {
      auto lock = RunLock::acquire(dir);
      ok = 1;
      (void)!::write(fds[1], &ok, sizeof ok);
      for (;;) ::pause();
    } catch (...) {
      (void)!::write(fds[1], &ok, sizeof ok);
    }
    ::_exit(0);
  }
  ::close(fds[1]);
  int ok = 0;
  REQUIRE(::read(fds[0], &ok, sizeof ok) == sizeof ok);
  ::close(fds[0]);
  REQUIRE(ok == 1);
  return pid;
}

}  // namespace

TEST_CASE("a run directory has one writer: a second process is refused with the holder's pid", "[run_dir]") {
  TempDir t("lock");
  RunConfig rc;
  rc.root = t.path.string();
  rc.experiment = "e";
  rc.name = "r";
  const fs::path dir = RunDir::path_of(rc, "unused");
  const pid_t child = hold_lock_in_child(dir);

  try {
    RunDir::open(rc, "a: 1\n", {}, "unused");
    FAIL("a locked run directory was opened");
  } catch (const UserError& e) {
    const std::string msg = e.what();
    CHECK(msg.find(dir.string()) != std::string::npos);
    CHECK(msg.find(fmt::format("pid {}", child)) != std::string::npos);
  }
  // run.force never deletes a run in use.
  fs::create_directories(dir / "checkpoints");
  { std::ofstream(dir / "checkpoints" / "last.pt") << "state"; }
  rc.force = true;
  CHECK_THROWS_AS(RunDir::open(rc, "a: 1\n", {}, "unused"), UserError);
  CHECK(fs::exists(dir / "checkpoints" / "last.pt"));
  rc.force = false;

  // The holder dies without cleaning up (kill -9): its lock file stays, with its
  // pid, but the lock went with it and the next process takes it over.
  ::kill(child, SIGKILL);
  int status = 0;
  ::waitpid(child, &status, 0);
  REQUIRE(fs::exists(dir / ".lock"));
  CHECK(slurp(dir / ".lock") == fmt::format("{}\n", child));
  {
    RunDir run = RunDir::open(rc, "a: 1\n", {}, "unused");
    CHECK(slurp(dir / ".lock") == fmt::format("{}\n", ::getpid()));
    // Nested opens in the holding process share the lock.
    RunDir again = RunDir::open(rc, "a: 1\n", {}, "unused");
    CHECK(again.path() == run.path());
  }
  CHECK(slurp(dir / ".lock").empty());  // released: nobody holds it
}

TEST_CASE("force redoes a run in its own directory, stale temporaries are removed", "[run_dir]") {
  TempDir t("force");
  RunConfig rc;
  rc.root = t.path.string();
  rc.experiment = "e";
  fs::path dir;
  {
    RunDir run = RunDir::open(rc, "a: 1\n", {"x=1"}, "cfg-abc");
    dir = run.path();
    run.mark_finished({{"loss", 0.5}});
    std::ofstream(run.checkpoints() / "last.pt") << "state";
    std::ofstream(run.checkpoints() / ".last.pt.tmp.424242.0") << "partial";
    std::ofstream(run.path() / ".summary.csv.tmp.424242.1") << "partial";
  }
  {
    RunDir run = RunDir::open(rc, "a: 1\n", {"x=1"}, "cfg-abc");
    CHECK(run.finished());
    CHECK_FALSE(fs::exists(dir / "checkpoints" / ".last.pt.tmp.424242.0"));
    CHECK_FALSE(fs::exists(dir / ".summary.csv.tmp.424242.1"));
    CHECK(fs::exists(dir / "checkpoints" / "last.pt"));
  }
  rc.force = true;
  {
    RunDir run = RunDir::open(rc, "a: 1\n", {"x=1"}, "cfg-abc");
    CHECK(run.path() == dir);  // the same directory, not a sibling
    CHECK_FALSE(run.finished());
    CHECK_FALSE(fs::exists(dir / "checkpoints" / "last.pt"));
    CHECK(fs::exists(dir / "config.yaml"));
  }
  // A different config in the directory is refused (force replaces it).
  rc.force = false;
  CHECK_THROWS_WITH(RunDir::open(rc, "a: 2\n", {}, "cfg-abc"), Catch::Contains("different config"));
}

TEST_CASE("run.threads, run.force and run.root are exactly the fields left out of a run's identity", "[run_dir]") {
  const std::string cfg = std::string(MOTIONCTL_SOURCE_DIR) + "/configs/train/autoencoder_smoke.yaml";
  auto base = load_job<TrainJobConfig>(cfg, {});
  const std::string base_hash = identity_hash(base);
  // Every field of run:, with a valid value other than the composed one.
  RunConfig defaults;
  YAML::Node fields = YAML::Load(dump_config(defaults));
  std::set<std::string> declared(RunConfig::non_identity_fields().begin(), RunConfig::non_identity_fields().end());
  std::set<std::string> seen;
  for (const auto& kv : fields) {
    const std::string key = kv.first.as<std::string>();
    seen.insert(key);
    const std::string now = YAML::Load(dump_config(base))["run"][key].as<std::string>();
    std::string other;
    if (key == "device") other = now == "cpu" ? "cuda" : "cpu";
    else if (now == "true" || now == "false") other = now == "true" ? "false" : "true";
    else if (!now.empty() && std::all_of(now.begin(), now.end(), ::isdigit)) other = std::to_string(std::stoll(now) + 1);
    else other = now + "x";
    auto changed = load_job<TrainJobConfig>(cfg, {fmt::format("run.{}={}", key, other)});
    INFO("run." << key << ": " << now << " -> " << other);
    REQUIRE(dump_config(changed) != dump_config(base));  // the override took
    if (declared.count(key))
      CHECK(identity_hash(changed) == base_hash);
    else
      CHECK(identity_hash(changed) != base_hash);
  }
  for (const auto& f : declared) CHECK(seen.count(f) == 1);  // no stale name in the list
  // Cleared fields go to their defaults, so a config that never set them hashes
  // as before the list existed (the shipped components' hashes hold).
  auto cleared = base;
  cleared.run.clear_non_identity();
  CHECK(config_hash(cleared) == config_hash(base));
}

TEST_CASE("a command's runs root reaches the components it trains", "[run_dir]") {
  const std::string cfg = std::string(MOTIONCTL_SOURCE_DIR) + "/configs/eval/evaluator_smoke.yaml";
  const fs::path plain = run_dir_of(cfg, {});
  {
    RunsRootScope scope("/tmp/elsewhere");
    const fs::path moved = run_dir_of(cfg, {});
    CHECK(moved.string().rfind("/tmp/elsewhere/", 0) == 0);
    CHECK(moved.filename() == plain.filename());  // same name and hash, another root
    {
      RunsRootScope inner("/tmp/inner");  // an outer scope is not replaced
      CHECK(run_dir_of(cfg, {}).string().rfind("/tmp/elsewhere/", 0) == 0);
    }
    CHECK(run_dir_of(cfg, {"run.root=/tmp/explicit"}).string().rfind("/tmp/explicit/", 0) == 0);
  }
  CHECK(run_dir_of(cfg, {}) == plain);
}
