// The plug-in point of the generic training loop: every trainable model (flow
// prior, tokenizer, TMD, adapters, evaluator, autoencoder) implements Trainable
// and registers under its `model.type`. It sits with the models that implement it;
// the loop that drives it (train/trainer.h) is a layer above.
#pragma once
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "core/run_dir.h"
#include "models/batch_shard.h"
#include "models/motion_dataset.h"

namespace mc {

struct LossOutput {
  torch::Tensor loss;                                        // scalar to minimise
  std::vector<std::pair<std::string, torch::Tensor>> parts;  // logged scalars (detached)
};

struct TrainContext {
  std::shared_ptr<MotionDataset> data;
  torch::Device device = torch::kCPU;
  const Config* job = nullptr;  // the whole job config, for models that need other sections
  int window = 0;
  bool trim_padding = false;  // data.trim_padding
  // optim.ema_decay: a model whose buffers follow the live weights (the VQ codebook)
  // refuses an EMA of them.
  double ema_decay = 0;
};

class Trainable {
 public:
  virtual ~Trainable() = default;
  virtual torch::nn::Module& module() = 0;
  // Parameters the optimiser updates (adapters return only theirs; the rest is frozen).
  virtual std::vector<torch::Tensor> trainable_parameters() { return module().parameters(); }
  // The loss of the batch `batch_indices` (clip ids; the whole, global batch).
  // Data-parallel training (train/batch_shard.h) passes the rank's shard: the
  // trainable then computes only the shard's rows and returns its share of the
  // loss and parts, which the trainer sums over ranks. A trainable that says so
  // in shards_batches(); one that does not is given the whole batch on every rank
  // (correct, but no faster than one process). One process: the whole batch.
  virtual LossOutput loss(const std::vector<int64_t>& batch_indices, const BatchShard& shard) = 0;
  LossOutput loss(const std::vector<int64_t>& batch_indices) { return loss(batch_indices, BatchShard{}); }
  // True when loss() computes only its shard's rows and returns shares.
  virtual bool shards_batches() const { return false; }
  // Metrics of the final (EMA) weights, e.g. validation reconstruction error.
  virtual std::map<std::string, double> evaluate() { return {}; }
  // The splits evaluate() reads: the loop checks them (and "train") before the
  // first step, so an empty one is refused up front, not after the training.
  virtual std::vector<std::string> evaluation_splits() const { return {"val"}; }
  // Multiply-add FLOPs (x2) of one training step (forward + backward) on this
  // batch, counting valid frames only; 0 = not known. `motionctl bench train`
  // reports the rate against sgemm's.
  virtual double flops_per_step(const std::vector<int64_t>& batch_indices) const {
    (void)batch_indices;
    return 0;
  }
  // Files a later user of the trained model needs besides the weights (e.g. a
  // vocabulary), written into the run directory's outputs/ when training ends.
  virtual void save_artifacts(const fs::path& outputs_dir) { (void)outputs_dir; }
};

// The validation losses the priors' evaluate() report at fixed times (flow times,
// TMD times, mask ratios): `chunk_values(t, chunk)` gives one chunk's
// `num_values` values and their weight (its valid frames, clips or target tokens), for every chunk of
// `chunk_size` clips of `idx` at every t of `times`, in order (so a generator the
// callback draws from is used in the same order on every call).
struct ChunkValues {
  std::vector<double> values;
  double weight = 0;
};
struct TimedValidation {
  std::vector<std::vector<double>> at_time;  // [time][value]: the chunks' weighted mean at that time
  std::vector<double> mean;                  // [value]: the mean of at_time over the times
};
TimedValidation validate_at_times(const std::vector<double>& times, const std::vector<int64_t>& idx, size_t chunk_size,
                                  size_t num_values,
                                  const std::function<ChunkValues(double, const std::vector<int64_t>&)>& chunk_values);

using TrainableFactory = std::function<std::unique_ptr<Trainable>(const Config& model_cfg, const TrainContext& ctx)>;
void register_trainable(const std::string& type, TrainableFactory make);
std::unique_ptr<Trainable> make_trainable(const Component& model, const TrainContext& ctx);

// Registers a model's config struct (family "model") and its trainable factory in one place.
#define MC_REGISTER_MODEL(TYPE, CONFIG, FACTORY, HELP)                                        \
  static const bool mc_model_registered_##CONFIG = [] {                                      \
    ::mc::register_component("model", TYPE, [] { return std::make_shared<CONFIG>(); }, HELP); \
    ::mc::register_trainable(TYPE, FACTORY);                                                  \
    return true;                                                                              \
  }()

}  // namespace mc
