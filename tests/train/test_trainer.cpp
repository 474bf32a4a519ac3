// Training loop: schedule as a pure function, end-to-end training of the motion
// autoencoder, kill -9 + resume reproducing the uninterrupted metrics exactly,
// finished runs as no-ops, sweeps.
#include <catch2/catch.hpp>

#include <signal.h>
#include <sys/wait.h>

#include <chrono>
#include <random>
#include <set>
#include <thread>

#include "test_util.h"
#include "train/trainer.h"

using namespace mc;
using namespace mc::test;

TEST_CASE("learning-rate schedule: warm-up, step decay, cosine", "[train]") {
  OptimConfig o;
  o.lr = 1.0;
  o.steps = 100;
  o.warmup = 10;
  o.schedule = "step";
  o.decay_at = {50, 80};
  o.decay_factor = 0.1;
  CHECK(scheduled_lr(o, 0) == Approx(0.1));
  CHECK(scheduled_lr(o, 9) == Approx(1.0));
  CHECK(scheduled_lr(o, 49) == Approx(1.0));
  CHECK(scheduled_lr(o, 50) == Approx(0.1));
  CHECK(scheduled_lr(o, 85) == Approx(0.01));
  o.schedule = "cosine";
  o.min_lr_ratio = 0.2;
  CHECK(scheduled_lr(o, 10) == Approx(1.0));
  CHECK(scheduled_lr(o, 100) == Approx(0.2));
  CHECK(scheduled_lr(o, 55) == Approx(0.6));
  for (int s = 11; s < 100; ++s) CHECK(scheduled_lr(o, s) <= scheduled_lr(o, s - 1) + 1e-12);
  o.schedule = "constant";
  CHECK(scheduled_lr(o, 99) == Approx(1.0));
}

namespace {


}  // namespace

TEST_CASE("kill -9 mid-training then resume reproduces the uninterrupted metrics.csv", "[train][slow]") {
  TempDir t("resume");
  std::string data = (t.path / "fx.h5").string();
  auto fx = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data));
  REQUIRE(fx.exit_code == 0);
  std::string common = fmt::format(
      "configs/train/autoencoder_smoke.yaml data.path={} optim.steps=300 run.log_every=5 run.checkpoint_every=10 "
      "run.threads=1 run.name=r model.width=32",
      data);
  auto a = run_motionctl(fmt::format("train {} run.root={}", common, (t.path / "a").string()));
  REQUIRE(a.exit_code == 0);
  fs::path run_a = t.path / "a" / "autoencoder" / "r";
  REQUIRE(fs::exists(run_a / "DONE"));

  // Interrupted run: start it, kill -9 once a checkpoint exists, then resume.
  fs::path run_b = t.path / "b" / "autoencoder" / "r";
  std::string cmd = fmt::format("cd '{}' && exec env CI=1 '{}' train {} run.root={} > /dev/null 2>&1",
                                MOTIONCTL_SOURCE_DIR, MOTIONCTL_BINARY, common, (t.path / "b").string());
  pid_t pid = ::fork();
  if (pid == 0) {
    ::execl("/bin/sh", "sh", "-c", cmd.c_str(), (char*)nullptr);
    ::_exit(127);
  }
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (!fs::exists(run_b / "checkpoints" / "last.pt") && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  std::this_thread::sleep_for(std::chrono::milliseconds(30));  // land between checkpoints
  ::kill(pid, SIGKILL);
  int status = 0;
  ::waitpid(pid, &status, 0);
  REQUIRE(WIFSIGNALED(status));
  REQUIRE_FALSE(fs::exists(run_b / "DONE"));
  auto b = run_motionctl(fmt::format("train {} run.root={}", common, (t.path / "b").string()));
  REQUIRE(b.exit_code == 0);
  CHECK(b.output.find("resuming") != std::string::npos);
  CHECK(metrics_without_wall(run_a / "metrics.csv") == metrics_without_wall(run_b / "metrics.csv"));
  CHECK(slurp(run_a / "summary.csv").find("val_mpjpe_m") != std::string::npos);

  // A finished run is a no-op; a different config in the same run dir is refused.
  auto again = run_motionctl(fmt::format("train {} run.root={}", common, (t.path / "a").string()));
  CHECK(again.exit_code == 0);
  CHECK(again.output.find("already finished") != std::string::npos);
  auto clash = run_motionctl(fmt::format("train {} run.root={} optim.lr=0.5", common, (t.path / "a").string()));
  CHECK(clash.exit_code == 2);
  CHECK(clash.output.find("different config") != std::string::npos);
}

