// Feedback features (control/anchor_feedback.*, issue 15, ours): residual and bearing of
// the next / previous anchor against an estimate, in the estimate's facing frame.
#include <catch2/catch.hpp>

#include <cmath>
#include <random>

#include "control/anchor_feedback.h"
#include "core/error.h"
#include "data/skeleton.h"

using namespace mc;

namespace {

constexpr int J = 22;

// A body at root (x, 0.9, z) facing heading theta (0 = +Z, pi/2 = +X): the hips and
// shoulders across its left-right axis, the other joints spread below the root.
void put_pose(std::vector<float>& m, int t, double x, double z, double theta) {
  const auto& sk = humanml3d_skeleton();
  const auto& face = sk.role("face");  // r_hip, l_hip, r_shoulder, l_shoulder
  // The left side of a body facing +Z is at +X (data/features.h); rotate by theta.
  const double lx = std::cos(theta), lz = -std::sin(theta);
  for (int j = 0; j < J; ++j) {
    float* p = m.data() + (static_cast<size_t>(t) * J + j) * 3;
    p[0] = static_cast<float>(x);
    p[1] = static_cast<float>(0.9 - 0.03 * j);
    p[2] = static_cast<float>(z);
  }
  auto side = [&](int j, double s, double y) {
    float* p = m.data() + (static_cast<size_t>(t) * J + j) * 3;
    p[0] = static_cast<float>(x + s * lx);
    p[1] = static_cast<float>(y);
    p[2] = static_cast<float>(z + s * lz);
  };
  side(face[0], -0.1, 0.9);
  side(face[1], 0.1, 0.9);
  side(face[2], -0.18, 1.4);
  side(face[3], 0.18, 1.4);
}

Anchor root_anchor(int f, double x, double y, double z, bool planar = false) {
  Anchor a;
  a.frame = f;
  a.joint = 0;
  a.axes = {true, !planar, true};
  a.value = Eigen::Vector3d(x, planar ? 0.0 : y, z);
  return a;
}

}  // namespace

TEST_CASE("feedback features: residual, bearing, times and flags on a straight walk", "[anchor_feedback]") {
  const int T = 40;
  const double v = 0.05;  // m per frame along +Z, facing +Z
  std::vector<float> est(static_cast<size_t>(T) * J * 3);
  for (int t = 0; t < T; ++t) put_pose(est, t, 0.0, v * t, 0.0);
  AnchorSet set;
  set.family = AnchorFamily::root_3d;
  set.frames = T;
  // Anchor at frame 10 exactly on the estimate; at frame 30 half a metre to the world's +X.
  set.anchors = {root_anchor(10, 0.0, 0.9, v * 10), root_anchor(30, 0.5, 0.9, v * 30)};
  auto m = anchor_feedback_features(set, est.data(), T, humanml3d_skeleton());
  REQUIRE(m.rows() == T);
  REQUIRE(m.cols() == kFeedbackWidth);
  // Frame 4: next anchor is frame 10, residual 0, bearing 6 frames ahead along +Z.
  CHECK(m(4, 0) == Approx(0.0).margin(1e-6));
  CHECK(m(4, 2) == Approx(0.0).margin(1e-6));
  CHECK(m(4, 3) == Approx(0.0).margin(1e-6));
  CHECK(m(4, 5) == Approx(v * 6).margin(1e-5));
  CHECK(m(4, 6) == Approx(6 / kPathFrameRate));
  CHECK(m(4, 7) == 1.0f);
  CHECK(m(4, 15) == 0.0f);  // no anchor before it
  CHECK(m(4, 16) == 0.0f);
  // Frame 10 is an anchor frame: next = previous = itself.
  CHECK(m(10, 16) == 1.0f);
  CHECK(m(10, 6) == 0.0f);
  CHECK(m(10, 14) == 0.0f);
  CHECK(m(10, 15) == 1.0f);
  // Frame 20: the next anchor misses by +0.5 m world x; facing +Z the lateral axis is x.
  CHECK(m(20, 0) == Approx(0.5).margin(1e-5));
  CHECK(m(20, 1) == Approx(0.0).margin(1e-5));
  CHECK(m(20, 2) == Approx(0.0).margin(1e-5));
  CHECK(m(20, 3) == Approx(0.5).margin(1e-5));
  CHECK(m(20, 5) == Approx(v * 10).margin(1e-5));
  CHECK(m(20, 14) == Approx(10 / kPathFrameRate));  // since frame 10
  // After the last anchor only the previous one is there.
  CHECK(m(35, 7) == 0.0f);
  CHECK(m(35, 0) == 0.0f);
  CHECK(m(35, 15) == 1.0f);
  CHECK(m(35, 8) == Approx(0.5).margin(1e-5));

  // The same walk facing +X (heading pi/2): the world's +X miss is now straight ahead.
  for (int t = 0; t < T; ++t) put_pose(est, t, 0.0, v * t, M_PI / 2);
  m = anchor_feedback_features(set, est.data(), T, humanml3d_skeleton());
  CHECK(m(20, 0) == Approx(0.0).margin(1e-5));
  CHECK(m(20, 2) == Approx(0.5).margin(1e-5));
}

