// Orthographic camera (reference-facts §3): orthonormal rows, R_x(pitch) R_y(yaw)
// written out by hand, known projections and the protocol's random draw.
#include <catch2/catch.hpp>

#include <cmath>

#include "control/camera.h"

using namespace mc;

namespace {
constexpr double kDeg = M_PI / 180.0;
}

TEST_CASE("camera rotation is orthonormal and the s = 1 projection has orthonormal rows", "[eval][camera]") {
  for (double pitch : {-80.0, 0.0, 17.0, 30.0})
    for (double yaw : {-45.0, 0.0, 33.0, 170.0})
      for (double roll : {0.0, 12.0, -95.0}) {
        const OrthoCamera cam{1.0, pitch * kDeg, yaw * kDeg, roll * kDeg};
        const Eigen::Matrix3d r = cam.rotation();
        REQUIRE((r * r.transpose() - Eigen::Matrix3d::Identity()).norm() < 1e-12);
        REQUIRE(r.determinant() == Approx(1.0));
        const Eigen::Matrix<double, 2, 3> p = cam.matrix();
        REQUIRE((p * p.transpose() - Eigen::Matrix2d::Identity()).norm() < 1e-12);
        const OrthoCamera scaled{1.3, pitch * kDeg, yaw * kDeg, roll * kDeg};
        REQUIRE((scaled.matrix() * scaled.matrix().transpose() - 1.69 * Eigen::Matrix2d::Identity()).norm() < 1e-12);
      }
}

TEST_CASE("with roll = 0 the camera is R_x(pitch) R_y(yaw) multiplied out by hand", "[eval][camera]") {
  const double p = 23.0 * kDeg, y = -37.0 * kDeg;
  const double cp = std::cos(p), sp = std::sin(p), cy = std::cos(y), sy = std::sin(y);
  // R_x = [[1,0,0],[0,cp,-sp],[0,sp,cp]], R_y = [[cy,0,sy],[0,1,0],[-sy,0,cy]] (reference-facts §3)
  Eigen::Matrix3d expected;
  expected << cy, 0, sy,
              sp * sy, cp, -sp * cy,
              -cp * sy, sp, cp * cy;
  const OrthoCamera cam{1.0, p, y, 0.0};
  REQUIRE((cam.rotation() - expected).norm() < 1e-14);
  REQUIRE((rotation_x(p) - (Eigen::Matrix3d() << 1, 0, 0, 0, cp, -sp, 0, sp, cp).finished()).norm() == 0.0);
  REQUIRE((rotation_y(y) - (Eigen::Matrix3d() << cy, 0, sy, 0, 1, 0, -sy, 0, cy).finished()).norm() == 0.0);
  const OrthoCamera scaled{0.9, p, y, 0.0};
  const Eigen::Vector3d x(0.3, 1.1, -0.7);
  REQUIRE((scaled.project(x) - 0.9 * expected.topRows<2>() * x).norm() < 1e-14);
}

TEST_CASE("camera projections of axis points by hand", "[eval][camera]") {
  // yaw 90: R_y maps x -> -z; pitch 30: -z -> (0, sin 30, -cos 30); keep x, y; scale 2.
  const OrthoCamera cam{2.0, 30.0 * kDeg, 90.0 * kDeg, 0.0};
  const Eigen::Vector2d a = cam.project(Eigen::Vector3d(1, 0, 0));
  REQUIRE(a.x() == Approx(0.0).margin(1e-12));
  REQUIRE(a.y() == Approx(1.0));
  // roll 90 alone turns image x into image y.
  const OrthoCamera rolled{1.0, 0.0, 0.0, 90.0 * kDeg};
  const Eigen::Vector2d b = rolled.project(Eigen::Vector3d(1, 0, 0));
  REQUIRE(b.x() == Approx(0.0).margin(1e-12));
  REQUIRE(b.y() == Approx(1.0));
  // The identity camera drops depth (z).
  REQUIRE((OrthoCamera{}.project(Eigen::Vector3d(1, 2, 3)) - Eigen::Vector2d(1, 2)).norm() == 0.0);
}

TEST_CASE("protocol cameras stay in the Sketch2Anim ranges and are reproducible", "[eval][camera]") {
  std::mt19937_64 a(5), b(5);
  double min_pitch = 1e9, max_pitch = -1e9, min_yaw = 1e9, max_yaw = -1e9;
  for (int i = 0; i < 2000; ++i) {
    const OrthoCamera c = sample_protocol_camera(a);
    const OrthoCamera d = sample_protocol_camera(b);
    REQUIRE(c.pitch == d.pitch);
    REQUIRE(c.scale == d.scale);
    REQUIRE(c.roll == 0.0);
    REQUIRE(c.scale >= 0.8);
    REQUIRE(c.scale < 1.2);
    min_pitch = std::min(min_pitch, c.pitch), max_pitch = std::max(max_pitch, c.pitch);
    min_yaw = std::min(min_yaw, c.yaw), max_yaw = std::max(max_yaw, c.yaw);
  }
  REQUIRE(min_pitch >= 0.0);
  REQUIRE(max_pitch < 30.0 * kDeg);
  REQUIRE(max_pitch > 29.0 * kDeg);  // the range is actually covered
  REQUIRE(min_yaw >= -45.0 * kDeg);
  REQUIRE(min_yaw < -44.0 * kDeg);
  REQUIRE(max_yaw < 45.0 * kDeg);
  REQUIRE(max_yaw > 44.0 * kDeg);
}
