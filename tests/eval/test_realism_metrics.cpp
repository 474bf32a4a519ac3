// Motion realism metrics by their defining properties: constant-velocity motion has
// zero acceleration and a known parabola has its known one; a rigid skeleton has zero
// bone-length drift and a bone that breathes by a known amount has that std; a clip
// shifted down by d penetrates the floor by d.
#include "data/skeleton.h"
#include "eval_test_util.h"

using namespace mc;
using mc::test::Clip;

namespace {

// The rest pose of `s` (root at the origin) translated by `offset`, at every frame.
Clip rest_clip(const Skeleton& s, int frames, const Eigen::Vector3d& offset = Eigen::Vector3d::Zero()) {
  Clip c(frames, s.num_joints());
  auto pose = s.rest_pose();
  for (int t = 0; t < frames; ++t)
    for (int j = 0; j < s.num_joints(); ++j) {
      const Eigen::Vector3d p = pose[j] + offset;
      c.set(t, j, p.x(), p.y(), p.z());
    }
  return c;
}

}  // namespace

TEST_CASE("mean |acceleration|: constant velocity is 0, a parabola is its second derivative", "[eval][health]") {
  const Skeleton& s = humanml3d_skeleton();
  const int T = 30;
  const double fps = 20.0;
  // Every joint moves at a constant (joint-dependent) velocity: zero second difference.
  // Dyadic steps keep every position exact in float storage, so the zero is exact.
  Clip linear(T, s.num_joints());
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < s.num_joints(); ++j)
      linear.set(t, j, 0.125 * j + 0.0625 * t, 1.0 - 0.015625 * t, 0.03125 * j * t);
  CHECK(mean_abs_acceleration(linear.view(), fps) == Approx(0.0).margin(1e-9));
  // x(t) = a/2 (t / fps)^2 along x, y(t) = const: |acceleration| = a exactly, at any fps.
  for (double a : {0.5, 3.0}) {
    Clip para(T, s.num_joints());
    for (int t = 0; t < T; ++t)
      for (int j = 0; j < s.num_joints(); ++j) {
        const double sec = t / fps;
        para.set(t, j, 0.5 * a * sec * sec, 0.3 * j, 0.0);
      }
    CHECK(mean_abs_acceleration(para.view(), fps) == Approx(a).epsilon(1e-4));
    // Over clips: the mean of per-clip means, a 2-frame clip (no interior frame) skipped.
    Clip tiny(2, s.num_joints());
    CHECK(mean_abs_acceleration({para.view(), linear.view(), tiny.view()}, fps) == Approx(a / 2).epsilon(1e-4));
  }
  // Only valid frames count: a jump into the padding does not.
  Clip padded(T, s.num_joints(), 10);
  for (int t = 10; t < T; ++t) padded.set(t, 3, 5.0, 5.0, 5.0);
  CHECK(mean_abs_acceleration(padded.view(), fps) == 0.0);
  Clip two(2, s.num_joints());
  REQUIRE_USER_ERROR(mean_abs_acceleration(std::vector<JointsView>{two.view()}, fps), "3 valid frames");
}