TEST_CASE("feedback features: planar anchors leave the vertical residual at 0", "[anchor_feedback]") {
  const int T = 20;
  std::vector<float> est(static_cast<size_t>(T) * J * 3);
  for (int t = 0; t < T; ++t) put_pose(est, t, 0.02 * t, 0.0, 0.3);
  AnchorSet set;
  set.family = AnchorFamily::planar_root;
  set.frames = T;
  set.anchors = {root_anchor(12, 1.0, 0.0, 1.0, true)};
  auto m = anchor_feedback_features(set, est.data(), T, humanml3d_skeleton());
  CHECK(m(5, 1) == 0.0f);  // no y residual on a planar anchor
  CHECK(m(5, 4) == Approx(0.0).margin(1e-6));  // the bearing's y is the estimate's own climb (none here)
  CHECK(std::hypot(m(5, 0), m(5, 2)) == Approx(std::hypot(1.0 - 0.24, 1.0)).epsilon(1e-4));
}

TEST_CASE("feedback features: unchanged when anchors and estimate turn about y and move together",
          "[anchor_feedback]") {
  const int T = 48;
  std::mt19937_64 rng(7);
  std::normal_distribution<double> n(0.0, 1.0);
  std::vector<float> est(static_cast<size_t>(T) * J * 3), gt(est.size());
  double x = 0, z = 0, th = 0.4, gx = 0.3, gz = -0.2, gth = 0.1;
  for (int t = 0; t < T; ++t) {
    th += 0.05 * n(rng);
    gth += 0.05 * n(rng);
    x += 0.04 * std::sin(th);
    z += 0.04 * std::cos(th);
    gx += 0.04 * std::sin(gth);
    gz += 0.04 * std::cos(gth);
    put_pose(est, t, x, z, th);
    put_pose(gt, t, gx, gz, gth);
  }
  for (auto fam : {AnchorFamily::root_3d, AnchorFamily::planar_root, AnchorFamily::body_point}) {
    std::mt19937_64 draw(11);
    auto set = draw_anchor_set(fam, 5, gt.data(), T, J, draw, {0, 10, 11, 15, 20, 21});
    auto a = anchor_feedback_features(set, est.data(), T, humanml3d_skeleton());
    // Turn everything by 1.1 rad about y and move it by (2, -3) in xz.
    const double c = std::cos(1.1), s = std::sin(1.1);
    auto move = [&](double& px, double& pz) {
      const double rx = c * px + s * pz, rz = -s * px + c * pz;
      px = rx + 2.0;
      pz = rz - 3.0;
    };
    std::vector<float> est2 = est;
    for (size_t i = 0; i < est2.size(); i += 3) {
      double px = est2[i], pz = est2[i + 2];
      move(px, pz);
      est2[i] = static_cast<float>(px);
      est2[i + 2] = static_cast<float>(pz);
    }
    AnchorSet set2 = set;
    for (auto& an : set2.anchors)
      if (an.axes[0]) move(an.value[0], an.value[2]);
    auto b = anchor_feedback_features(set2, est2.data(), T, humanml3d_skeleton());
    CHECK((a - b).cwiseAbs().maxCoeff() < 2e-4f);
    CHECK(a.cwiseAbs().maxCoeff() > 0.1f);  // not trivially zero
  }
}

TEST_CASE("feedback features: a short estimate or an unknown joint is a clear error", "[anchor_feedback]") {
  const int T = 10;
  std::vector<float> est(static_cast<size_t>(T) * J * 3);
  for (int t = 0; t < T; ++t) put_pose(est, t, 0, 0, 0);
  AnchorSet set;
  set.frames = T;
  set.anchors = {root_anchor(3, 0, 0.9, 0)};
  CHECK_THROWS_AS(anchor_feedback_features(set, est.data(), T - 1, humanml3d_skeleton()), UserError);
  set.anchors[0].joint = 40;
  CHECK_THROWS_AS(anchor_feedback_features(set, est.data(), T, humanml3d_skeleton()), UserError);
  AnchorSet empty;
  empty.frames = T;
  CHECK(anchor_feedback_features(empty, est.data(), T, humanml3d_skeleton()).cwiseAbs().maxCoeff() == 0.0f);
}
