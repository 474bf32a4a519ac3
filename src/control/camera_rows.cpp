// Orthographic camera rows for camera_2d constraints (eq. (19)).
#include "control/camera_rows.h"

#include <cmath>

namespace mc {

Eigen::Matrix3d camera_rotation(double pitch, double yaw, double roll) {
  const double cp = std::cos(pitch), sp = std::sin(pitch);
  const double cy = std::cos(yaw), sy = std::sin(yaw);
  const double cr = std::cos(roll), sr = std::sin(roll);
  Eigen::Matrix3d ry, rx, rz;
  ry << cy, 0, sy, 0, 1, 0, -sy, 0, cy;
  rx << 1, 0, 0, 0, cp, -sp, 0, sp, cp;
  rz << cr, -sr, 0, sr, cr, 0, 0, 0, 1;
  return rz * rx * ry;
}

Eigen::Matrix<double, 2, 3> camera_rows(double scale, double pitch, double yaw, double roll) {
  return scale * camera_rotation(pitch, yaw, roll).topRows<2>();
}

}  // namespace mc
