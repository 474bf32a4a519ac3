// `motionctl bench train CONFIG`: the time of one training step of any trainable
// config, its FLOP count and FLOP rate as a fraction of sgemm's at the same thread
// count; for whole-clip configs also the same step padded to t_max, so the cost
// of padding shows as a ratio measured in one run.
#include <chrono>
#include <cmath>

#include "bench/bench.h"
#include "core/error.h"
#include "train/dependencies.h"
#include "train/train_job.h"
#include "train/trainer.h"

namespace mc {

namespace {

struct StepTiming {
  double seconds = 0;       // mean wall time of one step (loss, backward, optimiser)
  double data_seconds = 0;  // of which: building the batch tensors (measured apart)
  double flops = 0;         // mean useful FLOPs per step (0 = unknown)
  double frames = 0;        // mean tensor frames per clip (padding included)
  int64_t params = 0;
};

StepTiming time_steps(const std::string& config, const std::vector<std::string>& overrides, int warmup, int steps) {
  auto job = load_job<TrainJobConfig>(config, overrides);
  ensure_training_data(job);
  torch::Device device = setup_torch(job.run);
  auto data = MotionDataset::load(resolve_data_path(job.data.path));
  TrainContext ctx{data, device, &job, job.data.window, job.data.trim_padding, job.optim.ema_decay};
  resolve_dependencies(job.model);
  auto trainable = make_trainable(job.model, ctx);
  trainable->module().to(device);
  trainable->module().train();
  auto params = trainable->trainable_parameters();
  StepTiming r;
  for (auto& p : params) r.params += p.numel();
  torch::optim::AdamW opt = make_optimizer(job.optim, params);
  EpochSampler sampler = make_sampler(job, *data);
  using clock = std::chrono::steady_clock;
  for (int s = 0; s < warmup + steps; ++s) {
    auto idx = sampler.next(job.optim.batch_size);
    auto t0 = clock::now();
    LossOutput out = trainable->loss(idx);
    opt.zero_grad();
    out.loss.backward();
    if (job.optim.grad_clip > 0) torch::nn::utils::clip_grad_norm_(params, job.optim.grad_clip);
    opt.step();
    double dt = std::chrono::duration<double>(clock::now() - t0).count();
    if (s < warmup) continue;
    r.seconds += dt / steps;
    r.flops += trainable->flops_per_step(idx) / steps;
    auto d0 = clock::now();
    auto b = data->batch(idx, job.data.window, 1, device, job.data.trim_padding);
    r.data_seconds += std::chrono::duration<double>(clock::now() - d0).count() / steps;
    r.frames += static_cast<double>(b.joints.size(1)) / steps;
  }
  return r;
}

}  // namespace

void bench_train(const TrainBenchOptions& o, std::ostream& out) {
  std::vector<std::string> overrides = o.overrides;
  if (o.threads > 0) overrides.push_back(fmt::format("run.threads={}", o.threads));
  auto job = load_job<TrainJobConfig>(o.config, overrides);
  StepTiming as_is = time_steps(o.config, overrides, o.warmup, o.steps);
  const int used_threads = torch::get_num_threads();  // what setup_torch chose for the run
  BlasBenchResult blas = bench_sgemm(used_threads);
  out << fmt::format("bench train {} ({}; {} trainable parameters; batch {}; {} thread(s); sgemm {:.1f} GFLOP/s)\n",
                     o.config, job.model.type, as_is.params, job.optim.batch_size, used_threads, blas.gflops);
  out << "| variant | frames/clip | s/step | data s/step | GFLOP/step (valid frames) | GFLOP/s | of sgemm |\n"
         "|---|---:|---:|---:|---:|---:|---:|\n";
  auto row = [&](const std::string& name, const StepTiming& t) {
    double rate = t.flops > 0 ? t.flops / t.seconds / 1e9 : NAN;
    out << fmt::format("| {} | {:.0f} | {:.3f} | {:.4f} | {} | {} | {} |\n", name, t.frames, t.seconds,
                       t.data_seconds, t.flops > 0 ? fmt::format("{:.2f}", t.flops / 1e9) : "–",
                       t.flops > 0 ? fmt::format("{:.1f}", rate) : "–",
                       t.flops > 0 ? fmt::format("{:.0f}%", 100 * rate / blas.gflops) : "–");
  };
  row("as configured", as_is);
  if (job.data.window == 0 && (job.data.trim_padding || job.data.length_buckets > 0) && o.compare_padded) {
    auto padded_overrides = overrides;
    padded_overrides.push_back("data.trim_padding=false");
    padded_overrides.push_back("data.length_buckets=0");
    StepTiming padded = time_steps(o.config, padded_overrides, o.warmup, o.steps);
    row("padded to t_max, no buckets", padded);
    out << fmt::format("speed-up of the configured step over the padded one: {:.2f}x\n",
                       padded.seconds / as_is.seconds);
  }
}

}  // namespace mc
