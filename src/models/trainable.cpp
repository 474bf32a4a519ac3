// The registry of trainable model types (model.type -> Trainable factory): filled
// by each model's MC_REGISTER_MODEL, read by the training loop (train/trainer.cpp).
#include "models/trainable.h"

#include "core/error.h"

namespace mc {

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

}  // namespace mc
