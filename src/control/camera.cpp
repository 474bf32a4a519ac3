// Orthographic camera (reference-facts §3): elementary rotations, projection and
// the protocol's random camera draw.
#include "control/camera.h"

#include <cmath>

namespace mc {

Eigen::Matrix3d rotation_x(double angle) {
  const double c = std::cos(angle), s = std::sin(angle);
  Eigen::Matrix3d r;
  r << 1, 0, 0,
       0, c, -s,
       0, s, c;
  return r;
}

Eigen::Matrix3d rotation_y(double angle) {
  const double c = std::cos(angle), s = std::sin(angle);
  Eigen::Matrix3d r;
  r << c, 0, s,
       0, 1, 0,
       -s, 0, c;
  return r;
}

Eigen::Matrix3d rotation_z(double angle) {
  const double c = std::cos(angle), s = std::sin(angle);
  Eigen::Matrix3d r;
  r << c, -s, 0,
       s, c, 0,
       0, 0, 1;
  return r;
}

Eigen::Matrix3d OrthoCamera::rotation() const {
  return rotation_z(roll) * rotation_x(pitch) * rotation_y(yaw);
}

Eigen::Matrix<double, 2, 3> OrthoCamera::matrix() const {
  return scale * rotation().topRows<2>();  // P keeps the first two rows
}

Eigen::Vector2d OrthoCamera::project(const Eigen::Vector3d& x) const { return matrix() * x; }

namespace {
// Uniform double in [0, 1) from the top 53 bits of one engine output.
double unit_uniform(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }
double uniform(std::mt19937_64& rng, double lo, double hi) { return lo + (hi - lo) * unit_uniform(rng); }
constexpr double kDeg = M_PI / 180.0;
}  // namespace

OrthoCamera sample_protocol_camera(std::mt19937_64& rng) {
  OrthoCamera cam;
  cam.pitch = uniform(rng, 0.0, 30.0) * kDeg;
  cam.yaw = uniform(rng, -45.0, 45.0) * kDeg;
  cam.roll = 0.0;
  cam.scale = uniform(rng, 0.8, 1.2);
  return cam;
}

}  // namespace mc
