// Anchors (AnchorRoute §3.1): the interpolation prior through every anchor, spec <->
// anchor round trips for the three families, clear errors for what anchors cannot
// express, the condition-feature layout, the benchmark draws and the support assignment,
// and the path-frame features (invariance under moving the anchor set, layout, zeros).
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <random>

#include "control/anchors.h"
#include "control/linear_observation.h"
#include "control_test_util.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

const Skeleton& skel() { return humanml3d_skeleton(); }

double cubic(double x, int c) { return 0.3 + (0.1 + c) * x - 0.02 * x * x + 0.001 * (c + 1) * x * x * x; }

}  // namespace

TEST_CASE("interpolation prior passes through every anchor (cubic and linear fallback)", "[anchors]") {
  std::mt19937_64 rng(3);
  for (int n : {1, 2, 3, 4, 5, 9}) {
    auto times = random_subset(rng, 60, n);
    Eigen::MatrixXd V = Eigen::MatrixXd::Random(n, 3);
    Eigen::MatrixXd P = interpolate_anchor_values(times, V);
    REQUIRE(P.rows() == times.back() - times.front() + 1);
    for (int i = 0; i < n; ++i) CHECK((P.row(times[i] - times.front()) - V.row(i)).norm() < 1e-12);
    CHECK(P.allFinite());
  }
  // Fewer than 4 points: piecewise linear between anchors.
  Eigen::MatrixXd V(3, 1);
  V << 0.0, 1.0, -1.0;
  Eigen::MatrixXd P = interpolate_anchor_values({0, 4, 6}, V);
  CHECK(P(2, 0) == Approx(0.5));
  CHECK(P(5, 0) == Approx(0.0));
  // 4 or more points: the not-a-knot spline reproduces any cubic exactly, which the
  // linear interpolant does not.
  for (const std::vector<int>& times : {std::vector<int>{2, 9, 13, 30}, std::vector<int>{0, 5, 7, 20, 33, 40}}) {
    Eigen::MatrixXd Y(times.size(), 2);
    for (size_t i = 0; i < times.size(); ++i)
      for (int c = 0; c < 2; ++c) Y(i, c) = cubic(times[i], c);
    Eigen::MatrixXd Q = interpolate_anchor_values(times, Y);
    for (int t = times.front(); t <= times.back(); ++t)
      for (int c = 0; c < 2; ++c) CHECK(Q(t - times.front(), c) == Approx(cubic(t, c)).margin(1e-9));
  }
  CHECK_THROWS_AS(interpolate_anchor_values({3, 3}, Eigen::MatrixXd::Zero(2, 1)), UserError);
}

TEST_CASE("anchors <-> spec round trip for the three families", "[anchors]") {
  const int T = 40, J = skel().num_joints();
  std::mt19937_64 rng(11);
  auto motion = random_motion(rng, T, skel());
  for (auto fam : {AnchorFamily::root_3d, AnchorFamily::planar_root, AnchorFamily::body_point}) {
    for (int K : {2, 4, 8, 16, 32}) {
      AnchorSet set = draw_anchor_set(fam, K, motion.data(), T, J, rng);
      REQUIRE(set.size() == K);
      ConstraintSpec spec = anchors_to_spec(set);
      AnchorSet back = anchors_from_spec(spec, T, skel());  // family inferred
      CHECK(back == set);
      CHECK(anchors_from_spec(spec, T, skel(), nullptr, fam) == set);
      // The control error of the motion the anchors came from is zero.
      for (double e : anchor_errors(set, motion.data(), J)) CHECK(e < 1e-6);
    }
  }
  // Six-point protocol: six joints at the same ~30% frames, body_point.
  AnchorSet six = draw_sparse_keyjoint_set(motion.data(), T, J, rng);
  CHECK(six.family == AnchorFamily::body_point);
  CHECK(six.times().size() == 12u);  // round(0.3 * 40)
  CHECK(six.joints() == std::vector<int>{0, 10, 11, 15, 20, 21});
  CHECK(six.size() == 72);
  CHECK(anchors_from_spec(anchors_to_spec(six), T, skel()) == six);
  // Several item types merge into one set: trajectory of the pelvis + keyframe of a wrist.
  auto spec = parse_constraint_spec_yaml(R"(
- {type: trajectory, joints: [pelvis], frames: {start: 0, stop: 40, step: 10}, from_source: true}
- {type: keyframe, joints: [l_wrist], frames: [5, 25], from_source: true}
)",
                                         "mixed.yaml");
  AnchorSet mixed = anchors_from_spec(spec, T, skel(), motion.data());
  CHECK(mixed.family == AnchorFamily::body_point);
  CHECK(mixed.size() == 6);
  CHECK(mixed.joints() == std::vector<int>{0, skel().joint_index("l_wrist")});
  for (double e : anchor_errors(mixed, motion.data(), J)) CHECK(e < 1e-6);
  // planar_root item -> planar family; xz only, uncontrolled y ignored by the error.
  auto planar = anchors_from_spec(
      parse_constraint_spec_yaml("- {type: planar_root, frames: [0, 7, 39], from_source: true}", "p.yaml"), T, skel(),
      motion.data());
  CHECK(planar.family == AnchorFamily::planar_root);
  auto shifted = motion;
  shifted[1] += 5.f;  // root y at frame 0
  CHECK(anchor_errors(planar, shifted.data(), J)[0] < 1e-6);
  shifted[0] += 0.3f;  // root x at frame 0
  CHECK(anchor_errors(planar, shifted.data(), J)[0] == Approx(0.3).margin(1e-6));
  CHECK(anchor_loss(planar, shifted.data(), J) == Approx(0.09).margin(1e-6));  // eq. (3)
}

