// check_train_resources (train/train_resources.h). The estimate reads the resolved
// config generically (model.width, model.depth, optim.batch_size, data.window), so
// every model type is covered without a formula per type; it is deliberately a
// lower bound: 3 d^2 weights per layer (a transformer block has ~12 d^2, a kernel-3
// conv 3 d^2), each held four times (weights, gradients, two
// Adam moments), and one [batch, frames, d] activation plus its gradient per block.
#include "train/train_resources.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>

#include "core/config.h"
#include "core/resources.h"
#include "train/trainer.h"

namespace mc {
namespace {

long double number_at(const YAML::Node& section, const char* key, long double fallback) {
  if (!section || !section.IsMap() || !section[key] || !section[key].IsScalar()) return fallback;
  try {
    return section[key].as<long double>();
  } catch (const YAML::Exception&) {
    return fallback;
  }
}

}  // namespace

void check_train_resources(TrainJobConfig& job) {
  check_thread_count(job.run.threads, "run.threads");
  const YAML::Node root = YAML::Load(dump_config(job));
  const YAML::Node model = root["model"];
  // Layers that keep an activation: transformer blocks (depth), or for the conv
  // models a strided conv plus res_depth residual blocks per stage, in both the
  // encoder and the decoder (one conv per block counted, to stay a lower bound).
  const long double depth = std::max<long double>(1, number_at(model, "depth", 1)) +
                            2 * number_at(model, "down_stages", 0) * (1 + number_at(model, "res_depth", 0));
  long double width = number_at(model, "width", 0);
  if (width <= 0) width = 64 * depth;  // the flow models' "0 = 64 * depth"
  const long double batch = number_at(root["optim"], "batch_size", 1);
  long double frames = number_at(root["data"], "window", 0);
  if (frames <= 0) frames = 196;  // whole clips: HumanML3D's longest
  const long double weights = 3 * width * width * depth * 4 /*copies*/ * 4 /*bytes*/;
  const long double activations = batch * frames * width * depth * 2 /*value + gradient*/ * 4 /*bytes*/;
  require_memory(weights + activations, "this training job",
                 fmt::format("model.width={} and {} layers: >= {} of weights, gradients and Adam moments; "
                             "optim.batch_size={} x {} frames: >= {} of activations",
                             static_cast<double>(width), static_cast<double>(depth), format_bytes(weights),
                             static_cast<double>(batch), static_cast<double>(frames), format_bytes(activations)),
                 weights > activations ? "lower model.width (or model.depth)" : "lower optim.batch_size (or data.window)");
}

}  // namespace mc
