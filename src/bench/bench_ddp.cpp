// `motionctl bench ddp CONFIG`: what data-parallel training gives on this machine
// (issue 19). The same global batch and steps timed as one process with all the
// threads and as N processes with threads / N each (Gloo on loopback), with the
// gradient all-reduce launched from the backward's hooks (overlap) and after the
// backward; and the all-reduce of every gradient alone, the per-step cost a cluster
// adds when nothing overlaps it. The N processes are this binary again
// (launch_local_ranks), in a hidden worker mode that reports to the parent.
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <map>
#include <optional>
#include <sstream>

#include "bench/bench.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "train/distributed.h"
#include "train/train_job.h"
#include "train/trainer.h"

namespace mc {

namespace {

using Clock = std::chrono::steady_clock;

struct DdpTiming {
  double step_seconds = 0;    // mean wall time of a step (loss, backward, reduction, optimiser)
  double wait_seconds = 0;    // of which: waiting for the gradient all-reduce after backward
  double scalar_seconds = 0;  // of which: the step's scalar all-reduce
  int64_t params = 0;
};

// Builds the job's trainable (training any component it needs first) and times
// `steps` steps after `warmup`, as the trainer runs them (trainer.cpp).
class StepTimer {
 public:
  StepTimer(const TrainJobConfig& job, DataParallel* dp) : job_(job), dp_(dp) {
    device_ = setup_torch(job_.run, dp ? dp->env().local_world : 1);
    const int threads = torch::get_num_threads();
    data_ = MotionDataset::load(resolve_data_path(job_.data.path));
    TrainContext ctx{data_, device_, &job_, job_.data.window, job_.data.trim_padding};
    trainable_ = make_trainable(job_.model, ctx);
    torch::set_num_threads(threads);
    trainable_->module().to(device_);
    trainable_->module().train();
    params_ = trainable_->trainable_parameters();
    opt_.emplace(make_optimizer(job_.optim, params_));
    sampler_.emplace(make_sampler(job_, *data_));
    if (dp_) dp_->attach(params_);
  }

  DdpTiming time(int warmup, int steps) {
    DdpTiming r;
    for (auto& p : params_) r.params += p.numel();
    ReduceTimes before;
    for (int s = 0; s < warmup + steps; ++s) {
      if (s == warmup && dp_) before = dp_->times();
      auto idx = sampler_->next(job_.optim.batch_size);
      const auto t0 = Clock::now();
      LossOutput out = loss_share(*trainable_, idx, dp_);
      opt_->zero_grad();
      if (dp_) dp_->begin_backward();
      out.loss.backward();
      if (dp_) {
        dp_->finish_gradients("a timed step");
        std::vector<double> scalars{out.loss.item<double>()};
        for (auto& [k, v] : out.parts) scalars.push_back(v.item<double>());
        dp_->sum_scalars(scalars, "a timed step");
      }
      if (job_.optim.grad_clip > 0) torch::nn::utils::clip_grad_norm_(params_, job_.optim.grad_clip);
      opt_->step();
      if (s >= warmup) r.step_seconds += std::chrono::duration<double>(Clock::now() - t0).count() / steps;
    }
    if (dp_) {
      r.wait_seconds = (dp_->times().wait_seconds - before.wait_seconds) / steps;
      r.scalar_seconds = (dp_->times().scalar_seconds - before.scalar_seconds) / steps;
    }
    return r;
  }

  // The all-reduce of every gradient bucket with no backward to hide behind.
  double allreduce_alone(int repeats) {
    const auto t0 = Clock::now();
    for (int i = 0; i < repeats; ++i) {
      dp_->begin_backward();
      dp_->finish_gradients("a timed all-reduce");
    }
    return std::chrono::duration<double>(Clock::now() - t0).count() / repeats;
  }

