// The registry of trainable model types (model.type -> Trainable factory): filled
// by each model's MC_REGISTER_MODEL, read by the training loop (train/trainer.cpp);
// and the timed validation means the priors' evaluate() share.
#include "models/trainable.h"

#include <algorithm>
#include <stdexcept>

#include "core/error.h"

namespace mc {

static std::map<std::string, TrainableFactory>& trainables() {
  static std::map<std::string, TrainableFactory> r;
  return r;
}

void register_trainable(const std::string& type, TrainableFactory make) { trainables()[type] = std::move(make); }

TimedValidation validate_at_times(const std::vector<double>& times, const std::vector<int64_t>& idx, size_t chunk_size,
                                  size_t num_values,
                                  const std::function<ChunkValues(double, const std::vector<int64_t>&)>& chunk_values) {
  TimedValidation out;
  out.mean.assign(num_values, 0.0);
  for (double t : times) {
    std::vector<double> sums(num_values, 0.0);
    double weight = 0;
    for (const auto& chunk : chunked(idx, chunk_size)) {
      const ChunkValues c = chunk_values(t, chunk);
      if (c.values.size() != num_values)
        throw std::logic_error(
            fmt::format("validate_at_times: a chunk gave {} values, not {}", c.values.size(), num_values));
      for (size_t k = 0; k < num_values; ++k) sums[k] += c.values[k] * c.weight;
      weight += c.weight;
    }
    for (size_t k = 0; k < num_values; ++k) {
      sums[k] /= std::max(1.0, weight);
      out.mean[k] += sums[k];
    }
    out.at_time.push_back(std::move(sums));
  }
  for (double& m : out.mean) m /= times.size();
  return out;
}

std::unique_ptr<Trainable> make_trainable(const Component& model, const TrainContext& ctx) {
  auto it = trainables().find(model.type);
  if (it == trainables().end()) fail("model type '{}' has no trainer registered", model.type);
  return it->second(*model.cfg, ctx);
}

}  // namespace mc