TEST_CASE("spec items anchors cannot express give a clear error", "[anchors]") {
  const int T = 20;
  std::mt19937_64 rng(5);
  auto src = random_motion(rng, T, skel());
  auto from_yaml = [&](const std::string& y) {
    return anchors_from_spec(parse_constraint_spec_yaml(y, "bad.yaml"), T, skel(), src.data());
  };
  expect_user_error([&] { from_yaml("- {type: camera_2d, frames: [0], camera: {yaw_deg: 10}, from_source: true}"); },
                    {"bad.yaml", "item 0", "camera_2d", "cannot be expressed as anchors"});
  expect_user_error([&] { from_yaml("- {type: relative, joints: [0, 10], values: [0, 0, 0]}"); },
                    {"relative", "cannot be expressed as anchors"});
  expect_user_error([&] { from_yaml("- {type: loop}"); }, {"loop", "cannot be expressed"});
  expect_user_error([&] { from_yaml("- {type: upper_body_edit}"); }, {"upper_body_edit"});
  // A keyframe on y only: not a subspace of any family.
  expect_user_error([&] { from_yaml("- {type: keyframe, name: hop, joints: [10], frames: [3], axes: y, from_source: true}"); },
                    {"'hop'", "joint 10 at frame 3", "axes y"});
  // Soft rows: anchors are hard.
  expect_user_error([&] { from_yaml("- {type: keyframe, joints: [0], frames: [3], variance: 0.01, from_source: true}"); },
                    {"soft", "variance 0"});
  // Root xz mixed with another joint's xyz.
  expect_user_error([&] {
    from_yaml("- {type: planar_root, frames: [1], from_source: true}\n- {type: keyframe, joints: [15], frames: [4], from_source: true}");
  }, {"mix"});
  // A family that does not fit.
  expect_user_error([&] {
    anchors_from_spec(parse_constraint_spec_yaml("- {type: keyframe, joints: [15], frames: [4], from_source: true}", "h.yaml"),
                      T, skel(), src.data(), AnchorFamily::root_3d);
  }, {"h.yaml", "root_3d anchors control x, y, z of the root"});
  // Rows compiled from a camera item, handed over directly: not single-coordinate rows.
  auto cam = compile(parse_constraint_spec_yaml("- {type: camera_2d, frames: [0], joints: [0], camera: {yaw_deg: 30}, from_source: true}", "c.yaml"),
                     T, skel(), src.data());
  expect_user_error([&] { anchors_from_observation(cam); }, {"c.yaml", "combines", "camera, relative or loop"});
  CHECK_THROWS_AS(parse_anchor_family("root3d"), UserError);
  CHECK(parse_anchor_family("planar_root") == AnchorFamily::planar_root);
}

