// Runs that cannot be corrupted (issue 16): --stop-after and SIGINT checkpoint at
// the step reached and the resumed curve equals the uninterrupted one; a diverged
// run never writes a checkpoint, final.pt, summary.csv or DONE and keeps its last
// good checkpoint; a corrupt checkpoint is refused naming the file; a failed start
// claims no directory; force and threads redo/reuse the same directory; a second
// process on a run in use is refused.
#include <catch2/catch.hpp>

#include <signal.h>
#include <sys/wait.h>

#include <chrono>
#include <thread>

#include "core/error.h"
#include "core/interrupt.h"
#include "test_util.h"
#include "train/train_job.h"
#include "train/trainer.h"

using namespace mc;
using namespace mc::test;

namespace {

// A four-number model whose loss is (w - 2)^2, with faults on demand: at loss call
// `blow_up_at` it sets its weights to 3e38 after computing the loss (finite
// weights that overflow the next loss, as lr 1e30 does), at `nan_at` the loss is
// NaN; evaluate() reads `eval_split`.
struct ToyFaultConfig : Config {
  int blow_up_at = 0;
  int nan_at = 0;
  std::string eval_split = "val";
  void visit(FieldVisitor& v) override {
    v("blow_up_at", blow_up_at, "loss call that sets the weights to 3e38 (0 = never)");
    v("nan_at", nan_at, "loss call that returns NaN (0 = never)");
    v("eval_split", eval_split, "split evaluate() reads");
  }
};

struct ToyModule : torch::nn::Module {
  torch::Tensor w;
  ToyModule() { w = register_parameter("w", torch::ones({4})); }
};

class ToyFaultTrainer : public Trainable {
 public:
  ToyFaultTrainer(const ToyFaultConfig& c, const TrainContext& ctx) : cfg_(c), ctx_(ctx) {}
  torch::nn::Module& module() override { return m_; }
  LossOutput loss(const std::vector<int64_t>&, const BatchShard&) override {
    ++calls_;
    LossOutput out;
    out.loss = (m_.w - 2).pow(2).mean();
    if (calls_ == cfg_.nan_at) out.loss = out.loss * std::numeric_limits<float>::quiet_NaN();
    if (calls_ == cfg_.blow_up_at) {
      torch::NoGradGuard ng;
      m_.w.fill_(3e38);
    }
    return out;
  }
  std::map<std::string, double> evaluate() override {
    ctx_.data->split(cfg_.eval_split);
    return {{"val_w", m_.w.mean().item<double>()}};
  }
  std::vector<std::string> evaluation_splits() const override { return {cfg_.eval_split}; }

 private:
  ToyFaultConfig cfg_;
  TrainContext ctx_;
  ToyModule m_;
  int calls_ = 0;
};

MC_REGISTER_MODEL("test_toy_fault", ToyFaultConfig,
                  [](const Config& c, const TrainContext& ctx) -> std::unique_ptr<Trainable> {
                    return std::make_unique<ToyFaultTrainer>(dynamic_cast<const ToyFaultConfig&>(c), ctx);
                  },
                  "test model with injected divergence");

// A small fixture shared by the tests of this file (built once).
const std::string& toy_data() {
  static TempDir dir("safety_data");
  static const std::string path = [] {
    std::string p = (dir.path / "fx.h5").string();
    auto r = run_motionctl(fmt::format("fixture configs/data/smoke.yaml output={} fixture.num_clips=40", p));
    REQUIRE(r.exit_code == 0);
    return p;
  }();
  return path;
}

TrainJobConfig toy_job(const fs::path& root, const std::string& model_extra, int steps = 20) {
  const std::string yaml = fmt::format(
      "run: {{experiment: toy, name: r, root: '{}', log_every: 5, checkpoint_every: 5, threads: 1}}\n"
      "data: {{path: '{}', window: 16}}\n"
      "model: {{type: test_toy_fault{}}}\n"
      "optim: {{steps: {}, batch_size: 4, lr: 0.01, warmup: 0, schedule: constant}}\n",
      root.string(), toy_data(), model_extra, steps);
  TrainJobConfig job;
  parse_config(config_from_string(yaml, "toy.yaml"), job);
  return job;
}

int64_t checkpoint_step(const fs::path& file) {
  std::istringstream in(read_checkpoint_payload(file));
  torch::serialize::InputArchive ar;
  ar.load_from(in);
  torch::Tensor step;
  ar.read("step", step);
  return step.item<int64_t>();
}


}  // namespace