TEST_CASE("training reduces the autoencoder loss and the run directory is complete", "[train]") {
  TempDir t("ae");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=60", data)).exit_code ==
          0);
  auto r = run_motionctl(fmt::format(
      "train configs/train/autoencoder_smoke.yaml data.path={} optim.steps=120 run.log_every=10 "
      "run.checkpoint_every=60 run.root={} run.name=ae run.seed=3",
      data, t.path.string()));
  REQUIRE(r.exit_code == 0);
  fs::path run = t.path / "autoencoder" / "ae";
  for (auto f : {"config.yaml", "overrides.txt", "seed.txt", "log.txt", "metrics.csv", "summary.csv", "DONE",
                 "checkpoints/last.pt", "checkpoints/final.pt"})
    CHECK(fs::exists(run / f));
  CHECK(slurp(run / "seed.txt") == "3\n");
  std::stringstream m(slurp(run / "metrics.csv"));
  std::string header, first, line, last;
  std::getline(m, header);
  std::getline(m, first);
  while (std::getline(m, line))
    if (!line.empty()) last = line;
  auto loss_at = [&](const std::string& row) {
    std::stringstream hs(header), rs(row);
    std::string h, v;
    while (std::getline(hs, h, ',') && std::getline(rs, v, ','))
      if (h == "loss") return std::stod(v);
    return -1.0;
  };
  CHECK(loss_at(last) < 0.5 * loss_at(first));
}

TEST_CASE("sweep runs every combination once and writes a summary", "[train][slow]") {
  TempDir t("sweep");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=50", data)).exit_code ==
          0);
  std::string args = fmt::format(
      "sweep configs/train/autoencoder_smoke.yaml data.path={} optim.steps=10 run.log_every=5 run.checkpoint_every=5 "
      "run.root={} model.width=16,24 optim.lr=0.001,0.002 --summary {}",
      data, t.path.string(), (t.path / "summary.csv").string());
  auto r = run_motionctl(args);
  REQUIRE(r.exit_code == 0);
  std::string csv = slurp(t.path / "summary.csv");
  CHECK(std::count(csv.begin(), csv.end(), '\n') == 5);  // header + 4 runs
  CHECK(csv.find("model.width,optim.lr") != std::string::npos);
  auto again = run_motionctl(args);
  REQUIRE(again.exit_code == 0);
  size_t skipped = 0;
  for (size_t p = 0; (p = again.output.find("already finished", p)) != std::string::npos; ++p) ++skipped;
  CHECK(skipped == 4);
}

TEST_CASE("length buckets: every clip once per epoch, similar lengths per batch, a function of (seed, epoch)",
          "[train]") {
  // 200 clips with lengths 40..196 spread over the pool; batches of 8, groups of 10 batches.
  std::vector<int64_t> pool, lengths;
  std::mt19937_64 rng(7);
  for (int64_t i = 0; i < 200; ++i) {
    pool.push_back(i);
    lengths.push_back(40 + static_cast<int64_t>(rng() % 157));
  }
  EpochSampler plain(pool, 3), bucketed(pool, 3, lengths, 8, 10), again(pool, 3, lengths, 8, 10);
  auto spread = [&](EpochSampler& s) {
    double sum = 0;
    std::set<int64_t> seen;
    for (int b = 0; b < 25; ++b) {
      auto idx = s.next(8);
      int64_t lo = 1000, hi = 0;
      for (int64_t i : idx) {
        lo = std::min(lo, lengths[i]);
        hi = std::max(hi, lengths[i]);
        seen.insert(i);
      }
      sum += hi - lo;
    }
    CHECK(seen.size() == 200);  // one epoch is still a permutation of the pool
    return sum / 25;
  };
  const double plain_spread = spread(plain), bucket_spread = spread(bucketed);
  CHECK(bucket_spread < 0.25 * plain_spread);
  // Deterministic: the same (seed, epoch) gives the same batches, and restore() lands on them.
  EpochSampler ref(pool, 3, lengths, 8, 10);
  for (int b = 0; b < 30; ++b) CHECK(again.next(8) == ref.next(8));
  EpochSampler resumed(pool, 3, lengths, 8, 10);
  resumed.restore(again.epoch(), again.pos());
  CHECK(resumed.next(8) == again.next(8));
}

// Every tensor of a checkpoint archive by name (the archive's bytes also hold its
// temporary file name, so files are compared tensor by tensor).
static void read_archive(torch::serialize::InputArchive& ar, const std::string& prefix,
                         std::map<std::string, torch::Tensor>& out) {
  for (const auto& k : ar.keys()) {
    torch::Tensor v;
    torch::serialize::InputArchive sub;
    if (ar.try_read(k, v))
      out[prefix + k] = v;
    else if (ar.try_read(k, sub))
      read_archive(sub, prefix + k + ".", out);
  }
}
static std::map<std::string, torch::Tensor> archive_tensors(const fs::path& file) {
  torch::serialize::InputArchive ar;
  ar.load_from(file.string());
  std::map<std::string, torch::Tensor> out;
  read_archive(ar, "", out);
  return out;
}