TEST_CASE("anchor-condition features follow the documented layout (eqs. (5)-(6))", "[anchors]") {
  const int T = 30;
  AnchorSet set;
  set.family = AnchorFamily::planar_root;
  set.frames = T;
  for (auto [t, x, z] : {std::tuple{4, 1.0, 2.0}, std::tuple{10, 2.0, 0.0}, std::tuple{20, 4.0, 1.0}}) {
    Anchor a;
    a.frame = t;
    a.axes = {true, false, true};
    a.value = {x, 0.0, z};
    set.anchors.push_back(a);
  }
  auto layout = anchor_feature_layout(AnchorFamily::planar_root);
  REQUIRE(layout.d_f == 2);
  REQUIRE(layout.width() == 3 * 2 + 2);  // 3 d_f + 2
  FeatureMatrix f = anchor_features(set, layout);
  REQUIRE(f.rows() == T);
  REQUIRE(f.cols() == 8);
  for (int t = 0; t < T; ++t) {
    const bool anchored = t == 4 || t == 10 || t == 20, prior = t >= 4 && t <= 20;
    CHECK(f(t, 7) == float(anchored));  // m^a
    CHECK(f(t, 6) == float(prior));     // m^p
    if (!anchored) CHECK((f(t, 0) == 0 && f(t, 1) == 0));
    if (!prior) CHECK(f.row(t).head(6).isZero());
  }
  CHECK(f(10, 0) == 2.f);
  CHECK(f(20, 1) == 1.f);
  CHECK(f(7, 2) == Approx(1.5));  // linear prior (3 anchors) halfway between 1 and 2
  CHECK(f(7, 4) == Approx(1.0 / 6));  // Delta p = slope (2 - 1) / 6
  CHECK(f(4, 4) == 0.f);              // first prior frame: no difference
  CHECK(f(15, 5) == Approx(0.1));     // z slope (1 - 0) / 10

  // body_point: one group per listed joint; anchors on other joints are an error.
  auto bl = anchor_feature_layout(AnchorFamily::body_point, {0, 10, 20});
  CHECK(bl.width() == 3 * 9 + 2 * 3);
  AnchorSet body;
  body.family = AnchorFamily::body_point;
  body.frames = T;
  Anchor a;
  a.frame = 5;
  a.joint = 10;
  a.value = {1, 2, 3};
  body.anchors.push_back(a);
  FeatureMatrix fb = anchor_features(body, bl);
  CHECK(fb(5, 3) == 1.f);
  CHECK(fb(5, 5) == 3.f);
  CHECK(fb(5, 27 + 1) == 1.f);      // m^p of group 1
  CHECK(fb(5, 27 + 3 + 1) == 1.f);  // m^a of group 1
  CHECK(fb.col(27 + 3).sum() == 0.f);
  body.anchors[0].joint = 15;
  expect_user_error([&] { anchor_features(body, bl); }, {"joint 15"});
}

TEST_CASE("support set and nearest-anchor assignment (eqs. (7)-(9))", "[anchors]") {
  auto n = nearest_anchor_assignment({3, 6, 20}, 25, 2);
  std::vector<int> expect(25, -1);
  for (int t = 1; t <= 4; ++t) expect[t] = 0;
  expect[5] = 1;  // 2 from anchor 0, 1 from anchor 1
  for (int t = 6; t <= 8; ++t) expect[t] = 1;
  for (int t = 18; t <= 22; ++t) expect[t] = 2;
  CHECK(n == expect);
  // Equidistant frames go to the earlier anchor.
  CHECK(nearest_anchor_assignment({2, 6}, 10, 2)[4] == 0);
  CHECK(nearest_anchor_assignment({2}, 5, 0) == std::vector<int>{-1, -1, 0, -1, -1});

  // Two body points at one frame keep their own supports; targets from the ground truth.
  const int T = 12, J = skel().num_joints();
  std::mt19937_64 rng(2);
  auto gt = random_motion(rng, T, skel());
  AnchorSet set;
  set.family = AnchorFamily::body_point;
  set.frames = T;
  for (int j : {0, 15}) {
    Anchor a;
    a.frame = 5;
    a.joint = j;
    set.anchors.push_back(a);
  }
  auto sup = support_targets(set, 2, gt.data(), J);
  CHECK(sup.size() == 10);
  for (const auto& a : sup.anchors) {
    CHECK(std::abs(a.frame - 5) <= 2);
    for (int c = 0; c < 3; ++c) CHECK(a.value[c] == gt[(a.frame * J + a.joint) * 3 + c]);
  }
  CHECK(anchor_loss(sup, gt.data(), J) == 0.0);  // eq. (10) vanishes on the ground truth
}

