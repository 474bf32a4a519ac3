// Velocity and facing directions of a motion, and the angle between directions.
#include "control/directions.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace mc {

std::vector<std::pair<int, double>> tangent_stencil(int t, int frames) {
  if (frames < 2 || t < 0 || t >= frames)
    throw std::invalid_argument("tangent_stencil: frame outside a clip of at least 2 frames");
  if (t == 0) return {{1, 1.0}, {0, -1.0}};
  if (t == frames - 1) return {{frames - 1, 1.0}, {frames - 2, -1.0}};
  return {{t + 1, 0.5}, {t - 1, -0.5}};
}

Eigen::VectorXd joint_velocity(const float* motion, int frames, int num_joints, int joint, int t,
                               const std::vector<int>& axes) {
  Eigen::VectorXd v = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(axes.size()));
  for (auto [f, w] : tangent_stencil(t, frames))
    for (size_t a = 0; a < axes.size(); ++a)
      v[static_cast<Eigen::Index>(a)] += w * motion[(static_cast<size_t>(f) * num_joints + joint) * 3 + axes[a]];
  return v;
}

Eigen::Vector2d body_forward(const float* motion, int num_joints, int right, int left, int t) {
  const float* r = motion + (static_cast<size_t>(t) * num_joints + right) * 3;
  const float* l = motion + (static_cast<size_t>(t) * num_joints + left) * 3;
  const double ax = double(r[0]) - double(l[0]), az = double(r[2]) - double(l[2]);
  return {az, -ax};
}

double angle_degrees(const Eigen::VectorXd& a, const Eigen::VectorXd& b) {
  const double na = a.norm(), nb = b.norm();
  if (na < 1e-9 || nb < 1e-9) return 90.0;
  const double c = std::clamp(a.dot(b) / (na * nb), -1.0, 1.0);
  return std::acos(c) * 180.0 / 3.14159265358979323846;
}

Eigen::MatrixXd orthogonal_complement(const Eigen::VectorXd& u) {
  const Eigen::Index n = u.size();
  if (n < 1 || n > 3) throw std::invalid_argument("orthogonal_complement: 1 to 3 dimensions");
  Eigen::MatrixXd out(n, n - 1);
  if (n == 2) {
    out.col(0) << -u[1], u[0];
  } else if (n == 3) {
    // Cross with the axis u is least aligned with, then complete the right-handed frame.
    Eigen::Index k = 0;
    u.cwiseAbs().minCoeff(&k);
    Eigen::Vector3d e = Eigen::Vector3d::Zero();
    e[k] = 1.0;
    Eigen::Vector3d uu(u[0], u[1], u[2]);
    Eigen::Vector3d e1 = uu.cross(e).normalized();
    Eigen::Vector3d e2 = uu.cross(e1);
    out.col(0) = e1;
    out.col(1) = e2;
  }
  return out;
}

}  // namespace mc
