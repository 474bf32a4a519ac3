// Normalised, cropped, padded batches from a motion file.
#include "models/motion_dataset.h"

#include <algorithm>

#include "core/error.h"

namespace mc {

MotionDataset::MotionDataset(MotionSet set, std::string source) : set_(std::move(set)), source_(std::move(source)) {
  const int64_t N = set_.size(), T = set_.t_max, J = set_.num_joints();
  all_ = torch::from_blob(set_.joints.data(), {N, T, J, 3}, torch::kFloat32);
  if (!set_.stats || set_.stats->joint_mean.size() != 3 || set_.stats->joint_std.size() != 3)
    fail("{}: no normalisation statistics (group 'stats'); rebuild it with `motionctl fixture` or the converter",
         source_);
  mean_ = torch::tensor(set_.stats->joint_mean, torch::kFloat32);
  std_ = torch::tensor(set_.stats->joint_std, torch::kFloat32);
}

std::shared_ptr<MotionDataset> MotionDataset::load(const std::string& path) {
  return std::make_shared<MotionDataset>(read_motion_file(path), path);
}

std::vector<int64_t> MotionDataset::split(const std::string& name) const {
  std::vector<int64_t> out;
  for (size_t i : set_.indices_of_split(name)) out.push_back(static_cast<int64_t>(i));
  if (out.empty()) fail("{}: split '{}' is empty", source_, name);
  return out;
}

std::vector<std::string> MotionDataset::drawn_captions(const std::vector<int64_t>& idx) const {
  std::vector<std::string> out;
  out.reserve(idx.size());
  for (int64_t i : idx) {
    const auto& c = set_.captions[i];
    out.push_back(c[torch::randint(0, static_cast<int64_t>(c.size()), {1}).item<int64_t>()]);
  }
  return out;
}

std::vector<std::string> MotionDataset::first_captions(const std::vector<int64_t>& idx) const {
  std::vector<std::string> out;
  out.reserve(idx.size());
  for (int64_t i : idx) out.push_back(set_.captions[i][0]);
  return out;
}

std::vector<std::vector<int64_t>> chunked(const std::vector<int64_t>& idx, size_t size) {
  std::vector<std::vector<int64_t>> out;
  for (size_t s = 0; s < idx.size(); s += size)
    out.emplace_back(idx.begin() + s, idx.begin() + std::min(idx.size(), s + size));
  return out;
}

torch::Tensor MotionDataset::normalize(const torch::Tensor& world) const {
  return (world - mean_.to(world.device())) / std_.to(world.device());
}

torch::Tensor MotionDataset::denormalize(const torch::Tensor& normed) const {
  return normed * std_.to(normed.device()) + mean_.to(normed.device());
}

MotionBatch MotionDataset::batch(const std::vector<int64_t>& idx, int window, int round_to,
                                 const torch::Device& device, bool trim, const BatchShard& shard) const {
  const int64_t J = num_joints();
  int64_t T = window > 0 ? window : set_.t_max;
  if (window == 0 && trim) {
    int64_t longest = 1;
    for (int64_t i : idx) longest = std::max<int64_t>(longest, set_.lengths[i]);
    T = std::min<int64_t>(T, longest);
  }
  if (round_to > 1) T = (T + round_to - 1) / round_to * round_to;
  // Every clip's crop is drawn, in order, whichever rows are built: a shard's
  // draws are the whole batch's.
  const int64_t Bw = idx.size();
  std::vector<int64_t> starts(Bw, 0), takes(Bw);
  for (int64_t b = 0; b < Bw; ++b) {
    int64_t len = set_.lengths[idx[b]];
    takes[b] = std::min(len, T);
    if (window > 0 && len > T) starts[b] = torch::randint(0, len - T + 1, {1}).item<int64_t>();
  }
  const BatchRows rows = shard.rows(Bw);
  const int64_t B = rows.size();
  auto x = torch::zeros({B, T, J, 3});
  auto mask = torch::zeros({B, T}, torch::kBool);
  auto lengths = torch::zeros({B}, torch::kInt64);
  for (int64_t b = 0; b < B; ++b) {
    const int64_t w = rows.begin + b;
    x[b].narrow(0, 0, takes[w]).copy_(normalize(all_[idx[w]].narrow(0, starts[w], takes[w])));
    mask[b].narrow(0, 0, takes[w]).fill_(true);
    lengths[b] = takes[w];
  }
  MotionBatch out{x.to(device), mask.to(device), lengths.to(device), shard.local(idx)};
  if (shard.whole()) {
    out.whole_mask = out.mask;
  } else {
    auto whole = torch::zeros({Bw, T}, torch::kBool);
    for (int64_t b = 0; b < Bw; ++b) whole[b].narrow(0, 0, takes[b]).fill_(true);
    out.whole_mask = whole.to(device);
  }
  return out;
}

}  // namespace mc