TEST_CASE("anchor draws are sorted, distinct and deterministic per seed", "[anchors]") {
  for (int K : {2, 4, 8, 16, 32}) {
    std::mt19937_64 a(42), b(42);
    auto fa = draw_anchor_frames(a, 60, K), fb = draw_anchor_frames(b, 60, K);
    CHECK(fa == fb);
    REQUIRE(fa.size() == size_t(K));
    for (int i = 1; i < K; ++i) CHECK(fa[i] > fa[i - 1]);
    CHECK(fa.front() >= 0);
    CHECK(fa.back() < 60);
  }
  std::mt19937_64 a(1), b(2);
  CHECK(draw_anchor_frames(a, 196, 8) != draw_anchor_frames(b, 196, 8));
  std::mt19937_64 r(0);
  CHECK(draw_anchor_frames(r, 5, 5) == std::vector<int>{0, 1, 2, 3, 4});
  CHECK_THROWS_AS(draw_anchor_frames(r, 5, 6), UserError);
}

// ------------------------------------------------------------------ path-frame features (issue 15)

namespace {

// A wandering motion [T, 22, 3]: the root turns and changes speed, joint j sits at a
// fixed body offset that turns with it, so every family's prior moves and curves.
std::vector<float> wandering_motion(int T, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double turn = 0.04 * u(rng), speed = 0.04 + 0.02 * u(rng), wobble = 0.3 * u(rng);
  std::vector<float> m(static_cast<size_t>(T) * 22 * 3);
  double x = 0, z = 0, psi = 0;
  for (int t = 0; t < T; ++t) {
    psi += turn + 0.02 * std::sin(0.1 * t + wobble);
    const double v = speed * (1.0 + 0.5 * std::sin(0.05 * t));
    x += v * std::sin(psi);
    z += v * std::cos(psi);
    for (int j = 0; j < 22; ++j) {
      const double ox = 0.02 * ((j * 7) % 11 - 5), oz = 0.015 * ((j * 5) % 9 - 4);
      float* p = m.data() + (static_cast<size_t>(t) * 22 + j) * 3;
      p[0] = static_cast<float>(x + std::cos(psi) * ox + std::sin(psi) * oz);
      p[1] = static_cast<float>(0.9 + 0.03 * j + 0.05 * std::sin(0.2 * t + j));
      p[2] = static_cast<float>(z - std::sin(psi) * ox + std::cos(psi) * oz);
    }
  }
  return m;
}

// The set rotated by `angle` about y and moved by (dx, dz).
AnchorSet moved(AnchorSet s, double angle, double dx, double dz) {
  const double c = std::cos(angle), sn = std::sin(angle);
  for (auto& a : s.anchors) {
    const double x = a.value[0], z = a.value[2];
    a.value[0] = a.axes[0] ? c * x + sn * z + dx : 0.0;
    a.value[2] = a.axes[2] ? -sn * x + c * z + dz : 0.0;
  }
  return s;
}

AnchorSet straight_root_set(int T, const std::vector<int>& frames, double vx, double vz, AnchorFamily family) {
  AnchorSet s;
  s.family = family;
  s.frames = T;
  for (int t : frames) {
    Anchor a;
    a.frame = t;
    a.axes = family == AnchorFamily::planar_root ? std::array<bool, 3>{true, false, true}
                                                 : std::array<bool, 3>{true, true, true};
    a.value = {1.0 + vx * t, a.axes[1] ? 0.95 : 0.0, -2.0 + vz * t};
    s.anchors.push_back(a);
  }
  return s;
}

}  // namespace

