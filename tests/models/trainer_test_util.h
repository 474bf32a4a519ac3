// Trainables for loss tests: a model section (YAML under `model:`) trained on a few
// random in-memory clips, and the same random weights for paired arms. Shared by
// the flow prior's and the tokenizer's loss tests.
#pragma once
#include <initializer_list>
#include <memory>
#include <string>
#include <vector>

#include "../data/data_test_util.h"
#include "core/config.h"
#include "data/normalizer.h"
#include "data/text_vocab.h"
#include "models/motion_dataset.h"
#include "models/trainable.h"
#include "train/trainer.h"

namespace mc::test {

// Parses `model_yaml` into `job` and builds its trainable on random clips of
// `lengths` (the first two train, the rest val), with the set's norm stats and
// vocabulary. The RNG is seeded just before construction, so two trainers built
// from the same lengths start from the same weights and buffers.
inline std::unique_ptr<Trainable> trainer_on_random_clips(TrainJobConfig& job, const std::string& model_yaml,
                                                          const std::vector<int>& lengths, bool trim = false,
                                                          std::shared_ptr<MotionDataset>* data_out = nullptr) {
  parse_config(config_from_string(model_yaml), job);
  std::vector<std::string> splits(lengths.size(), "val");
  for (size_t i = 0; i < splits.size() && i < 2; ++i) splits[i] = "train";
  MotionSet set = random_motion_set(lengths, splits);
  set.stats = compute_norm_stats(set);
  set.vocab = TextVocab::build(set).words();
  auto data = std::make_shared<MotionDataset>(set, "<memory>");
  if (data_out) *data_out = data;
  torch::manual_seed(4);
  TrainContext ctx{data, torch::kCPU, &job, 0, trim};
  return make_trainable(job.model, ctx);
}

// The same non-trivial weights in every trainer (AdaLN-Zero would make a flow
// prior's output 0), so arms that differ only in their loss see the same network.
inline void same_random_weights(std::initializer_list<Trainable*> trainers) {
  for (auto* tr : trainers) {
    torch::manual_seed(21);
    torch::NoGradGuard ng;
    for (auto& p : tr->module().parameters()) p.normal_(0.0, 0.1);
  }
}

}  // namespace mc::test
