// Read-only views of joint sequences and the position error between two sets of
// them (reconstruction MPJPE). Below models and eval: a tokenizer's validation and
// the evaluation metrics (eval/metrics.h) measure with the same definitions.
#pragma once
#include <Eigen/Dense>
#include <string>
#include <vector>

#include "data/motion_set.h"

namespace mc {

// Read-only view of one motion stored frame-major as [frames, joints, 3] floats
// (world metres, Y up), exactly like one clip of a MotionSet. Frames in
// [length, frames) are padding. Does not own its data.
struct JointsView {
  const float* data = nullptr;
  int frames = 0;  // stored (possibly padded) frames
  int joints = 0;
  int length = 0;  // valid frames, <= frames

  Eigen::Vector3d at(int t, int j) const {
    const float* p = data + (static_cast<size_t>(t) * joints + j) * 3;
    return {p[0], p[1], p[2]};
  }
};

// View over `data` (size must be frames * joints * 3); length < 0 means `frames`.
// UserError naming `what` on a size mismatch or an invalid length.
JointsView joints_view(const std::vector<float>& data, int frames, int joints, int length = -1,
                       const std::string& what = "motion");
// View of clip i of a motion set (frames = t_max, length = lengths[i]).
JointsView joints_view(const MotionSet& set, size_t i);

// Tokenizer reconstruction MPJPE: mean ||r_tj - g_tj|| (metres) over all joints of
// all valid frames of all clips (frame-weighted, as MoMask's evaluation pools poses).
// Valid frames = the ground truth's length; the reconstruction must have the same
// length. root_aligned subtracts each frame's root position from both first
// (MoMask's variant).
double reconstruction_mpjpe(const std::vector<JointsView>& reconstruction,
                            const std::vector<JointsView>& ground_truth, bool root_aligned = false,
                            int root = 0);

}  // namespace mc