TEST_CASE("path-frame features are invariant to rotating the anchor set about y and moving it in xz",
          "[anchors][path_features]") {
  const std::vector<int> body = {0, 10, 11, 15, 20, 21};
  std::mt19937_64 draw(17);
  std::uniform_real_distribution<double> angle(-M_PI, M_PI), offset(-5.0, 5.0);
  for (uint64_t clip = 0; clip < 4; ++clip) {
    const int T = 120;
    auto motion = wandering_motion(T, clip);
    std::mt19937_64 rng(100 + clip);
    std::vector<AnchorSet> sets;
    for (int K : {2, 5, 16}) {
      sets.push_back(draw_anchor_set(AnchorFamily::root_3d, K, motion.data(), T, 22, rng, body));
      sets.push_back(draw_anchor_set(AnchorFamily::planar_root, K, motion.data(), T, 22, rng, body));
      sets.push_back(draw_anchor_set(AnchorFamily::body_point, K, motion.data(), T, 22, rng, body));
    }
    // Six joints anchored at shared frames: the root-relative channels are live.
    sets.push_back(draw_sparse_keyjoint_set(motion.data(), T, 22, rng, 0.1, body));
    for (const auto& s : sets) {
      auto layout = anchor_feature_layout(s.family, body);
      FeatureMatrix f = anchor_path_features(s, layout);
      REQUIRE(f.cols() == path_feature_width(layout));
      CHECK(f.cwiseAbs().maxCoeff() > 0.1f);  // live channels, not an all-zero block
      for (int rep = 0; rep < 5; ++rep) {
        const double a = angle(draw), dx = offset(draw), dz = offset(draw);
        INFO(family_name(s.family) << " K=" << s.size() << " angle " << a << " offset " << dx << ", " << dz);
        auto m = moved(s, a, dx, dz);
        FeatureMatrix g = anchor_path_features(m, layout);
        CHECK((g - f).cwiseAbs().maxCoeff() < 2e-4f);
        // The world features do move (so the comparison above could fail).
        if (std::abs(a) > 0.1)
          CHECK((anchor_features(m, layout) - anchor_features(s, layout)).cwiseAbs().maxCoeff() > 1e-2f);
      }
    }
  }
}

