// The generic training loop with exact resume: model, optimiser, EMA, step,
// data position and torch's RNG state all live in one atomically written,
// checksummed checkpoint, written only once its weights are known to be sound.
#include "train/trainer.h"

#include <c10/util/hash.h>

#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <optional>
#include <random>
#include <sstream>
#include <thread>

#include <fmt/ranges.h>

#include "core/resources.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/interrupt.h"
#include "models/trained_run.h"
#include "train/dependencies.h"
#include "train/dependency_record.h"
#include "train/distributed.h"

namespace mc {

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

torch::Device setup_torch(const RunConfig& run, int ranks_here) {
  check_thread_count(run.threads, "run.threads");  // thousands of threads stall the machine (core/resources.h)
  // 0 = all cores, unless OMP_NUM_THREADS says otherwise (ctest runs tests in
  // parallel with OMP_NUM_THREADS=1: oversubscribed cores make torch ~50x slower).
  int threads = run.threads;
  if (threads <= 0) {
    const char* env = std::getenv("OMP_NUM_THREADS");
    threads = env && std::atoi(env) > 0 ? std::atoi(env)
                                        : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  }
  // Data-parallel ranks on one machine share its threads (docs/choices.md).
  if (ranks_here > 1) threads = std::max(1, threads / ranks_here);
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

void check_batch_divides(const TrainJobConfig& job, int processes) {
  if (job.optim.batch_size % processes != 0)
    fail("optim.batch_size = {} does not divide over {} data-parallel processes (the global batch is the config's; "
         "each process computes batch_size / processes clips): use a multiple of {} (e.g. optim.batch_size={}) or "
         "another process count",
         job.optim.batch_size, processes, processes, (job.optim.batch_size / processes + 1) * processes);
}

LossOutput loss_share(Trainable& trainable, const std::vector<int64_t>& idx, DataParallel* dp) {
  if (!dp) return trainable.loss(idx, BatchShard{});
  if (!trainable.shards_batches()) {
    LossOutput out = trainable.loss(idx, BatchShard{});
    out.loss = out.loss / dp->world();
    for (auto& [k, v] : out.parts) v = v / dp->world();
    return out;
  }
  BatchShard shard(dp);
  BatchRowsScope rows(shard.rows(static_cast<int64_t>(idx.size())));
  return trainable.loss(idx, shard);
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

// Everything the loop carries from one step to the next besides the weights,
// optimiser, EMA and sampler: all of it is checkpointed, so a run stopped at any
// step (not only a logged one) resumes to the uninterrupted metrics.csv.
struct LoopState {
  int64_t step = 0;
  double wall = 0;                      // seconds spent in earlier invocations
  double last_loss = NAN;               // loss of the last step (summary's final_loss)
  std::map<std::string, double> accum;  // sums since the last metrics.csv row
  int64_t accum_n = 0;
};

// The bytes of a checkpoint (a torch archive) of the loop's whole state.
std::string serialize_checkpoint(Trainable& tr, torch::optim::Optimizer& opt, const std::vector<torch::Tensor>& ema,
                                 const LoopState& st, const EpochSampler& sampler) {
  torch::serialize::OutputArchive ar;
  torch::serialize::OutputArchive model_ar, opt_ar;
  tr.module().save(model_ar);
  opt.save(opt_ar);
  ar.write("format_version", torch::tensor(static_cast<int64_t>(kCheckpointFormat)));
  ar.write("model", model_ar);
  ar.write("optimizer", opt_ar);
  for (size_t i = 0; i < ema.size(); ++i) ar.write(fmt::format("ema.{}", i), ema[i]);
  ar.write("step", torch::tensor(st.step));
  ar.write("wall", torch::tensor(st.wall, torch::kFloat64));
  ar.write("last_loss", torch::tensor(st.last_loss, torch::kFloat64));
  std::string keys;
  std::vector<double> sums;
  for (auto& [k, v] : st.accum) {
    keys += k + "\n";
    sums.push_back(v);
  }
  ar.write("accum_keys", c10::IValue(keys));
  ar.write("accum_sums", torch::tensor(sums, torch::kFloat64));
  ar.write("accum_n", torch::tensor(st.accum_n));
  ar.write("sampler_epoch", torch::tensor(sampler.epoch()));
  ar.write("sampler_pos", torch::tensor(sampler.pos()));
  ar.write("rng", rng_state());
  std::ostringstream os;
  ar.save_to(os);
  return os.str();
}

// Loads a checkpoint's archive bytes (`payload`; `source` names them in errors,
// `legacy` for a format-1 file) into the loop's state.
void load_checkpoint_bytes(const std::string& payload, bool legacy, const std::string& source, Trainable& tr,
                           torch::optim::Optimizer& opt, std::vector<torch::Tensor>& ema, LoopState& st,
                           EpochSampler& sampler) {
  std::istringstream in(payload);
  torch::serialize::InputArchive ar;
  try {
    ar.load_from(in);
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
    if (!legacy) {  // format 1 wrote checkpoints on logged steps only: nothing was accumulated
      torch::Tensor last_loss, sums, n;
      c10::IValue keys;
      ar.read("last_loss", last_loss);
      ar.read("accum_keys", keys);
      ar.read("accum_sums", sums);
      ar.read("accum_n", n);
      st.last_loss = last_loss.item<double>();
      st.accum_n = n.item<int64_t>();
      std::istringstream ks(keys.toStringRef());
      int64_t i = 0;
      for (std::string k; std::getline(ks, k);) st.accum[k] = sums[i++].item<double>();
    }
    sampler.restore(epoch.item<int64_t>(), pos.item<int64_t>());
    set_rng_state(rng);
  } catch (const c10::Error& e) {
    fail("checkpoint '{}' is unreadable or belongs to another model ({}); delete it or use run.force=true", source,
         std::string(e.what_without_backtrace()).substr(0, 200));
  }
}

bool all_finite(const std::vector<torch::Tensor>& ts) {
  torch::NoGradGuard ng;
  for (const auto& t : ts)
    if (!torch::isfinite(t).all().item<bool>()) return false;
  return true;
}

// The loss of one process (or this rank's share of it) on the global batch `idx`.
using ShareOfLoss = std::function<LossOutput(const std::vector<int64_t>& idx)>;

// The loss the weights would give on the next batch, without changing anything
// the run carries on with (sampler copied, torch RNG restored, no gradients, eval
// mode so no running statistic or EMA codebook moves): a checkpoint written where
// the loop stops, and the last step's weights, are checked with it, since no
// later step will. Weights of ~3e38 are finite yet give an infinite loss.
// Data-parallel: every rank calls it at the same step and gets the summed loss.
double probe_loss(Trainable& tr, const ShareOfLoss& loss, EpochSampler sampler, int batch, DataParallel* dp) {
  torch::Tensor rng = rng_state();
  const bool was_training = tr.module().is_training();
  tr.module().eval();
  double v = 0;
  try {
    torch::NoGradGuard ng;
    v = loss(sampler.next(batch)).loss.item<double>();
  } catch (const c10::Error&) {
    v = 0;  // a loss that cannot run without gradients is not probed; the weights were checked
  }
  tr.module().train(was_training);
  set_rng_state(rng);
  if (dp) v = dp->sum_scalars({v}, "the loss probe")[0];
  return v;
}

// The loss column of metrics.csv's last row (final_loss of a format-1 checkpoint
// taken on the last step, which did not record the step's own loss).
double last_logged_loss(const fs::path& metrics) {
  if (!fs::exists(metrics)) return NAN;
  std::istringstream in(read_file(metrics));
  std::string header, line, last;
  std::getline(in, header);
  while (std::getline(in, line))
    if (!line.empty()) last = line;
  std::istringstream hs(header), ls(last);
  for (std::string h, v; std::getline(hs, h, ',') && std::getline(ls, v, ',');)
    if (h == "loss") return std::strtod(v.c_str(), nullptr);
  return NAN;
}

std::string format_eta(double seconds) {
  if (!std::isfinite(seconds) || seconds < 0) return "?";
  int s = static_cast<int>(seconds);
  return s >= 3600 ? fmt::format("{}h{:02}m", s / 3600, s / 60 % 60) : fmt::format("{}m{:02}s", s / 60, s % 60);
}

// The config text of an existing run directory is the same run as `identity`
// (identity_yaml of the job): equal once the non-identity fields are cleared.
bool same_train_run(const std::string& existing_yaml, const std::string& identity) {
  try {
    TrainJobConfig old;
    parse_config(config_from_string(existing_yaml, "config.yaml"), old);
    return identity_yaml(old) == identity;
  } catch (const UserError&) {
    return false;  // written by a version with other fields: not provably the same run
  }
}

}  // namespace

// ---------------------------------------------------------------- checkpoint files

namespace {
constexpr const char* kCheckpointMagic = "motionctl-checkpoint";
}

void write_checkpoint_file(const fs::path& path, const std::string& payload) {
  const std::string header = fmt::format("{} {} sha1 {} bytes {}\n", kCheckpointMagic, kCheckpointFormat,
                                         c10::sha1(payload).str(), payload.size());
  write_file_atomic(path, header + payload);
}

std::string read_checkpoint_payload(const fs::path& path, bool* legacy) {
  std::string bytes = read_file(path);
  if (legacy) *legacy = false;
  if (bytes.rfind("PK", 0) == 0) {  // format 1: a bare torch archive (a zip), no checksum
    if (legacy) *legacy = true;
    return bytes;
  }
  const auto nl = bytes.find('\n');
  std::istringstream head(bytes.substr(0, nl == std::string::npos ? 0 : std::min<size_t>(nl, 200)));
  std::string magic, sha_word, sha, bytes_word;
  int format = 0;
  size_t size = 0;
  head >> magic >> format >> sha_word >> sha >> bytes_word >> size;
  const std::string fix = "delete it to restart the run from its beginning, or pass run.force=true";
  if (nl == std::string::npos || magic != kCheckpointMagic || sha_word != "sha1" || bytes_word != "bytes")
    fail("checkpoint '{}' is corrupt: it does not start with a motionctl checkpoint header; {}", path.string(), fix);
  if (format > kCheckpointFormat)
    fail("checkpoint '{}' has format {}, newer than this motionctl reads ({}); update motionctl", path.string(), format,
         kCheckpointFormat);
  std::string payload = bytes.substr(nl + 1);
  if (payload.size() != size)
    fail("checkpoint '{}' is corrupt: {} bytes after the header, the header says {} (truncated?); {}", path.string(),
         payload.size(), size, fix);
  const std::string got = c10::sha1(payload).str();
  if (got != sha)
    fail("checkpoint '{}' is corrupt: its SHA-1 is {}, the header says {}; {}", path.string(), got, sha, fix);
  return payload;
}
// ---------------------------------------------------------------- loop

TrainResult train(TrainJobConfig& job, const std::vector<std::string>& overrides, const std::string& default_name,
                  const TrainLoopOptions& loop) {
  const int64_t stop_after = loop.stop_after;
  DataParallel* dp = loop.data_parallel;  // null: one process
  const bool writer = !dp || dp->rank() == 0;  // rank 0 alone touches the run directory
  const int world = dp ? dp->world() : 1;
  if (job.run.checkpoint_every % job.run.log_every != 0)
    fail("run.checkpoint_every ({}) must be a multiple of run.log_every ({}) so checkpoints fall on logged steps",
         job.run.checkpoint_every, job.run.log_every);
  check_batch_divides(job, world);
  TrainResult result;
  const std::string yaml = dump_config(job);
  const std::string identity = identity_yaml(job);
  const RunDir::SameRun same = [&](const std::string& old) { return same_train_run(old, identity); };
  auto finished_result = [&](RunDir& run) {
    run.log().info(fmt::format("{} is finished; nothing to do (run.force=true redoes it)", run.path().string()));
    result.run_dir = run.path();
    result.skipped = true;
    result.summary = run.summary();
    if (dp) dp->announce_start("finished");
    return result;
  };
  auto retrain_command = [&] {
    std::string cmd = "motionctl train " + (loop.config_file.empty() ? "<its training config>" : loop.config_file);
    for (const auto& o : overrides) cmd += " " + o;
    return cmd + " run.force=true";
  };
  // Why the run is trained again from scratch (a stale finished or half-trained
  // run); logged once its directory is cleared, so its new log.txt says it too.
  std::string restart_reason;
  // Whether the finished run `run` may be reused with the components its model is
  // built on resolved as `now` (train/dependency_record.h). A legacy run (no record)
  // that nothing shows stale is taken as built on them, with one warning, and the
  // record is written, so from then on a retrained dependency is noticed.
  auto reusable = [&](RunDir& run, const std::vector<ResolvedDependency>& now) {
    const DependencyCheck c = check_dependencies(run.path(), now);
    if (c.state == DependencyCheck::State::stale) {
      restart_reason =
          fmt::format("{} was trained on {}: retraining", run.path().string(), fmt::join(c.reasons, "; "));
      return false;
    }
    if (c.state == DependencyCheck::State::unrecorded) {
      write_dependency_record(run.path(), now,
                              fmt::format("adopted {}: the run predates dependency records; taken as built on the "
                                          "components its config resolved to when it was adopted",
                                          utc_timestamp()));
      run.log().info(fmt::format("warning: {} has no record of the components it was built on (trained before "
                                 "motionctl kept one): taking it as built on today's {}; if one of them was retrained "
                                 "since, retrain it with `{}`",
                                 run.path().string(), describe_dependencies(now), retrain_command()));
    }
    return true;
  };

  // Everything the loop works on; rank 0 builds it first (it may train components
  // the model needs, and claims the run directory), the other ranks once rank 0
  // has started.
  torch::Device device = torch::kCPU;
  std::shared_ptr<MotionDataset> data;
  std::unique_ptr<Trainable> trainable;
  std::vector<torch::Tensor> params;
  int64_t n_params = 0;
  std::optional<torch::optim::AdamW> opt;
  std::vector<torch::Tensor> ema;
  std::optional<EpochSampler> sampler;
  std::vector<ResolvedDependency> deps;  // the components the model is built on, as build() resolved them
  auto build = [&] {
    // Everything that can refuse the job is checked before the run directory is
    // claimed, so a failed start leaves no directory (an explicit run.name stays free).
    device = setup_torch(job.run, dp ? dp->env().local_world : 1);
    const int threads = torch::get_num_threads();
    data = MotionDataset::load(resolve_data_path(job.data.path));
    TrainContext ctx{data, device, &job, job.data.window, job.data.trim_padding, job.optim.ema_decay};
    // The components the model is built on (a frozen base, a tokenizer, a text
    // encoder) are trained here, by the job, if missing; the model only loads them.
    deps = resolve_dependencies(job.model);
    trainable = make_trainable(job.model, ctx);
    // A component trained on demand for the model (rank 0) sets its own thread count.
    if (dp) torch::set_num_threads(threads);
    data->split("train");  // UserError naming the file and split when empty
    for (const auto& s : trainable->evaluation_splits()) data->split(s);
    trainable->module().to(device);
    params = trainable->trainable_parameters();
    for (auto& p : params) n_params += p.numel();
    opt.emplace(make_optimizer(job.optim, params));
    if (job.optim.ema_decay > 0)
      for (auto& p : params) ema.push_back(p.detach().clone());
    sampler.emplace(make_sampler(job, *data));
  };

  std::optional<RunDir> run_holder;
  std::optional<InterruptScope> interrupt_scope;
  std::optional<MetricsCsv> metrics;
  LoopState st;
  fs::path last;
  int64_t saved_step = -1;  // step of the checkpoint on disk (-1: none)
  Logger quiet;             // ranks > 0: nothing is logged (the lines would go to stderr only)
  std::string start_state;  // rank 0's state at the start, for the other ranks
  if (writer) {
    try {
      // A finished run is a no-op, answered without loading data or building the
      // model, while the components it was built on are still the ones its config
      // resolves to: resolving them first trains what is missing or stale below it
      // (transitively: a retrained tokenizer makes its TMD prior stale, which makes
      // the TMD's adapters stale). A stale run stays locked (`held`) until it is
      // opened again to be trained from scratch, as with run.force=true.
      RunConfig open_as = job.run;
      std::shared_ptr<RunLock> held;
      if (!job.run.force && fs::exists(RunDir::path_of(job.run, default_name) / "DONE")) {
        RunDir run = RunDir::open(job.run, yaml, overrides, default_name, same);
        if (run.finished()) {
          if (reusable(run, resolve_dependencies(job.model, nullptr))) return finished_result(run);
          held = RunLock::acquire(run.path());
          open_as.force = true;
        }
      }
      build();
      run_holder.emplace(RunDir::open(open_as, yaml, overrides, default_name, same));
      // Finished by another process meanwhile (it resolved the same components).
      if (run_holder->finished()) return finished_result(*run_holder);
      last = run_holder->checkpoints() / "last.pt";
      if (const auto c = fs::exists(last) ? check_dependencies(run_holder->path(), deps) : DependencyCheck{};
          c.state == DependencyCheck::State::stale) {
        // Resuming on other components than the run started on would mix two trainings.
        restart_reason = fmt::format("{} was being trained on {}: starting it again from scratch",
                                     run_holder->path().string(), fmt::join(c.reasons, "; "));
        held = RunLock::acquire(run_holder->path());
        run_holder.reset();
        open_as.force = true;
        run_holder.emplace(RunDir::open(open_as, yaml, overrides, default_name, same));
      }
      held.reset();
      RunDir& run = *run_holder;
      result.run_dir = run.path();
      if (!restart_reason.empty()) run.log().info(restart_reason);
      if (!fs::exists(last))
        write_dependency_record(run.path(), deps);
      else if (!read_dependency_record(run.path()))
        write_dependency_record(run.path(), deps,
                                fmt::format("recorded when resumed at {}: the run was started before dependency "
                                            "records",
                                            utc_timestamp()));
      interrupt_scope.emplace();
      metrics.emplace(run.metrics_path());
      const std::string ranks = dp ? fmt::format(", {} data-parallel processes", world) : "";
      if (fs::exists(last)) {
        bool legacy = false;
        const std::string payload = read_checkpoint_payload(last, &legacy);
        if (legacy)
          run.log().info(
              fmt::format("{} predates checksummed checkpoints (format 1); loading it unchecked", last.string()));
        load_checkpoint_bytes(payload, legacy, last.string(), *trainable, *opt, ema, st, *sampler);
        saved_step = st.step;
        metrics->truncate_after(st.step);
        run.log().info(fmt::format("resuming {} from step {} ({} threads{})", run.path().string(), st.step,
                                   torch::get_num_threads(), ranks));
        if (dp) start_state = payload;
      } else {
        fs::remove(run.metrics_path());
        run.log().info(fmt::format("training {} ({} trainable parameters, {} threads{}, device {}) in {}",
                                   job.model.type, n_params, torch::get_num_threads(), ranks, device.str(),
                                   run.path().string()));
      }
    } catch (const UserError& e) {
      if (dp) dp->announce_start(std::string("error: ") + e.what());
      throw;
    } catch (const std::exception& e) {
      if (dp) dp->announce_start(std::string("failed: ") + e.what());
      throw;
    }
  } else {
    const std::string status = dp->await_start();
    if (status == "finished") {
      result.run_dir = RunDir::path_of(job.run, default_name);
      result.skipped = true;
      return result;
    }
    if (status.rfind("error: ", 0) == 0)
      fail("rank 0 could not start the job: {}", status.substr(std::strlen("error: ")));
    if (status != "ok")
      throw DataParallelError(fmt::format("data-parallel rank {}: rank 0 failed to start ({})", dp->rank(), status));
    build();
    interrupt_scope.emplace();
    result.run_dir = RunDir::path_of(job.run, default_name);
  }
  Logger& log = writer ? run_holder->log() : quiet;

  // Data-parallel: rank 0's state (its last checkpoint, or its freshly built weights)
  // reaches every rank, so all start from the same weights, optimiser, EMA, step,
  // data position and random stream; then the gradient buckets.
  if (dp) {
    if (writer) {
      if (start_state.empty()) start_state = serialize_checkpoint(*trainable, *opt, ema, st, *sampler);
      dp->announce_start("ok");
    }
    dp->broadcast(start_state);
    if (!writer) {
      load_checkpoint_bytes(start_state, false, "rank 0's training state", *trainable, *opt, ema, st, *sampler);
      saved_step = st.step;
    }
    start_state.clear();
    start_state.shrink_to_fit();
    dp->attach(params);
  }

  const ShareOfLoss share = [&](const std::vector<int64_t>& idx) { return loss_share(*trainable, idx, dp); };

  auto diverged = [&](const std::string& what) {
    const std::string kept = saved_step >= 0 ? fmt::format("its last good checkpoint (step {}) is kept", saved_step)
                                             : std::string("no checkpoint had been written");
    fail("training diverged: {} in {}; nothing of the diverged steps was saved ({}). Lower optim.lr (now {:g}), or "
         "raise optim.warmup (now {}) or lower optim.grad_clip (now {:g}), and train again (a changed optim "
         "value is a new run)",
         what, result.run_dir.string(), kept, job.optim.lr, job.optim.warmup, job.optim.grad_clip);
  };

  const auto t0 = std::chrono::steady_clock::now();
  const int64_t first_step = st.step;
  auto wall_now = [&] {
    return st.wall + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  auto snapshot_state = [&] {
    LoopState s = st;
    s.wall = wall_now();
    return serialize_checkpoint(*trainable, *opt, ema, s, *sampler);
  };
  // A periodic checkpoint is written only once the next step's loss shows its
  // weights are sound (weights of ~3e38 are finite, yet give an infinite loss):
  // a diverged run never leaves a checkpoint it cannot resume from. Every rank
  // keeps the bookkeeping; rank 0 alone holds and writes the bytes.
  struct Pending {
    int64_t step;
    std::string bytes;
  };
  std::optional<Pending> pending;
  auto commit_pending = [&] {
    if (!pending) return;
    if (writer) write_checkpoint_file(last, pending->bytes);
    saved_step = pending->step;
    pending.reset();
  };
  // Where the loop stops early (--stop-after, a signal): no next step will check
  // this checkpoint, so the weights and a probe of the next batch's loss do.
  auto checkpoint_here = [&] {
    if (saved_step == st.step) return;
    if (!pending || pending->step != st.step) pending = Pending{st.step, writer ? snapshot_state() : std::string()};
    if (!all_finite(params) || !all_finite(ema)) diverged(fmt::format("the weights are not finite at step {}", st.step));
    const double probe = probe_loss(*trainable, share, *sampler, job.optim.batch_size, dp);
    if (!std::isfinite(probe)) diverged(fmt::format("the weights of step {} give a loss of {}", st.step, probe));
    commit_pending();
  };

  while (st.step < job.optim.steps) {
    double lr = scheduled_lr(job.optim, st.step);
    for (auto& g : opt->param_groups()) static_cast<torch::optim::AdamWOptions&>(g.options()).lr(lr);
    auto idx = sampler->next(job.optim.batch_size);
    LossOutput out = share(idx);
    opt->zero_grad();
    if (dp) dp->begin_backward();
    out.loss.backward();
    const std::string step_name = fmt::format("step {}", st.step + 1);
    if (dp) dp->finish_gradients(step_name);
    // The step's loss and parts (summed shares), and whether a rank was asked to
    // stop: every rank then decides the same.
    std::vector<double> scalars{out.loss.item<double>()};
    for (auto& [k, v] : out.parts) scalars.push_back(v.item<double>());
    int stop_signal = 0;
    if (dp) {
      const int sig = interrupt_requested();
      scalars.push_back(sig == SIGINT ? 1 : 0);
      scalars.push_back(sig != 0 && sig != SIGINT ? 1 : 0);
      scalars = dp->sum_scalars(scalars, fmt::format("the loss of {}", step_name));
      const double term = scalars.back(), intr = scalars[scalars.size() - 2];
      stop_signal = term > 0 ? SIGTERM : intr > 0 ? SIGINT : 0;
    }
    const double loss_v = scalars[0];
    if (!std::isfinite(loss_v)) diverged(fmt::format("the loss is {} at step {}", loss_v, st.step));
    commit_pending();  // the weights it holds just gave a finite loss
    double gnorm = 0;
    if (job.optim.grad_clip > 0) gnorm = torch::nn::utils::clip_grad_norm_(params, job.optim.grad_clip);
    opt->step();
    if (!ema.empty()) {
      torch::NoGradGuard ng;
      double d = std::min(job.optim.ema_decay, (1.0 + st.step) / (10.0 + st.step));  // warm EMA for short runs
      for (size_t i = 0; i < ema.size(); ++i) ema[i].mul_(d).add_(params[i].detach(), 1.0 - d);
    }
    ++st.step;
    st.accum["loss"] += loss_v;
    for (size_t i = 0; i < out.parts.size(); ++i) st.accum[out.parts[i].first] += scalars[1 + i];
    st.accum["grad_norm"] += gnorm;
    ++st.accum_n;
    st.last_loss = loss_v;

    double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    double ips = (st.step - first_step) / std::max(1e-9, elapsed);
    std::string line = fmt::format("step {}/{} loss {:.5f} lr {:.2e} {:.1f} it/s ETA {}", st.step, job.optim.steps,
                                   loss_v, lr, ips, format_eta((job.optim.steps - st.step) / ips));
    if (writer) log.progress(line);
    bool last_step = st.step == job.optim.steps;
    if (st.step % job.run.log_every == 0 || last_step) {
      std::vector<std::pair<std::string, double>> row{{"wall_time", wall_now()}, {"lr", lr}};
      for (auto& [k, v] : st.accum) row.emplace_back(k, v / st.accum_n);
      if (writer) metrics->append(st.step, row);
      st.accum.clear();
      st.accum_n = 0;
      if (writer && !Logger::interactive()) log.info(line);
    }
    if (st.step % job.run.checkpoint_every == 0 && !last_step) {
      if (!all_finite(params) || !all_finite(ema)) diverged(fmt::format("the weights are not finite at step {}", st.step));
      pending = Pending{st.step, writer ? snapshot_state() : std::string()};
    }
    if (loop.snapshot_every > 0 && st.step % loop.snapshot_every == 0 && !last_step) {
      if (!all_finite(params) || !all_finite(ema)) diverged(fmt::format("the weights are not finite at step {}", st.step));
      if (writer) {
        // The weights final.pt would hold now: EMA swapped in, saved, swapped back.
        torch::NoGradGuard ng;
        std::vector<torch::Tensor> live;
        for (size_t i = 0; i < ema.size(); ++i) {
          live.push_back(params[i].detach().clone());
          params[i].copy_(ema[i]);
        }
        torch::serialize::OutputArchive ar;
        trainable->module().save(ar);
        AtomicOutput snap(run_holder->checkpoints() / fmt::format("snapshot_{:06d}.pt", st.step));
        ar.save_to(snap.tmp_path().string());
        snap.commit();
        for (size_t i = 0; i < live.size(); ++i) params[i].copy_(live[i]);
        // Vocabulary and metadata too, so a snapshot of a run still training can be loaded.
        trainable->save_artifacts(run_holder->outputs());
      }
    }
    if (last_step) break;
    // One process acts on a signal as soon as the step ends; data-parallel ranks on
    // the step's summed flags, so they all stop at the same step.
    if (const int sig = dp ? stop_signal : interrupt_requested()) {
      if (writer) log.end_progress();
      checkpoint_here();
      clear_interrupt();
      const std::string msg = fmt::format("interrupted by signal {} at step {}: checkpoint written in {}; running "
                                          "the same command again resumes from it",
                                          sig, st.step, (result.run_dir / "checkpoints" / "last.pt").string());
      if (writer) log.info(msg);
      throw Interrupted(sig, msg);
    }
    if (stop_after > 0 && st.step - first_step >= stop_after) {
      if (writer) log.end_progress();
      checkpoint_here();
      if (writer)
        log.info(fmt::format("stopping at step {} as asked: checkpoint written in {}; running the same command "
                             "again resumes from it",
                             st.step, last.string()));
      result.summary["step"] = st.step;
      return result;
    }
  }
  if (writer) log.end_progress();

  // The end: the training state of the last step, then the final weights (the
  // EMA copy when there is one) and their evaluation. Each is checked before
  // anything is written, so last.pt, final.pt, summary.csv and DONE only ever
  // hold finite numbers; last.pt comes first, so a kill before DONE resumes
  // here without training again. Ranks > 0 are done once the weights are checked.
  if (!all_finite(params) || !all_finite(ema)) diverged(fmt::format("the weights are not finite at step {}", st.step));
  if (const double probe = probe_loss(*trainable, share, *sampler, job.optim.batch_size, dp); !std::isfinite(probe))
    diverged(fmt::format("the weights of the last step ({}) give a loss of {}", st.step, probe));
  if (!writer) {
    result.summary["step"] = st.step;
    return result;
  }
  RunDir& run = *run_holder;
  if (std::isnan(st.last_loss)) st.last_loss = last_logged_loss(run.metrics_path());  // format-1 checkpoint
  const std::string final_state = snapshot_state();
  if (!ema.empty()) {
    torch::NoGradGuard ng;
    for (size_t i = 0; i < ema.size(); ++i) params[i].copy_(ema[i]);
  }
  // run.final_weights.dtype: the weights are rounded before they are evaluated, so
  // the summary describes exactly the weights final.pt stores.
  const torch::ScalarType final_dtype = weights_dtype(job.run.final_weights.dtype);
  round_module_weights(trainable->module(), final_dtype, run.path().string());
  trainable->module().eval();
  std::map<std::string, double> summary = trainable->evaluate();
  summary["steps"] = static_cast<double>(st.step);
  summary["final_loss"] = st.last_loss;
  summary["trainable_params"] = static_cast<double>(n_params);
  summary["wall_time"] = wall_now();
  for (auto& [k, v] : summary)
    if (!std::isfinite(v)) diverged(fmt::format("the final weights give {} = {}", k, v));
  if (saved_step != st.step) write_checkpoint_file(last, final_state);
  {
    AtomicOutput out(run.checkpoints() / "final.pt");
    save_module_weights(trainable->module(), final_dtype, out.tmp_path());
    out.commit();
  }
  trainable->save_artifacts(run.outputs());
  for (auto& [k, v] : summary) log.info(fmt::format("  {} = {:.6g}", k, v));
  run.mark_finished(summary);
  result.summary = summary;
  return result;
}

}  // namespace mc
