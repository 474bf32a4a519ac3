// Orthographic camera for the 2D lifting task (Sketch2Anim protocol): projects
// world joints to image-plane keypoints. Shared by the ProjFlow constraint compiler
// (2D observation rows) and the 2D/3D metrics in eval/. Eigen only, torch-free.
#pragma once
#include <Eigen/Dense>
#include <cstdint>
#include <random>

namespace mc {

// Elementary rotations, written out exactly as reference-facts §3 gives them
// (angles in radians, c = cos, s = sin):
//   R_x = [[1,0,0],[0,c,-s],[0,s,c]],  R_y = [[c,0,s],[0,1,0],[-s,0,c]].
// R_z is not in the reference; the standard right-handed form is used:
//   R_z = [[c,-s,0],[s,c,0],[0,0,1]].
Eigen::Matrix3d rotation_x(double angle);
Eigen::Matrix3d rotation_y(double angle);
Eigen::Matrix3d rotation_z(double angle);

// y = scale * P * R_cam * x with P = [[1,0,0],[0,1,0]] and
// R_cam = R_z(roll) R_x(pitch) R_y(yaw) (reference-facts §3; with roll = 0 this is
// exactly the reference's R_x(pitch) R_y(yaw)). Angles in radians.
struct OrthoCamera {
  double scale = 1.0;
  double pitch = 0.0;
  double yaw = 0.0;
  double roll = 0.0;

  Eigen::Matrix3d rotation() const;           // R_cam (orthonormal)
  Eigen::Matrix<double, 2, 3> matrix() const;  // scale * P * R_cam: the 2x3 observation block of one joint
  Eigen::Vector2d project(const Eigen::Vector3d& x) const;
};

// Draws a camera from the Sketch2Anim protocol (reference-facts §3): pitch U(0, 30 deg),
// yaw U(-45, 45 deg), roll 0, scale U(0.8, 1.2). Uses explicit 53-bit draws from the
// engine (no std distributions), so the cameras are identical on every platform.
OrthoCamera sample_protocol_camera(std::mt19937_64& rng);

}  // namespace mc