TEST_CASE("snapshots hold the weights of each step without changing the run", "[train]") {
  TempDir t("snap");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40", data)).exit_code ==
          0);
  auto train_run = [&](const std::string& name, const std::string& extra) {
    auto r = run_motionctl(fmt::format(
        "train configs/train/autoencoder_smoke.yaml data.path={} optim.steps=40 run.log_every=10 "
        "run.checkpoint_every=20 run.root={} run.name={} run.seed=3 run.threads=1 {}",
        data, t.path.string(), name, extra));
    REQUIRE(r.exit_code == 0);
    return t.path / "autoencoder" / name;
  };
  fs::path plain = train_run("plain", ""), snap = train_run("snap", "--snapshot-every 20");
  CHECK(fs::exists(snap / "checkpoints/snapshot_000020.pt"));
  auto partial = run_motionctl(fmt::format(
      "train configs/prior/flow_tiny.yaml data.path={} optim.steps=40 optim.warmup=5 run.log_every=10 "
      "run.checkpoint_every=20 run.root={} run.name=partial run.seed=3 run.threads=1 --snapshot-every 10 "
      "--stop-after 20",
      data, t.path.string()));
  REQUIRE(partial.exit_code == 0);
  // A run still training: its snapshots come with the outputs that load them.
  CHECK(fs::exists(t.path / "prior/partial/checkpoints/snapshot_000010.pt"));
  CHECK(fs::exists(t.path / "prior/partial/outputs/vocab.txt"));
  CHECK(fs::exists(t.path / "prior/partial/outputs/prior_meta.yaml"));
  CHECK_FALSE(fs::exists(t.path / "prior/partial/DONE"));
  CHECK_FALSE(fs::exists(snap / "checkpoints/snapshot_000040.pt"));  // the last step is final.pt
  CHECK_FALSE(fs::exists(plain / "checkpoints/snapshot_000020.pt"));
  auto a = archive_tensors(plain / "checkpoints/final.pt"), b = archive_tensors(snap / "checkpoints/final.pt");
  auto s20 = archive_tensors(snap / "checkpoints/snapshot_000020.pt");
  REQUIRE(!a.empty());
  REQUIRE(a.size() == b.size());
  REQUIRE(s20.size() == a.size());  // final.pt's format: the same tensors
  bool all_equal = true, some_differ = false;
  for (auto& [k, v] : a) {
    REQUIRE(b.count(k) == 1);
    REQUIRE(s20.count(k) == 1);
    all_equal = all_equal && torch::equal(v, b[k]);  // snapshotting observes the run, bit for bit
    some_differ = some_differ || !torch::equal(v, s20[k]);  // 20 steps earlier
  }
  CHECK(all_equal);
  CHECK(some_differ);
}

TEST_CASE("float16 final weights are the float32 run's weights rounded and stored as half and loaded as float32", "[train]") {
  TempDir t("half");
  std::string data = (t.path / "fx.h5").string();
  REQUIRE(run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40", data)).exit_code ==
          0);
  auto train_run = [&](const std::string& name, const std::string& extra) {
    auto r = run_motionctl(fmt::format(
        "train configs/prior/flow_tiny.yaml data.path={} optim.steps=20 optim.warmup=5 run.log_every=10 "
        "run.checkpoint_every=10 run.root={} run.name={} run.seed=3 run.threads=1 {}",
        data, t.path.string(), name, extra));
    REQUIRE(r.exit_code == 0);
    return t.path / "prior" / name;
  };
  const fs::path full = train_run("full", ""), half = train_run("half", "run.final_weights.dtype=float16");
  // The switch is part of the run's identity only when on: float32 dumps as before.
  CHECK(slurp(full / "config.yaml").find("final_weights") == std::string::npos);
  CHECK(slurp(half / "config.yaml").find("dtype: \"float16\"") != std::string::npos);
  auto a = archive_tensors(full / "checkpoints/final.pt"), b = archive_tensors(half / "checkpoints/final.pt");
  REQUIRE(!a.empty());
  REQUIRE(a.size() == b.size());
  int halves = 0;
  for (auto& [k, v] : a) {
    INFO(k);
    REQUIRE(b.count(k) == 1);
    if (b[k].scalar_type() == torch::kFloat16) {
      REQUIRE(v.scalar_type() == torch::kFloat32);
      // Same training (seed, one thread), then rounding: exactly float32 -> float16.
      CHECK(torch::equal(b[k], v.to(torch::kFloat16)));
      ++halves;
    } else {
      CHECK(torch::equal(b[k], v));  // buffers (statistics, counters) stay as they are
    }
  }
  CHECK(halves > 10);
  CHECK(fs::file_size(half / "checkpoints/final.pt") < 0.6 * fs::file_size(full / "checkpoints/final.pt"));
  // Consumers load it back as float32 and sample from it.
  const std::string out = (t.path / "s.h5").string();
  auto s = run_motionctl(fmt::format("sample configs/sample/t2m_smoke.yaml prior.run_dir={} texts.from_split= "
                                     "'texts.prompts=[walk]' texts.length=20 sampler.steps=2 output={} run.threads=1",
                                     half.string(), out));
  INFO(s.output);
  CHECK(s.exit_code == 0);
  CHECK(fs::exists(out));
  // A bad value is named.
  auto bad = run_motionctl(fmt::format("train configs/prior/flow_tiny.yaml data.path={} run.root={} "
                                       "run.final_weights.dtype=bfloat16",
                                       data, t.path.string()));
  CHECK(bad.exit_code == 2);
  CHECK(bad.output.find("run.final_weights.dtype") != std::string::npos);
}