TEST_CASE("a diverged run writes nothing of its diverged steps and keeps its last good checkpoint", "[train]") {
  TempDir t("diverge");
  const fs::path run = t.path / "toy" / "r";
  SECTION("weights that overflow after a checkpoint step") {
    // Step 10's update leaves weights of 3e38 (finite); its checkpoint must not be
    // written, since step 11's loss is infinite. Step 5's stays.
    auto job = toy_job(t.path, ", blow_up_at: 10");
    try {
      train(job, {}, "r");
      FAIL("a diverged run finished");
    } catch (const UserError& e) {
      const std::string msg = e.what();
      CHECK(msg.find("diverged") != std::string::npos);
      CHECK(msg.find("optim.lr") != std::string::npos);
      CHECK(msg.find("step 5") != std::string::npos);
    }
    REQUIRE(fs::exists(run / "checkpoints" / "last.pt"));
    CHECK(checkpoint_step(run / "checkpoints" / "last.pt") == 5);
  }
  SECTION("weights that overflow on the last step") {
    auto job = toy_job(t.path, ", blow_up_at: 20");
    CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains("optim.lr"));
    CHECK(checkpoint_step(run / "checkpoints" / "last.pt") == 15);
  }
  SECTION("a NaN loss") {
    auto job = toy_job(t.path, ", nan_at: 3");
    CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains("no checkpoint had been written"));
    CHECK_FALSE(fs::exists(run / "checkpoints" / "last.pt"));
  }
  for (auto f : {"DONE", "summary.csv", "checkpoints/final.pt"}) CHECK_FALSE(fs::exists(run / f));
}

TEST_CASE("a failed start claims no run directory", "[train]") {
  TempDir t("claim");
  auto job = toy_job(t.path, ", eval_split: test_missing");
  CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains("split 'test_missing' is empty"));
  CHECK_FALSE(fs::exists(t.path / "toy" / "r"));
  auto bad_device = toy_job(t.path, "");
  bad_device.run.device = "cuda:0";
  CHECK_THROWS_AS(train(bad_device, {}, "r"), UserError);
  CHECK_FALSE(fs::exists(t.path / "toy" / "r"));
}

TEST_CASE("stop after any step and SIGINT checkpoint where they stop, the resumed run equals the uninterrupted one",
          "[train]") {
  TempDir t("stop");
  auto whole = toy_job(t.path / "a", "", 23);
  REQUIRE(train(whole, {}, "r").summary.count("final_loss"));
  const fs::path a = t.path / "a" / "toy" / "r";

  const fs::path b = t.path / "b" / "toy" / "r";
  TrainLoopOptions stop;
  stop.stop_after = 7;  // not a multiple of log_every or checkpoint_every
  auto part = toy_job(t.path / "b", "", 23);
  train(part, {}, "r", stop);
  CHECK(checkpoint_step(b / "checkpoints" / "last.pt") == 7);
  stop.stop_after = 4;
  train(part, {}, "r", stop);
  CHECK(checkpoint_step(b / "checkpoints" / "last.pt") == 11);
  // A signal between steps: the loop checkpoints at the step reached and throws.
  {
    InterruptScope scope;  // the loop's own scope nests in this one
    request_interrupt(SIGINT);
    try {
      train(part, {}, "r");
      FAIL("the interrupted run did not stop");
    } catch (const Interrupted& e) {
      CHECK(e.signal == SIGINT);
      CHECK(std::string(e.what()).find("resumes") != std::string::npos);
    }
  }
  CHECK(checkpoint_step(b / "checkpoints" / "last.pt") == 12);
  auto r = train(part, {}, "r");
  CHECK_FALSE(r.skipped);
  CHECK(metrics_without_wall(a / "metrics.csv") == metrics_without_wall(b / "metrics.csv"));
  CHECK(slurp(a / "summary.csv").find("final_loss") != std::string::npos);
  auto sa = read_summary_csv(a / "summary.csv"), sb = read_summary_csv(b / "summary.csv");
  CHECK(sa.at("final_loss") == sb.at("final_loss"));
  CHECK(sa.at("val_w") == sb.at("val_w"));
}

TEST_CASE("a kill between the last checkpoint and DONE finishes with the real final loss", "[train]") {
  TempDir t("tail");
  auto job = toy_job(t.path, "", 10);
  train(job, {}, "r");
  const fs::path run = t.path / "toy" / "r";
  const auto before = read_summary_csv(run / "summary.csv");
  // As if killed after last.pt (step 10) was written but before DONE.
  fs::remove(run / "DONE");
  fs::remove(run / "summary.csv");
  fs::remove(run / "checkpoints" / "final.pt");
  auto r = train(job, {}, "r");
  CHECK_FALSE(r.skipped);
  const auto after = read_summary_csv(run / "summary.csv");
  REQUIRE(std::isfinite(after.at("final_loss")));
  CHECK(after.at("final_loss") == before.at("final_loss"));
}