TEST_CASE("path-frame features: layout, width and zero where the prior is undefined", "[anchors][path_features]") {
  // Widths: root_3d 4 + 2 * 4 + 2, planar_root 2 + 2 * 3 + 2, body point + 3 root-relative per group.
  CHECK(path_feature_width(anchor_feature_layout(AnchorFamily::root_3d)) == 14);
  CHECK(path_feature_width(anchor_feature_layout(AnchorFamily::planar_root)) == 10);
  CHECK(path_feature_width(anchor_feature_layout(AnchorFamily::body_point, {0, 10, 20})) == 3 * 17);

  // A straight root path at 0.05 m/frame heading +X (psi = pi / 2), anchors at 5, 15, 25.
  const int T = 40;
  auto s = straight_root_set(T, {5, 15, 25}, 0.05, 0.0, AnchorFamily::root_3d);
  FeatureMatrix f = anchor_path_features(s, anchor_feature_layout(AnchorFamily::root_3d));
  for (int t = 0; t < T; ++t) {
    INFO("frame " << t);
    if (t < 5 || t > 25) {
      CHECK(f.row(t).isZero());
      continue;
    }
    CHECK(f(t, 0) == Approx(0.05 * kPathFrameRate));  // speed, m/s
    CHECK(f(t, 1) == Approx(0.0).margin(1e-6));       // no turn
    CHECK(f(t, 2) == Approx(0.0).margin(1e-6));       // no vertical speed
    CHECK(f(t, 3) == Approx(0.95));                   // height
    const int next = t < 15 ? 15 : t < 25 ? 25 : -1, prev = t > 15 ? 15 : t > 5 ? 5 : -1;
    if (next >= 0) {
      CHECK(f(t, 4) == Approx(0.0).margin(1e-5));                    // lateral
      CHECK(f(t, 5) == Approx(0.0).margin(1e-6));                    // up
      CHECK(f(t, 6) == Approx(0.05 * (next - t)).margin(1e-5));      // ahead along the path
      CHECK(f(t, 7) == Approx((next - t) / kPathFrameRate));         // seconds to it
    } else {
      CHECK(f.row(t).segment(4, 4).isZero());
    }
    if (prev >= 0) {
      CHECK(f(t, 10) == Approx(-0.05 * (t - prev)).margin(1e-5));  // behind
      CHECK(f(t, 11) == Approx((t - prev) / kPathFrameRate));
    } else {
      CHECK(f.row(t).segment(8, 4).isZero());
    }
    CHECK(f(t, 12) == 1.f);                                       // m^p
    CHECK(f(t, 13) == float(t == 5 || t == 15 || t == 25));       // m^a
  }

  // A path that turns toward +X from +Z (heading increasing): positive turn rate, the
  // tokenizer's sign of a heading change. A quarter circle of radius 2 over 40 frames.
  AnchorSet arc;
  arc.family = AnchorFamily::planar_root;
  arc.frames = 60;
  for (int t = 0; t <= 40; t += 8) {
    const double phi = M_PI / 2 * t / 40.0;
    Anchor a;
    a.frame = t + 10;
    a.axes = {true, false, true};
    a.value = {2.0 - 2.0 * std::cos(phi), 0.0, 2.0 * std::sin(phi)};
    arc.anchors.push_back(a);
  }
  FeatureMatrix g = anchor_path_features(arc, anchor_feature_layout(AnchorFamily::planar_root));
  const double omega = M_PI / 2 / 40 * kPathFrameRate;  // rad/s
  for (int t = 15; t <= 45; ++t) CHECK(g(t, 1) == Approx(omega).epsilon(0.05));
  CHECK(g(10, 1) == 0.f);  // first prior frame: no turn yet
  CHECK(g.row(9).isZero());
  CHECK(g.row(51).isZero());

  // A standing path (sub-threshold jitter) reads as no turn however its direction flips.
  AnchorSet still;
  still.family = AnchorFamily::planar_root;
  still.frames = 30;
  for (int t = 0; t < 30; t += 3) {
    Anchor a;
    a.frame = t;
    a.axes = {true, false, true};
    a.value = {0.001 * ((t / 3) % 2), 0.0, 0.001 * ((t / 3) % 3)};
    still.anchors.push_back(a);
  }
  FeatureMatrix h = anchor_path_features(still, anchor_feature_layout(AnchorFamily::planar_root));
  CHECK(h.col(1).cwiseAbs().maxCoeff() < 1e-6f);
  CHECK(h.col(0).cwiseAbs().maxCoeff() < kPathMinSpeed * kPathFrameRate);

  // Body points: a hand 0.3 m to the right of (+x') and 0.5 m above the root while the
  // root walks along +X; in the root path's frame that is (0.3, 0.5, 0) at every frame.
  auto bl = anchor_feature_layout(AnchorFamily::body_point, {0, 20});
  AnchorSet bp;
  bp.family = AnchorFamily::body_point;
  bp.frames = 30;
  for (int t : {4, 12, 20}) {
    for (int j : {0, 20}) {
      Anchor a;
      a.frame = t;
      a.joint = j;
      // Heading +X: x' = cos(pi/2) dx - sin(pi/2) dz = -dz, so +x' is world -z.
      a.value = {0.04 * t, j == 0 ? 0.9 : 1.4, j == 0 ? 0.0 : -0.3};
      bp.anchors.push_back(a);
    }
  }
  FeatureMatrix b = anchor_path_features(bp, bl);
  REQUIRE(b.cols() == 34);
  for (int t = 4; t <= 20; ++t) {
    CHECK(b.row(t).segment(14, 3).isZero());                 // the root group has no root-relative channels
    CHECK(b(t, 17 + 14) == Approx(0.3).margin(1e-5));        // x'
    CHECK(b(t, 17 + 15) == Approx(0.5).margin(1e-5));        // y
    CHECK(b(t, 17 + 16) == Approx(0.0).margin(1e-5));        // z'
  }
  CHECK(b.row(3).isZero());
  CHECK(b.row(21).isZero());
  // Without the root anchored the hand's root-relative channels stay 0.
  bp.anchors.erase(std::remove_if(bp.anchors.begin(), bp.anchors.end(), [](const Anchor& a) { return a.joint == 0; }),
                   bp.anchors.end());
  FeatureMatrix b2 = anchor_path_features(bp, bl);
  CHECK(b2.block(0, 17 + 14, 30, 3).isZero());
  CHECK(b2.block(0, 0, 30, 17).isZero());
  CHECK(b2(12, 17 + 12) == 1.f);
  // Anchors on a joint the layout does not list are an error naming it.
  bp.anchors[0].joint = 15;
  expect_user_error([&] { anchor_path_features(bp, bl); }, {"joint 15"});
}
