// The generic training loop with exact resume: model, optimiser, EMA, step,
// data position and torch's RNG state all live in one atomically written checkpoint.
#include "train/trainer.h"

#include <chrono>
#include <cstdlib>
#include <cmath>
#include <random>
#include <thread>

#include "core/resources.h"
#include "core/atomic_file.h"
#include "core/error.h"

namespace mc {

// ---------------------------------------------------------------- registry

static std::map<std::string, TrainableFactory>& trainables() {
  static std::map<std::string, TrainableFactory> r;
  return r;
}

void register_trainable(const std::string& type, TrainableFactory make) { trainables()[type] = std::move(make); }

std::unique_ptr<Trainable> make_trainable(const Component& model, const TrainContext& ctx) {
  auto it = trainables().find(model.type);
  if (it == trainables().end()) fail("model type '{}' has no trainer registered", model.type);
  return it->second(*model.cfg, ctx);
}

// ---------------------------------------------------------------- schedule

torch::optim::AdamW make_optimizer(const OptimConfig& o, const std::vector<torch::Tensor>& params) {
  return torch::optim::AdamW(
      params, torch::optim::AdamWOptions(o.lr).betas({o.betas[0], o.betas[1]}).weight_decay(o.weight_decay));
}

double scheduled_lr(const OptimConfig& o, int64_t step) {
  if (o.warmup > 0 && step < o.warmup) return o.lr * static_cast<double>(step + 1) / o.warmup;
  if (o.schedule == "constant") return o.lr;
  if (o.schedule == "step") {
    double lr = o.lr;
    for (int at : o.decay_at)
      if (step >= at) lr *= o.decay_factor;
    return lr;
  }
  double span = std::max<int64_t>(1, o.steps - o.warmup);
  double progress = std::min(1.0, static_cast<double>(step - o.warmup) / span);
  return o.lr * (o.min_lr_ratio + (1.0 - o.min_lr_ratio) * 0.5 * (1.0 + std::cos(M_PI * progress)));
}

torch::Device setup_torch(const RunConfig& run) {
  check_thread_count(run.threads, "run.threads");  // thousands of threads stall the machine (core/resources.h)
  // 0 = all cores, unless OMP_NUM_THREADS says otherwise (ctest runs tests in
  // parallel with OMP_NUM_THREADS=1: oversubscribed cores make torch ~50x slower).
  int threads = run.threads;
  if (threads <= 0) {
    const char* env = std::getenv("OMP_NUM_THREADS");
    threads = env && std::atoi(env) > 0 ? std::atoi(env)
                                        : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  }
  torch::set_num_threads(threads);
  torch::manual_seed(static_cast<uint64_t>(run.seed));
  try {
    torch::Device dev(run.device);
    if (dev.is_cuda() && !torch::cuda::is_available())
      fail("run.device = {} but this build of LibTorch sees no CUDA device; use run.device=cpu", run.device);
    return dev;
  } catch (const c10::Error&) {
    fail("run.device = '{}' is not a device name; use cpu, cuda or cuda:N", run.device);
  }
}

// ---------------------------------------------------------------- data order

EpochSampler::EpochSampler(std::vector<int64_t> pool, uint64_t seed, std::vector<int64_t> lengths, int batch,
                           int buckets)
    : pool_(std::move(pool)), lengths_(std::move(lengths)), seed_(seed), batch_(batch), buckets_(buckets) {
  shuffle();
}

std::vector<int64_t> EpochSampler::next(int n) {
  std::vector<int64_t> out;
  while (static_cast<int>(out.size()) < n) {
    if (pos_ >= static_cast<int64_t>(order_.size())) {
      ++epoch_;
      pos_ = 0;
      shuffle();
    }
    out.push_back(order_[pos_++]);
  }
  return out;
}

void EpochSampler::restore(int64_t epoch, int64_t pos) {
  epoch_ = epoch;
  pos_ = pos;
  shuffle();
}

void EpochSampler::shuffle() {
  order_ = pool_;
  std::mt19937_64 rng(seed_ ^ (0x9E3779B97F4A7C15ull * static_cast<uint64_t>(epoch_ + 1)));
  for (size_t i = order_.size(); i > 1; --i) std::swap(order_[i - 1], order_[rng() % i]);  // Fisher-Yates
  if (buckets_ <= 0 || batch_ <= 1 || lengths_.empty()) return;
  // Sort each group of buckets_ batches by length (stable: ties keep the shuffled
  // order), cut it into batches, then shuffle the whole batches so lengths do not
  // follow a pattern over the epoch. A function of (seed, epoch) still.
  const size_t group = static_cast<size_t>(buckets_) * batch_;
  for (size_t g = 0; g < order_.size(); g += group) {
    auto end = order_.begin() + std::min(order_.size(), g + group);
    std::stable_sort(order_.begin() + g, end,
                     [&](int64_t a, int64_t b) { return lengths_[a] < lengths_[b]; });
  }
  const size_t nb = order_.size() / batch_;  // a final partial batch stays last
  std::vector<size_t> perm(nb);
  for (size_t i = 0; i < nb; ++i) perm[i] = i;
  for (size_t i = nb; i > 1; --i) std::swap(perm[i - 1], perm[rng() % i]);
  std::vector<int64_t> out;
  out.reserve(order_.size());
  for (size_t b : perm) out.insert(out.end(), order_.begin() + b * batch_, order_.begin() + (b + 1) * batch_);
  out.insert(out.end(), order_.begin() + nb * batch_, order_.end());
  order_ = std::move(out);
}

EpochSampler make_sampler(const TrainJobConfig& job, const MotionDataset& data) {
  std::vector<int64_t> lengths;
  if (job.data.length_buckets > 0)
    for (int64_t i = 0; i < static_cast<int64_t>(data.set().size()); ++i) lengths.push_back(data.length(i));
  return EpochSampler(data.split("train"), static_cast<uint64_t>(job.run.seed), std::move(lengths),
                      job.optim.batch_size, job.data.length_buckets);
}

namespace {

torch::Tensor rng_state() {
  auto gen = at::detail::getDefaultCPUGenerator();
  std::lock_guard<std::mutex> lock(gen.mutex());
  return gen.get_state();
}

void set_rng_state(const torch::Tensor& s) {
  auto gen = at::detail::getDefaultCPUGenerator();
  std::lock_guard<std::mutex> lock(gen.mutex());
  gen.set_state(s);
}

struct LoopState {
  int64_t step = 0;
  double wall = 0;  // seconds spent in earlier invocations
};

void save_checkpoint(const fs::path& path, Trainable& tr, torch::optim::Optimizer& opt,
                     const std::vector<torch::Tensor>& ema, const LoopState& st, const EpochSampler& sampler) {
  torch::serialize::OutputArchive ar;
  torch::serialize::OutputArchive model_ar, opt_ar;
  tr.module().save(model_ar);
  opt.save(opt_ar);
  ar.write("model", model_ar);
  ar.write("optimizer", opt_ar);
  for (size_t i = 0; i < ema.size(); ++i) ar.write(fmt::format("ema.{}", i), ema[i]);
  ar.write("step", torch::tensor(st.step));
  ar.write("wall", torch::tensor(st.wall, torch::kFloat64));
  ar.write("sampler_epoch", torch::tensor(sampler.epoch()));
  ar.write("sampler_pos", torch::tensor(sampler.pos()));
  ar.write("rng", rng_state());
  AtomicOutput out(path);
  ar.save_to(out.tmp_path().string());
  out.commit();
}

void load_checkpoint(const fs::path& path, Trainable& tr, torch::optim::Optimizer& opt, std::vector<torch::Tensor>& ema,
                     LoopState& st, EpochSampler& sampler) {
  torch::serialize::InputArchive ar;
  try {
    ar.load_from(path.string());
    torch::serialize::InputArchive model_ar, opt_ar;
    ar.read("model", model_ar);
    ar.read("optimizer", opt_ar);
    tr.module().load(model_ar);
    opt.load(opt_ar);
    torch::NoGradGuard ng;
    for (size_t i = 0; i < ema.size(); ++i) {
      torch::Tensor t;
      ar.read(fmt::format("ema.{}", i), t);
      ema[i].copy_(t);
    }
    torch::Tensor step, wall, epoch, pos, rng;
    ar.read("step", step);
    ar.read("wall", wall);
    ar.read("sampler_epoch", epoch);
    ar.read("sampler_pos", pos);
    ar.read("rng", rng);
    st.step = step.item<int64_t>();
    st.wall = wall.item<double>();
    sampler.restore(epoch.item<int64_t>(), pos.item<int64_t>());
    set_rng_state(rng);
  } catch (const c10::Error& e) {
    fail("checkpoint '{}' is unreadable or belongs to another model ({}); delete it or use run.force=true",
         path.string(), std::string(e.what_without_backtrace()).substr(0, 200));
  }
}

std::string format_eta(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "?";
  int s = static_cast<int>(seconds);
  return s >= 3600 ? fmt::format("{}h{:02}m", s / 3600, s / 60 % 60) : fmt::format("{}m{:02}s", s / 60, s % 60);
}

}  // namespace

// ---------------------------------------------------------------- loop

TrainResult train(TrainJobConfig& job, const std::vector<std::string>& overrides, const std::string& default_name,
                  const TrainLoopOptions& loop) {
  const int64_t stop_after = loop.stop_after;
  if (job.run.checkpoint_every % job.run.log_every != 0)
    fail("run.checkpoint_every ({}) must be a multiple of run.log_every ({}) so checkpoints fall on logged steps",
         job.run.checkpoint_every, job.run.log_every);
  TrainResult result;
  RunDir run = RunDir::open(job.run, dump_config(job), overrides, default_name);
  result.run_dir = run.path();
  if (run.finished()) {
    run.log().info(fmt::format("{} is finished; nothing to do (run.force=true redoes it)", run.path().string()));
    result.skipped = true;
    result.summary = run.summary();
    return result;
  }
  torch::Device device = setup_torch(job.run);
  auto data = MotionDataset::load(resolve_data_path(job.data.path));
  TrainContext ctx{data, device, &job, job.data.window, job.data.trim_padding};
  auto trainable = make_trainable(job.model, ctx);
  trainable->module().to(device);
  auto params = trainable->trainable_parameters();
  int64_t n_params = 0;
  for (auto& p : params) n_params += p.numel();

  torch::optim::AdamW opt = make_optimizer(job.optim, params);
  std::vector<torch::Tensor> ema;
  if (job.optim.ema_decay > 0)
    for (auto& p : params) ema.push_back(p.detach().clone());
  EpochSampler sampler = make_sampler(job, *data);
  MetricsCsv metrics(run.metrics_path());
  LoopState st;
  fs::path last = run.checkpoints() / "last.pt";
  if (fs::exists(last)) {
    load_checkpoint(last, *trainable, opt, ema, st, sampler);
    metrics.truncate_after(st.step);
    run.log().info(fmt::format("resuming {} from step {} ({} threads)", run.path().string(), st.step,
                               torch::get_num_threads()));
  } else {
    fs::remove(run.metrics_path());
    run.log().info(fmt::format("training {} ({} trainable parameters, {} threads, device {}) in {}", job.model.type,
                               n_params, torch::get_num_threads(), device.str(), run.path().string()));
  }

  const auto t0 = std::chrono::steady_clock::now();
  const int64_t first_step = st.step;
  std::map<std::string, double> accum;
  int64_t accum_n = 0;
  auto wall_now = [&] {
    return st.wall + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  double last_loss = NAN;
  while (st.step < job.optim.steps) {
    double lr = scheduled_lr(job.optim, st.step);
    for (auto& g : opt.param_groups()) static_cast<torch::optim::AdamWOptions&>(g.options()).lr(lr);
    auto idx = sampler.next(job.optim.batch_size);
    LossOutput out = trainable->loss(idx);
    double loss_v = out.loss.item<double>();
    if (!std::isfinite(loss_v))
      fail("training diverged: loss is {} at step {} of {}; lower optim.lr or raise optim.warmup", loss_v, st.step,
           run.path().string());
    opt.zero_grad();
    out.loss.backward();
    double gnorm = 0;
    if (job.optim.grad_clip > 0) gnorm = torch::nn::utils::clip_grad_norm_(params, job.optim.grad_clip);
    opt.step();
    if (!ema.empty()) {
      torch::NoGradGuard ng;
      double d = std::min(job.optim.ema_decay, (1.0 + st.step) / (10.0 + st.step));  // warm EMA for short runs
      for (size_t i = 0; i < ema.size(); ++i) ema[i].mul_(d).add_(params[i].detach(), 1.0 - d);
    }
    ++st.step;
    accum["loss"] += loss_v;
    for (auto& [k, v] : out.parts) accum[k] += v.item<double>();
    accum["grad_norm"] += gnorm;
    ++accum_n;
    last_loss = loss_v;

    double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    double ips = (st.step - first_step) / std::max(1e-9, elapsed);
    std::string line = fmt::format("step {}/{} loss {:.5f} lr {:.2e} {:.1f} it/s ETA {}", st.step, job.optim.steps,
                                   loss_v, lr, ips, format_eta((job.optim.steps - st.step) / ips));
    run.log().progress(line);
    bool last_step = st.step == job.optim.steps;
    if (st.step % job.run.log_every == 0 || last_step) {
      std::vector<std::pair<std::string, double>> row{{"wall_time", wall_now()}, {"lr", lr}};
      for (auto& [k, v] : accum) row.emplace_back(k, v / accum_n);
      metrics.append(st.step, row);
      accum.clear();
      accum_n = 0;
      if (!Logger::interactive()) run.log().info(line);
    }
    if (st.step % job.run.checkpoint_every == 0 || last_step) {
      LoopState snap{st.step, wall_now()};
      save_checkpoint(last, *trainable, opt, ema, snap, sampler);
    }
    if (loop.snapshot_every > 0 && st.step % loop.snapshot_every == 0 && !last_step) {
      // The weights final.pt would hold now: EMA swapped in, saved, swapped back.
      torch::NoGradGuard ng;
      std::vector<torch::Tensor> live;
      for (size_t i = 0; i < ema.size(); ++i) {
        live.push_back(params[i].detach().clone());
        params[i].copy_(ema[i]);
      }
      torch::serialize::OutputArchive ar;
      trainable->module().save(ar);
      AtomicOutput out(run.checkpoints() / fmt::format("snapshot_{:06d}.pt", st.step));
      ar.save_to(out.tmp_path().string());
      out.commit();
      for (size_t i = 0; i < live.size(); ++i) params[i].copy_(live[i]);
      // Vocabulary and metadata too, so a snapshot of a run still training can be loaded.
      trainable->save_artifacts(run.outputs());
    }
    if (stop_after > 0 && st.step - first_step >= stop_after && !last_step) {
      run.log().info(fmt::format("stopping at step {} as asked (resume by running again)", st.step));
      result.summary["step"] = st.step;
      return result;
    }
  }
  run.log().end_progress();

  // Final weights: the EMA copy, when there is one.
  if (!ema.empty()) {
    torch::NoGradGuard ng;
    for (size_t i = 0; i < ema.size(); ++i) params[i].copy_(ema[i]);
  }
  trainable->module().eval();
  std::map<std::string, double> summary = trainable->evaluate();
  summary["steps"] = static_cast<double>(st.step);
  summary["final_loss"] = last_loss;
  summary["trainable_params"] = static_cast<double>(n_params);
  summary["wall_time"] = wall_now();
  {
    torch::serialize::OutputArchive ar;
    trainable->module().save(ar);
    AtomicOutput out(run.checkpoints() / "final.pt");
    ar.save_to(out.tmp_path().string());
    out.commit();
  }
  trainable->save_artifacts(run.outputs());
  for (auto& [k, v] : summary) run.log().info(fmt::format("  {} = {:.6g}", k, v));
  run.mark_finished(summary);
  result.summary = summary;
  return result;
}

}  // namespace mc
