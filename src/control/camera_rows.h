// The 2x3 rows of one orthographic 2D observation, y = s * P * R_cam * x (eq. (19)),
// kept local to the constraint compiler until the shared camera type lands.
#pragma once
#include <Eigen/Dense>

namespace mc {

// s * P * R_cam with P = [[1,0,0],[0,1,0]] and R_cam = R_z(roll) * R_x(pitch) * R_y(yaw)
// (reference-facts §3; the protocol keeps roll = 0). Angles in radians.
//   R_y(a) = [[c,0,s],[0,1,0],[-s,0,c]],  R_x(a) = [[1,0,0],[0,c,-s],[0,s,c]],
//   R_z(a) = [[c,-s,0],[s,c,0],[0,0,1]].
Eigen::Matrix<double, 2, 3> camera_rows(double scale, double pitch, double yaw, double roll);

// The full camera rotation R_cam (same convention), for callers that need the depth row.
Eigen::Matrix3d camera_rotation(double pitch, double yaw, double roll);

}  // namespace mc