 private:
  TrainJobConfig job_;
  DataParallel* dp_;
  torch::Device device_ = torch::kCPU;
  std::shared_ptr<MotionDataset> data_;
  std::unique_ptr<Trainable> trainable_;
  std::vector<torch::Tensor> params_;
  std::optional<torch::optim::AdamW> opt_;
  std::optional<EpochSampler> sampler_;
};

std::vector<std::string> job_overrides(const DdpBenchOptions& o) {
  std::vector<std::string> overrides = o.overrides;
  if (o.threads > 0) overrides.push_back(fmt::format("run.threads={}", o.threads));
  return overrides;
}

// A worker rank: both overlap modes, then the all-reduce alone; rank 0 reports.
void bench_ddp_worker(const DdpBenchOptions& o) {
  const DistEnv env = dist_env_from_environment();
  if (!env.distributed()) fail("bench ddp --worker runs as a rank of `bench ddp` (WORLD_SIZE unset)");
  DistOptions dopt;
  dopt.bucket_bytes = static_cast<int64_t>(o.bucket_mb * (1 << 20));
  dopt.overlap = true;
  auto dp = DataParallel::join(env, dopt);
  auto job = load_job<TrainJobConfig>(o.config, job_overrides(o));
  StepTimer timer(job, dp.get());
  const DdpTiming on = timer.time(o.warmup, o.steps);
  dp->set_overlap(false);
  const DdpTiming off = timer.time(o.warmup, o.steps);
  const double alone = timer.allreduce_alone(std::max(3, o.steps));
  if (dp->rank() != 0) return;
  write_file_atomic(o.report, fmt::format("threads {}\nbuckets {}\noverlap_step {}\noverlap_wait {}\noverlap_scalar "
                                          "{}\nafter_step {}\nafter_wait {}\nafter_scalar {}\nallreduce_alone {}\n",
                                          torch::get_num_threads(), dp->bucket_count(), on.step_seconds,
                                          on.wait_seconds, on.scalar_seconds, off.step_seconds, off.wait_seconds,
                                          off.scalar_seconds, alone));
}

}  // namespace

void bench_ddp(const DdpBenchOptions& o, std::ostream& out) {
  if (o.worker) return bench_ddp_worker(o);
  if (dist_env_from_environment().distributed())
    fail("bench ddp starts its own processes; run it without RANK/WORLD_SIZE set");
  auto job = load_job<TrainJobConfig>(o.config, job_overrides(o));
  if (job.optim.batch_size % o.nproc != 0)
    fail("optim.batch_size = {} does not divide over --nproc {}; pass optim.batch_size={}", job.optim.batch_size,
         o.nproc, (job.optim.batch_size / o.nproc + 1) * o.nproc);
  ensure_training_data(job);
  // One process first (it also trains any component the model needs, so the ranks
  // find them), then the ranks.
  DdpTiming one;
  int threads_one = 0;
  {
    StepTimer timer(job, nullptr);
    threads_one = torch::get_num_threads();
    one = timer.time(o.warmup, o.steps);
  }
  const fs::path report =
      fs::temp_directory_path() / fmt::format("motionctl-bench-ddp-{}-{}.txt", ::getpid(), std::rand());
  std::vector<std::string> args = command_line();
  args.push_back("--worker");
  args.push_back("--report");
  args.push_back(report.string());
  const int code = launch_local_ranks(o.nproc, args, 60);
  if (code != 0) fail("bench ddp: the {} worker processes failed (exit code {}); see their messages above", o.nproc, code);
  std::map<std::string, double> r;
  {
    std::istringstream in(read_file(report));
    std::string k;
    double v;
    while (in >> k >> v) r[k] = v;
  }
  std::error_code ec;
  fs::remove(report, ec);
  const double B = job.optim.batch_size, mb = one.params * 4.0 / (1 << 20);
  out << fmt::format(
      "bench ddp {} ({}; {} trainable parameters = {:.1f} MiB of float gradients in {:.0f} bucket(s) of <= {:g} MiB; "
      "global batch {}; {} step(s) after {} warm-up)\n",
      o.config, job.model.type, one.params, mb, r["buckets"], o.bucket_mb, job.optim.batch_size, o.steps, o.warmup);
  out << "| setup | s/step | clips/s | vs 1 process | waiting for the all-reduce after backward, s/step |\n"
         "|---|---:|---:|---:|---:|\n";
  out << fmt::format("| 1 process x {} thread(s) | {:.3f} | {:.1f} | 1.00x | – |\n", threads_one, one.step_seconds,
                     B / one.step_seconds);
  const int t = static_cast<int>(r["threads"]);
  for (auto [name, key] : {std::pair<const char*, const char*>{"all-reduce from the backward's hooks", "overlap"},
                           {"all-reduce after the backward", "after"}}) {
    const double s = r[std::string(key) + "_step"], w = r[std::string(key) + "_wait"];
    out << fmt::format("| {} processes x {} thread(s), {} | {:.3f} | {:.1f} | {:.2f}x | {:.4f} |\n", o.nproc, t, name,
                       s, B / s, one.step_seconds / s, w);
  }
  out << fmt::format(
      "all-reduce of every gradient alone: {:.4f} s/step ({:.1f} MiB over loopback Gloo, {} processes); the step's "
      "scalar all-reduce: {:.5f} s\n",
      r["allreduce_alone"], mb, o.nproc, r["after_scalar"]);
}

}  // namespace mc
