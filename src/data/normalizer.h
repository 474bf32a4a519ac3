// Normalisation statistics from the train split and the maps in and out of the
// normalised space: per-axis z-score for joints (ACMDM), per-dimension for features.
#pragma once
#include <array>
#include <cstddef>
#include <string>

#include "data/features.h"
#include "data/motion_set.h"

namespace mc {

struct NormOptions {
  std::string split = "train";          // statistics come from these clips only
  std::string feature_layout = "mc67";  // layout of feature_mean / feature_std
  FeatureOptions features;
  // Standard deviations are floored here so a dimension that is constant over the
  // split (a contact channel never active, a zero root velocity in a tiny fixture)
  // maps to 0 instead of dividing by zero. 1e-4 (metres, radians or 0/1 per frame)
  // lies well below the spread of per-frame displacements of moving clips
  // (millimetres per frame and up), so it only ever changes constant dimensions.
  double std_floor = 1e-4;
};

// joint_mean/joint_std (3,): over every valid frame and every joint of the split,
// per axis; feature_mean/feature_std (F,): over every valid feature frame. Std is
// the population one (ddof 0, as numpy's default), floored at opt.std_floor.
// UserError when the split has no clips (or no clip of 2+ frames for features).
NormStats compute_norm_stats(const MotionSet& m, const NormOptions& opt = {});

// An affine map applied per xyz axis: out[a] = scale[a] * in[a] + offset[a].
// The constraint compiler needs it explicitly to move linear observations between
// world and normalised units.
struct AxisAffine {
  std::array<double, 3> scale{1, 1, 1}, offset{0, 0, 0};
  AxisAffine inverse() const;
  void apply(float* xyz, size_t points) const;  // in place on [points, 3]
};

AxisAffine joint_normalizer(const NormStats& s);    // world metres -> normalised: scale 1/std, offset -mean/std
AxisAffine joint_denormalizer(const NormStats& s);  // normalised -> world metres: scale std, offset mean

// In place on [points, 3] buffers (any [..., J, 3] layout works: points = product of leading dims).
void normalize_joints(const NormStats& s, float* xyz, size_t points);
void denormalize_joints(const NormStats& s, float* xyz, size_t points);
// In place on [frames, dim] buffers; UserError when dim differs from the stats'.
void normalize_features(const NormStats& s, float* values, size_t frames, int dim);
void denormalize_features(const NormStats& s, float* values, size_t frames, int dim);

}  // namespace mc
