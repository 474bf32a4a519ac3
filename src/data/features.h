// Joint-derived motion features (HumanML3D-style, positions only, no rotations):
// facing frame, root velocities, root-relative positions, joint velocities, foot
// contacts, and the "mc67" layout the evaluator reads. docs/formats.md documents them.
#pragma once
#include <cmath>
#include <string>
#include <vector>

#include "data/motion_set.h"
#include "data/skeleton.h"

namespace mc {

// A clip is `frames` frames of J joints, row-major [frames, J, 3] floats in world
// metres, Y up (J = skeleton.num_joints()).

struct FeatureOptions {
  // Std (frames) of the Gaussian that smooths the forward direction over time
  // before the facing angle is taken; HumanML3D uses 20. 0 = no smoothing.
  double facing_smooth_sigma = 20.0;
  // A foot joint is in contact when its squared displacement to the next frame
  // is below this (m^2 per frame); HumanML3D uses 0.002 at 20 fps.
  double contact_threshold = 0.002;
};

// Heading angle per frame [frames], radians: theta = atan2(f_x, f_z) of the
// (smoothed) forward direction f, so 0 faces +Z and +pi/2 faces +X. Forward is
// normalise(cross(up, across)) with across = (r_hip - l_hip) + (r_shoulder - l_shoulder)
// from the skeleton's "face" role; a rest pose with its left side at +X faces +Z.
std::vector<double> facing_angles(const float* joints, int frames, const Skeleton& sk,
                                  const FeatureOptions& opt = {});

// Rotates the world vector (x, z) into the frame of a character with heading theta
// (its forward becomes +Z): R_y(-theta).
inline void to_facing_frame(double theta, double x, double z, double& out_x, double& out_z) {
  const double c = std::cos(theta), s = std::sin(theta);
  out_x = c * x - s * z;
  out_z = s * x + c * z;
}

// Root-relative, facing-normalised positions of joints 1..J-1 [frames, J-1, 3]: joint
// minus root xz (y kept absolute), rotated so the character faces +Z.
std::vector<float> local_positions(const float* joints, int frames, const Skeleton& sk,
                                   const FeatureOptions& opt = {});

// Per-frame displacement of every joint to the next frame, in the facing frame of
// the current frame [frames-1, J, 3] (HumanML3D's local velocities, metres/frame).
std::vector<float> joint_velocities(const float* joints, int frames, const Skeleton& sk,
                                    const FeatureOptions& opt = {});

// Foot contacts [frames-1, C]: 1 where |p[t+1] - p[t]|^2 < contact_threshold, for the
// joints of the "left_foot" role then the "right_foot" role (C = 4 for humanml3d22:
// l_ankle, l_foot, r_ankle, r_foot).
std::vector<float> foot_contacts(const float* joints, int frames, const Skeleton& sk,
                                 const FeatureOptions& opt = {});

// The "mc67" layout [frames-1, 4 + 3(J-1)] (67 for 22 joints), HumanML3D's first 67
// dims: [0] root angular velocity about y (half the per-frame heading change, sign
// as HumanML3D: theta[t] - theta[t+1] over 2), [1:3] root xz displacement t -> t+1 in
// the facing frame of t+1, [3] root height at t, [4:] local_positions at t.
std::vector<float> mc67_features(const float* joints, int frames, const Skeleton& sk,
                                 const FeatureOptions& opt = {});

// Inverse of mc67_features (HumanML3D's recover_from_ric): integrates the root and
// un-rotates the local positions. Returns [feature_frames, J, 3] world joints whose
// frame 0 has its root at x = z = 0 facing +Z; equals the input clip's first
// frames-1 frames up to that rotation about y and xz translation.
std::vector<float> recover_joints_from_mc67(const float* features, int feature_frames, int num_joints);

// The translation-invariant per-frame layout the tokenizer reads ("inv67", the same
// content as mc67 but one row per frame, T rows for T frames, by backward differences):
// [0] heading change theta[t] - theta[t-1] (radians, wrapped to (-pi, pi]), [1:3] root
// xz displacement t-1 -> t in the facing frame of t, [3] root height at t, [4:] the
// local_positions at t. Frame -1 is a virtual canonical frame (root at the origin,
// heading 0), so row 0 holds theta[0] and root xz at frame 0 (both ~0 for a canonical
// clip) and recover_joints_from_invariant returns the clip exactly, in its own world
// frame. With `extras` ("inv67+vel+contact") each row also holds the joint
// displacements t-1 -> t in the facing frame of t (3J; 0 at t = 0) and the foot
// contacts of the step t-1 -> t (row 0 copies row 1's): auxiliary targets, unused by
// the recovery. [frames, 4 + 3(J-1) (+ 3J + C)].
std::vector<float> invariant_features(const float* joints, int frames, const Skeleton& sk, bool extras,
                                      const FeatureOptions& opt = {});
// Inverse of invariant_features (reads the first 4 + 3(J-1) of `dim` columns):
// heading and root integrated from frame -1 = (origin, heading 0). [frames, J, 3].
std::vector<float> recover_joints_from_invariant(const float* features, int frames, int num_joints, int dim);

// Named layouts: "mc67" and "mc67+vel+contact" (mc67, joint_velocities, foot_contacts),
// "inv67" and "inv67+vel+contact" (invariant_features).
std::vector<std::string> feature_layouts();
int feature_dim(const std::string& layout, const Skeleton& sk);  // UserError for an unknown layout
// Feature rows of a clip of `frames` frames: frames - 1 (mc67*) or frames (inv67*).
int feature_frames(const std::string& layout, int frames);
// [feature_frames, feature_dim] for one clip of `frames` >= 1 frames (mc67*: empty when frames == 1).
std::vector<float> compute_features(const std::string& layout, const float* joints, int frames, const Skeleton& sk,
                                    const FeatureOptions& opt = {});

// Features of every clip of a set, padded like MotionSet::joints.
struct FeatureSet {
  std::string layout;
  int dim = 0;
  int t_max = 0;               // feature_frames(layout, motion t_max) (mc67*: T - 1 rows for T frames)
  std::vector<int> lengths;    // [N] valid feature frames: feature_frames(layout, motion length)
  std::vector<float> values;   // [N, t_max, dim], zero past lengths[i]
  size_t size() const { return lengths.size(); }
  const float* clip(size_t i) const { return values.data() + i * static_cast<size_t>(t_max) * dim; }
};
FeatureSet compute_features(const MotionSet& m, const std::string& layout, const FeatureOptions& opt = {});

}  // namespace mc
