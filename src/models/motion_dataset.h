// Torch view of a motion file for training: split indices, normalised joint
// batches with padding masks and random crops (drawn from torch's generator so
// checkpoints capture them).
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/motion_set.h"
#include "models/batch_shard.h"

namespace mc {

struct DataConfig : Config {
  std::string path = "data/fixture_smoke.h5";
  std::string fixture = "configs/data/smoke.yaml";  // built with `motionctl fixture` when `path` is missing
  int window = 64;                                  // training crop in frames; 0 = full padded length
  // Whole-clip batches (window 0) are padded only to their longest clip: the flow
  // loss and attention mask padding, so this changes no result, only the cost.
  bool trim_padding = true;
  // Length bucketing: the epoch's shuffled order is cut into groups of this many
  // batches, each group sorted by length, and the batches shuffled again, so a
  // batch holds clips of similar length and trimming removes most padding.
  int length_buckets = 0;
  void visit(FieldVisitor& v) override {
    v("path", path, "motion HDF5 file (docs/formats.md)");
    v("fixture", fixture, "fixture config that builds `path` when it is missing ('' = never build)");
    v("window", window, "training crop length in frames (0 = whole clip)", at_least(0));
    v("trim_padding", trim_padding, "whole-clip batches (window 0) pad only to their longest clip");
    v("length_buckets", length_buckets,
      "sort groups of this many batches by clip length so batches hold similar lengths (0 = plain shuffle)",
      in_range(0, 10000));
  }
};

struct MotionBatch {
  torch::Tensor joints;   // [B, T, J, 3] normalised
  torch::Tensor mask;     // [B, T] bool, true on valid frames
  torch::Tensor lengths;  // [B] int64
  std::vector<int64_t> indices;
  // The whole batch's mask [B_whole, T] when the batch is a data-parallel shard's
  // rows (for means over the whole batch's valid frames); else `mask` itself.
  torch::Tensor whole_mask;
};

class MotionDataset {
 public:
  MotionDataset(MotionSet set, std::string source);
  static std::shared_ptr<MotionDataset> load(const std::string& path);

  const MotionSet& set() const { return set_; }
  const std::string& source() const { return source_; }
  std::vector<int64_t> split(const std::string& name) const;  // UserError if empty
  int num_joints() const { return set_.num_joints(); }
  torch::Tensor joint_mean() const { return mean_; }  // (3,)
  torch::Tensor joint_std() const { return std_; }    // (3,)

  // Normalised clips; window > 0 crops a random window (padded when shorter),
  // `round_to` pads T up to a multiple (for strided convolutions). With window 0,
  // `trim` pads to the longest clip of the batch instead of t_max. With a shard,
  // its rows of that batch exactly: crops drawn for every clip of `idx` and the
  // whole batch's padded length.
  MotionBatch batch(const std::vector<int64_t>& idx, int window, int round_to, const torch::Device& device,
                    bool trim = false, const BatchShard& shard = {}) const;
  int64_t length(int64_t i) const { return set_.lengths[i]; }
  // One caption per clip of `idx`, in order. drawn_captions: uniformly among the
  // clip's captions, one draw per clip from torch's generator (so a checkpoint
  // resumes the same draws); the training losses use it. first_captions: each clip's
  // first caption, the same on every call; the validation passes use it.
  std::vector<std::string> drawn_captions(const std::vector<int64_t>& idx) const;
  std::vector<std::string> first_captions(const std::vector<int64_t>& idx) const;
  torch::Tensor normalize(const torch::Tensor& world) const;    // [..., 3]
  torch::Tensor denormalize(const torch::Tensor& normed) const;  // [..., 3]

 private:
  MotionSet set_;
  std::string source_;
  torch::Tensor all_;  // [N, t_max, J, 3] world
  torch::Tensor mean_, std_;
};

// `idx` cut into consecutive chunks of `size` clips (the last may be shorter): the
// batches of the validation passes.
std::vector<std::vector<int64_t>> chunked(const std::vector<int64_t>& idx, size_t size);

}  // namespace mc
