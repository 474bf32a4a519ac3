// The generic training loop: AdamW, warm-up/decay schedule as a pure function of
// the step, EMA, gradient clipping, logging, atomic checkpoints and exact resume.
#pragma once
#include <map>
#include <string>

#include "core/config.h"
#include "core/run_dir.h"
#include "models/motion_dataset.h"
#include "models/trainable.h"

namespace mc {

class DataParallel;  // train/distributed.h

struct OptimConfig : Config {
  int steps = 1000;
  int batch_size = 64;
  double lr = 2e-4;
  std::vector<double> betas = {0.9, 0.99};
  double weight_decay = 1e-5;
  int warmup = 100;
  std::string schedule = "step";  // constant | step | cosine
  std::vector<int> decay_at = {};
  double decay_factor = 0.1;
  double min_lr_ratio = 0.0;
  double grad_clip = 1.0;
  double ema_decay = 0.999;
  void visit(FieldVisitor& v) override {
    v("steps", steps, "optimiser steps", at_least(1));
    v("batch_size", batch_size, "clips per step", at_least(1));
    v("lr", lr, "peak learning rate", positive<double>());
    v("betas", betas, "AdamW betas", each(in_range(0.0, 0.999999)));
    v("weight_decay", weight_decay, "AdamW decoupled weight decay", at_least(0.0));
    v("warmup", warmup, "linear warm-up steps from 0 to lr", at_least(0));
    v("schedule", schedule, "after warm-up: constant, step (x decay_factor at each decay_at) or cosine",
      one_of({"constant", "step", "cosine"}));
    v("decay_at", decay_at, "steps where the step schedule multiplies lr by decay_factor", each(at_least(0)));
    v("decay_factor", decay_factor, "step-schedule multiplier", in_range(0.0, 1.0));
    v("min_lr_ratio", min_lr_ratio, "cosine floor as a fraction of lr", in_range(0.0, 1.0));
    v("grad_clip", grad_clip, "max global gradient L2 norm (0 = off)", at_least(0.0));
    v("ema_decay", ema_decay, "EMA decay of the weights (0 = no EMA)", in_range(0.0, 1.0));
  }
  std::string validate() const override {
    if (betas.size() != 2) return "optim.betas needs two numbers, e.g. [0.9, 0.99]";
    return "";
  }
};

// The AdamW optimiser of `o` (lr, betas, weight decay) over `params`: the one
// training and `bench train` step with.
torch::optim::AdamW make_optimizer(const OptimConfig& o, const std::vector<torch::Tensor>& params);

// Learning rate at `step` (0-based): a pure function so resume needs no state.
double scheduled_lr(const OptimConfig& o, int64_t step);

// What `motionctl train` parses: run, data, model (by type) and optimiser.
struct TrainJobConfig : Config {
  RunConfig run;
  DataConfig data;
  Component model{"model"};
  OptimConfig optim;
  void visit(FieldVisitor& v) override {
    v("run", run, "run directory, seed, threads, device");
    v("data", data, "training data");
    v("model", model, "the model to train (picked by type)");
    v("optim", optim, "optimiser and schedule");
  }
};

struct TrainResult {
  fs::path run_dir;
  bool skipped = false;  // finished earlier; nothing done
  std::map<std::string, double> summary;
};

// Epoch-wise shuffled batches; the permutation of an epoch depends only on
// (seed, epoch), so (epoch, pos) is the whole state. With `buckets` > 0 and clip
// `lengths` (indexed by clip id), groups of `buckets` batches are sorted by length
// before the batches are shuffled (data.length_buckets).
class EpochSampler {
 public:
  EpochSampler(std::vector<int64_t> pool, uint64_t seed, std::vector<int64_t> lengths = {}, int batch = 0,
               int buckets = 0);
  std::vector<int64_t> next(int n);
  int64_t epoch() const { return epoch_; }
  int64_t pos() const { return pos_; }
  void restore(int64_t epoch, int64_t pos);

 private:
  void shuffle();
  std::vector<int64_t> pool_, order_, lengths_;
  uint64_t seed_;
  int batch_ = 0, buckets_ = 0;
  int64_t epoch_ = 0, pos_ = 0;
};

// The training sampler a job uses: its train split, seed, batch and length buckets.
EpochSampler make_sampler(const TrainJobConfig& job, const MotionDataset& data);

// UserError unless optim.batch_size (the global batch) divides over `processes`.
void check_batch_divides(const TrainJobConfig& job, int processes);

// This rank's share of the loss of the global batch `idx` (train/batch_shard.h):
// the whole batch in one process (dp null); with data parallelism the rank's shard
// when the trainable computes shards (its dropout rows set, models/sharded_dropout.h),
// else the whole batch on every rank, counted 1 / ranks times.
LossOutput loss_share(Trainable& trainable, const std::vector<int64_t>& idx, DataParallel* dp);

// Applies run.threads/device/seed; returns the device. `ranks_here` processes of a
// data-parallel job share this machine: each takes run.threads / ranks_here
// threads (at least one; run.threads = 0 means all cores, or $OMP_NUM_THREADS).
torch::Device setup_torch(const RunConfig& run, int ranks_here = 1);

// checkpoints/last.pt: a header line "motionctl-checkpoint <format> sha1 <hex>
// bytes <n>" then the torch archive it checks. Format 1 (a bare archive, before
// the header) is still read, unchecked.
inline constexpr int kCheckpointFormat = 2;
// Writes `payload` (a torch archive's bytes) atomically with its header.
void write_checkpoint_file(const fs::path& path, const std::string& payload);
// The checked archive bytes of a checkpoint file; UserError naming the file when
// it is corrupt (header, size or SHA-1) or newer than this build. `legacy` (may
// be null) is set for a format-1 file.
std::string read_checkpoint_payload(const fs::path& path, bool* legacy = nullptr);

// How one invocation drives the loop. Not part of the config (and of the run's
// name): they change what is observed, never what is trained.
struct TrainLoopOptions {
  // > 0: stop (without finishing) after that many steps of this invocation,
  // writing a checkpoint at the step reached; running again resumes from it. Used
  // by tests of resume and to split long trainings.
  int64_t stop_after = 0;
  // > 0: every that many steps also write the weights a finished run would hold
  // at that step (the EMA copy when there is one) to checkpoints/snapshot_NNNNNN.pt,
  // in final.pt's format, for curves of health against training time.
  int64_t snapshot_every = 0;
  // Data-parallel training (issue 19; train/distributed.h): this process is one rank
  // of the job, which has already joined. Each rank computes its shard of every
  // global batch (optim.batch_size must divide over the ranks), gradients and the
  // step's scalars are summed over the ranks, and rank 0 alone writes the run
  // directory (lock, logs, metrics, checkpoints, final weights). Null: one process.
  DataParallel* data_parallel = nullptr;
};

// Trains (or resumes, or skips) the run described by `job`. `default_name` names
// the run directory when run.name is empty. The directory is locked for the
// call (RunLock) and claimed only once data, splits, device and model are
// checked. A non-finite loss or weight stops it with a UserError naming the knob
// to change, before anything of the diverged steps is written. SIGINT/SIGTERM
// write a checkpoint at the step reached and throw Interrupted (data-parallel:
// every rank stops at the same step).
TrainResult train(TrainJobConfig& job, const std::vector<std::string>& overrides, const std::string& default_name,
                  const TrainLoopOptions& loop = {});

}  // namespace mc