TEST_CASE("a corrupt checkpoint is refused naming the file, stale temporaries go", "[train]") {
  TempDir t("corrupt");
  auto job = toy_job(t.path, "");
  TrainLoopOptions stop;
  stop.stop_after = 10;
  train(job, {}, "r", stop);
  const fs::path ckpt = t.path / "toy" / "r" / "checkpoints" / "last.pt";
  const fs::path stale = ckpt.parent_path() / ".last.pt.tmp.99999.3";
  std::ofstream(stale) << "half a checkpoint";
  std::string bytes = slurp(ckpt);
  SECTION("a flipped byte") {
    bytes[bytes.size() / 2] ^= 0x5a;
    std::ofstream(ckpt, std::ios::binary) << bytes;
    CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains(ckpt.string()) && Catch::Contains("SHA-1"));
  }
  SECTION("a truncated file") {
    std::ofstream(ckpt, std::ios::binary) << bytes.substr(0, bytes.size() - 100);
    CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains(ckpt.string()) && Catch::Contains("truncated"));
  }
  SECTION("garbage") {
    std::ofstream(ckpt, std::ios::binary) << "not a checkpoint";
    CHECK_THROWS_WITH(train(job, {}, "r"), Catch::Contains(ckpt.string()) && Catch::Contains("corrupt"));
  }
  CHECK_FALSE(fs::exists(stale));
}

TEST_CASE("train: force redoes the run in its directory, threads reuse it, a run in use is refused",
          "[train][slow]") {
  TempDir t("cli_runs");
  const std::string data = toy_data();
  const std::string common = fmt::format(
      "configs/train/autoencoder_smoke.yaml data.path={} optim.steps=20 run.log_every=5 run.checkpoint_every=10 "
      "model.width=16 run.root={}",
      data, t.path.string());
  auto first = run_motionctl("train " + common + " run.threads=1");
  REQUIRE(first.exit_code == 0);
  auto dir_of = [](const std::string& out) {
    auto p = out.rfind("run: ");
    return out.substr(p + 5, out.find_first_of(" \n", p + 5) - p - 5);
  };
  const std::string dir = dir_of(first.output);
  auto other_threads = run_motionctl("train " + common + " run.threads=2");
  CHECK(other_threads.exit_code == 0);
  CHECK(dir_of(other_threads.output) == dir);
  CHECK(other_threads.output.find("already finished") != std::string::npos);
  auto forced = run_motionctl("train " + common + " run.force=true");
  CHECK(forced.exit_code == 0);
  CHECK(dir_of(forced.output) == dir);
  CHECK(forced.output.find("already finished") == std::string::npos);
  auto plain = run_motionctl("train " + common);
  CHECK(dir_of(plain.output) == dir);
  CHECK(plain.output.find("already finished") != std::string::npos);

  // A run in use: a long training holds it; a second `train` and a forced one
  // are refused with its pid; SIGTERM stops it with a checkpoint (exit 143).
  const std::string long_args = fmt::format(
      "configs/train/autoencoder_smoke.yaml data.path={} optim.steps=100000 run.log_every=5 run.checkpoint_every=10 "
      "model.width=16 run.root={} run.name=busy run.threads=1",
      data, t.path.string());
  const fs::path busy = t.path / "autoencoder" / "busy";
  std::string cmd = fmt::format("cd '{}' && exec env CI=1 '{}' train {} > '{}' 2>&1", MOTIONCTL_SOURCE_DIR,
                                MOTIONCTL_BINARY, long_args, (t.path / "busy.log").string());
  pid_t pid = ::fork();
  if (pid == 0) {
    ::execl("/bin/sh", "sh", "-c", cmd.c_str(), (char*)nullptr);
    ::_exit(127);
  }
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (!fs::exists(busy / "metrics.csv") && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  REQUIRE(fs::exists(busy / "metrics.csv"));
  auto second = run_motionctl("train " + long_args);
  CHECK(second.exit_code == 2);
  CHECK(second.output.find(fmt::format("pid {}", pid)) != std::string::npos);
  auto force_busy = run_motionctl("train " + long_args + " run.force=true");
  CHECK(force_busy.exit_code == 2);
  CHECK(fs::exists(busy / "metrics.csv"));
  ::kill(pid, SIGTERM);
  int status = 0;
  ::waitpid(pid, &status, 0);
  REQUIRE(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 128 + SIGTERM);
  CHECK(fs::exists(busy / "checkpoints" / "last.pt"));
  CHECK(slurp(t.path / "busy.log").find("interrupted by signal") != std::string::npos);
  CHECK(slurp(busy / ".lock").empty());
}
