// Train-split normalisation statistics (two-pass, in double) and the affine maps
// between world/feature units and the normalised space models see.
#include "data/normalizer.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/error.h"

namespace mc {
namespace {

void require_joint_stats(const NormStats& s) {
  if (s.joint_mean.size() != 3 || s.joint_std.size() != 3)
    fail("normalisation stats need 3 joint means and stds (x, y, z), have {} and {}; recompute the statistics",
         s.joint_mean.size(), s.joint_std.size());
}

void require_feature_stats(const NormStats& s, int dim) {
  if (s.feature_mean.size() != static_cast<size_t>(dim) || s.feature_std.size() != static_cast<size_t>(dim))
    fail("normalisation stats have {} feature dims (layout '{}') but the features have {}; use statistics computed "
         "for the same feature layout",
         s.feature_mean.size(), s.feature_layout, dim);
}

// Mean and floored population std of samples added one vector at a time.
class MomentAccumulator {
 public:
  explicit MomentAccumulator(size_t dim) : sum_(dim, 0.0), sq_(dim, 0.0) {}
  // Two passes: first the means, then squared deviations (accurate where
  // E[x^2] - E[x]^2 would cancel, e.g. a root height of 0.9 +- 1e-3).
  void add_mean(const float* v) {
    for (size_t d = 0; d < sum_.size(); ++d) sum_[d] += v[d];
    ++count_;
  }
  void finish_mean() {
    mean_.resize(sum_.size());
    for (size_t d = 0; d < sum_.size(); ++d) mean_[d] = sum_[d] / static_cast<double>(count_);
  }
  void add_deviation(const float* v) {
    for (size_t d = 0; d < sq_.size(); ++d) sq_[d] += (v[d] - mean_[d]) * (v[d] - mean_[d]);
  }
  size_t count() const { return count_; }
  std::vector<float> mean() const { return {mean_.begin(), mean_.end()}; }
  std::vector<float> std(double floor) const {
    std::vector<float> s(sq_.size());
    for (size_t d = 0; d < sq_.size(); ++d)
      s[d] = static_cast<float>(std::max(std::sqrt(sq_[d] / static_cast<double>(count_)), floor));
    return s;
  }

 private:
  std::vector<double> sum_, sq_, mean_;
  size_t count_ = 0;
};

}  // namespace

NormStats compute_norm_stats(const MotionSet& m, const NormOptions& opt) {
  const std::vector<size_t> clips = m.indices_of_split(opt.split);
  if (clips.empty())
    fail("cannot compute normalisation statistics: the motion set has no clips in split '{}'", opt.split);
  if (!(opt.std_floor > 0)) fail("normalisation std_floor must be > 0 (got {})", opt.std_floor);
  const int J = m.num_joints();

  MomentAccumulator joints(3);
  for (size_t i : clips)
    for (int t = 0; t < m.lengths[i]; ++t)
      for (int j = 0; j < J; ++j) joints.add_mean(m.at(i, t, j));
  joints.finish_mean();
  for (size_t i : clips)
    for (int t = 0; t < m.lengths[i]; ++t)
      for (int j = 0; j < J; ++j) joints.add_deviation(m.at(i, t, j));

  const int F = feature_dim(opt.feature_layout, m.skeleton);
  std::vector<std::vector<float>> features;
  for (size_t i : clips)
    if (m.lengths[i] >= 2) features.push_back(compute_features(opt.feature_layout, m.clip(i), m.lengths[i], m.skeleton,
                                                               opt.features));
  MomentAccumulator feats(F);
  for (auto& f : features)
    for (size_t k = 0; k < f.size(); k += F) feats.add_mean(f.data() + k);
  if (feats.count() == 0)
    fail("cannot compute feature statistics: no clip in split '{}' has 2 or more frames", opt.split);
  feats.finish_mean();
  for (auto& f : features)
    for (size_t k = 0; k < f.size(); k += F) feats.add_deviation(f.data() + k);

  NormStats s;
  s.joint_mean = joints.mean();
  s.joint_std = joints.std(opt.std_floor);
  s.feature_mean = feats.mean();
  s.feature_std = feats.std(opt.std_floor);
  s.feature_layout = opt.feature_layout;
  return s;
}

AxisAffine AxisAffine::inverse() const {
  AxisAffine inv;
  for (int a = 0; a < 3; ++a) {
    inv.scale[a] = 1.0 / scale[a];
    inv.offset[a] = -offset[a] / scale[a];
  }
  return inv;
}

void AxisAffine::apply(float* xyz, size_t points) const {
  for (size_t p = 0; p < points; ++p)
    for (int a = 0; a < 3; ++a) xyz[p * 3 + a] = static_cast<float>(scale[a] * xyz[p * 3 + a] + offset[a]);
}

AxisAffine joint_normalizer(const NormStats& s) {
  require_joint_stats(s);
  AxisAffine n;
  for (int a = 0; a < 3; ++a) {
    n.scale[a] = 1.0 / s.joint_std[a];
    n.offset[a] = -static_cast<double>(s.joint_mean[a]) / s.joint_std[a];
  }
  return n;
}

AxisAffine joint_denormalizer(const NormStats& s) {
  require_joint_stats(s);
  AxisAffine d;
  for (int a = 0; a < 3; ++a) {
    d.scale[a] = s.joint_std[a];
    d.offset[a] = s.joint_mean[a];
  }
  return d;
}

void normalize_joints(const NormStats& s, float* xyz, size_t points) { joint_normalizer(s).apply(xyz, points); }
void denormalize_joints(const NormStats& s, float* xyz, size_t points) { joint_denormalizer(s).apply(xyz, points); }

void normalize_features(const NormStats& s, float* values, size_t frames, int dim) {
  require_feature_stats(s, dim);
  for (size_t t = 0; t < frames; ++t)
    for (int d = 0; d < dim; ++d) {
      float& v = values[t * dim + d];
      v = static_cast<float>((double(v) - s.feature_mean[d]) / s.feature_std[d]);
    }
}

void denormalize_features(const NormStats& s, float* values, size_t frames, int dim) {
  require_feature_stats(s, dim);
  for (size_t t = 0; t < frames; ++t)
    for (int d = 0; d < dim; ++d) {
      float& v = values[t * dim + d];
      v = static_cast<float>(double(v) * s.feature_std[d] + s.feature_mean[d]);
    }
}

}  // namespace mc
