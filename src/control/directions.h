// Direction cues (issue 20, beyond both papers): the velocity direction of a joint
// (tangent items) and the facing direction of the body (facing items), shared by
// compile(), which turns them into linear rows, and the angle-error metric, which
// reads them off a motion. One definition, so a motion that meets the rows scores
// zero angle error.
#pragma once
#include <Eigen/Dense>
#include <utility>
#include <vector>

namespace mc {

// The velocity stencil of a tangent at frame t of a clip of `frames` frames (>= 2):
// the central difference (x[t+1] - x[t-1]) / 2 inside the clip, the one-sided
// difference at its ends. (frame, weight) pairs; velocity = sum weight * x[frame].
std::vector<std::pair<int, double>> tangent_stencil(int t, int frames);

// A joint's velocity on `axes` at frame t of a motion [frames, J, 3] (world,
// row-major), metres per frame; not normalised.
Eigen::VectorXd joint_velocity(const float* motion, int frames, int num_joints, int joint, int t,
                               const std::vector<int>& axes);

// The body's forward direction (x, z) at frame t from two joints on its right and
// left (the hips): forward = up x (x_right - x_left) = (a_z, -a_x) with a = x_right -
// x_left, HumanML3D's convention (motion_process.py) with the hips alone. Linear in
// the motion, which is what makes facing rows linear; not normalised (its length
// is the hips' horizontal distance).
Eigen::Vector2d body_forward(const float* motion, int num_joints, int right, int left, int t);

// Angle between a and b in degrees, in [0, 180]. A (near-)zero a (below 1e-9) has no
// direction and scores 90: neither along nor against the target.
double angle_degrees(const Eigen::VectorXd& a, const Eigen::VectorXd& b);

// An orthonormal basis of the complement of the unit vector u in R^n (n = 1..3),
// one column per vector: the directions a tangent must not move along.
Eigen::MatrixXd orthogonal_complement(const Eigen::VectorXd& u);

}  // namespace mc