TEST_CASE("bone-length std: a rigid skeleton moving rigidly is 0, a breathing bone gives its std", "[eval][health]") {
  const Skeleton& s = humanml3d_skeleton();
  const int T = 40;
  // Rest pose translated and rotated about y over time: every bone keeps its length.
  Clip rigid(T, s.num_joints());
  auto pose = s.rest_pose();
  for (int t = 0; t < T; ++t) {
    const double ang = 0.1 * t;
    const Eigen::Matrix3d R = Eigen::AngleAxisd(ang, Eigen::Vector3d::UnitY()).toRotationMatrix();
    for (int j = 0; j < s.num_joints(); ++j) {
      const Eigen::Vector3d p = R * pose[j] + Eigen::Vector3d(0.3 * t, 0.9, -0.1 * t);
      rigid.set(t, j, p.x(), p.y(), p.z());
    }
  }
  CHECK(bone_length_std_mm(rigid.view(), s) == Approx(0.0).margin(1e-3));  // float storage: < 1 micrometre
  // One leaf joint (the head, 15) alternates +-2 cm along its bone: that bone's
  // population std is 20 mm, the other 20 bones' 0 -> mean 20 / 21 mm.
  const int head = s.joint_index("head");
  REQUIRE(s.parents[head] >= 0);
  Clip breathing = rest_clip(s, T);
  const Eigen::Vector3d dir = (pose[head] - pose[s.parents[head]]).normalized();
  for (int t = 0; t < T; ++t) {
    const Eigen::Vector3d p = pose[head] + dir * (t % 2 ? 0.02 : -0.02);
    breathing.set(t, head, p.x(), p.y(), p.z());
  }
  const int bones = s.num_joints() - 1;
  CHECK(bone_length_std_mm(breathing.view(), s) == Approx(20.0 / bones).epsilon(1e-4));
  // Mean over clips.
  CHECK(bone_length_std_mm({breathing.view(), rigid.view()}, s) == Approx(10.0 / bones).epsilon(1e-3));
  Clip wrong(T, 5);
  REQUIRE_USER_ERROR(bone_length_std_mm(wrong.view(), s), "5 joints");
}

TEST_CASE("toe floor penetration: a clip shifted down by d penetrates by d", "[eval][health]") {
  const Skeleton& s = humanml3d_skeleton();
  auto pose = s.rest_pose();
  double lowest_toe = INFINITY;
  for (int j : s.role("toes")) lowest_toe = std::min(lowest_toe, pose[j].y());
  // Stand the rest pose on the floor: its lowest toe at y = 0 exactly.
  Clip on_floor = rest_clip(s, 20, Eigen::Vector3d(0, -lowest_toe, 0));
  FloorPenetration p0 = toe_floor_penetration({on_floor.view()}, s);
  CHECK(p0.depth == Approx(0.0).margin(1e-6));
  CHECK(p0.frame_fraction == 0.0);
  for (double d : {0.01, 0.1}) {
    Clip sunk = rest_clip(s, 20, Eigen::Vector3d(0, -lowest_toe - d, 0));
    FloorPenetration p = toe_floor_penetration({sunk.view()}, s);
    CHECK(p.depth == Approx(d).epsilon(1e-5));
    CHECK(p.frame_fraction == 1.0);
    // Mean over clips for the depth; frames pooled for the fraction.
    Clip longer = rest_clip(s, 60, Eigen::Vector3d(0, -lowest_toe, 0));
    FloorPenetration mixed = toe_floor_penetration({sunk.view(), longer.view()}, s);
    CHECK(mixed.depth == Approx(d / 2).epsilon(1e-5));
    CHECK(mixed.frame_fraction == Approx(20.0 / 80.0));
  }
  // Only the toes count: a hand below the floor is not penetration here.
  Clip hand_low = rest_clip(s, 10, Eigen::Vector3d(0, -lowest_toe, 0));
  for (int t = 0; t < 10; ++t) hand_low.set(t, s.joint_index("l_wrist"), 0.0, -0.3, 0.0);
  CHECK(toe_floor_penetration({hand_low.view()}, s).depth == Approx(0.0).margin(1e-6));
  // Frames past the length are padding: a sunk padded frame does not count.
  Clip padded = rest_clip(s, 20, Eigen::Vector3d(0, -lowest_toe, 0));
  padded.length = 10;
  for (int t = 10; t < 20; ++t)
    for (int j : s.role("toes")) padded.set(t, j, 0.0, -1.0, 0.0);
  CHECK(toe_floor_penetration({padded.view()}, s).frame_fraction == 0.0);
  REQUIRE_USER_ERROR(toe_floor_penetration({}, s), "no clips");
}
