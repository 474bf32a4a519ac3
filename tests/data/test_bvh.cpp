// BVH export and reader: Euler angles round-trip and stay continuous, forward
// kinematics of the written file returns fixture clips (rigid layout) and
// arbitrary non-rigid motion (every joint translated) to 1e-4 m, and a
// malformed file is refused naming its line.
#include <catch2/catch.hpp>

#include <cmath>
#include <random>

#include "core/error.h"
#include "data/bvh.h"
#include "data/fixture/fixture.h"
#include "data_test_util.h"

using namespace mc;
using Catch::Matchers::Contains;

namespace {

constexpr double kPi = 3.14159265358979323846;

Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::Quaterniond q(n(rng), n(rng), n(rng), n(rng));
  return q.normalized().toRotationMatrix();
}

// Largest distance between the BVH's forward kinematics and the clip, matching joints by name.
double round_trip_error(const Skeleton& s, const float* clip, int frames, const BvhExport& e, double scale = 1.0) {
  BvhMotion b = parse_bvh(e.text, "test");
  REQUIRE(b.frames == frames);
  REQUIRE(b.names.size() == static_cast<size_t>(s.num_joints()));
  std::vector<double> pos = bvh_positions(b, scale);
  double worst = 0;
  for (size_t k = 0; k < b.names.size(); ++k) {
    const int j = s.joint_index(b.names[k]);
    for (int t = 0; t < frames; ++t) {
      const double* q = pos.data() + (static_cast<size_t>(t) * b.names.size() + k) * 3;
      const float* p = clip + (static_cast<size_t>(t) * s.num_joints() + j) * 3;
      worst = std::max(worst, std::sqrt(std::pow(q[0] - p[0], 2) + std::pow(q[1] - p[1], 2) + std::pow(q[2] - p[2], 2)));
    }
  }
  return worst;
}

}  // namespace

TEST_CASE("BVH Euler angles (ZXY) reproduce the rotation and unwrap towards the previous frame", "[data][bvh]") {
  std::mt19937 rng(5);
  for (int k = 0; k < 500; ++k) {
    const Eigen::Matrix3d R = random_rotation(rng);
    std::uniform_real_distribution<double> u(-10.0, 10.0);
    const Eigen::Vector3d prev(u(rng), u(rng), u(rng));
    const Eigen::Vector3d e = euler_zxy_nearest(R, prev);
    CHECK((rotation_zxy(e) - R).cwiseAbs().maxCoeff() < 1e-9);
    // Each angle lies within half a turn of the previous one (its nearest equivalent).
    for (int a = 0; a < 3; ++a) CHECK(std::abs(e[a] - prev[a]) <= kPi + 1e-9);
  }
  SECTION("gimbal lock (x = +-90 degrees) keeps z and solves y") {
    for (double x : {kPi / 2, -kPi / 2}) {
      const Eigen::Vector3d truth(0.3, x, -1.1);
      const Eigen::Vector3d e = euler_zxy_nearest(rotation_zxy(truth), Eigen::Vector3d(0.7, 0, 0));
      CHECK(e[0] == Approx(0.7));
      CHECK((rotation_zxy(e) - rotation_zxy(truth)).cwiseAbs().maxCoeff() < 1e-9);
    }
  }
  SECTION("a joint spinning past 360 degrees gives a continuous curve") {
    Eigen::Vector3d prev = Eigen::Vector3d::Zero();
    for (int t = 0; t <= 100; ++t) {
      const double angle = t * 0.1;  // 10 rad: more than one and a half turns about Y
      Eigen::Vector3d e = euler_zxy_nearest(Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitY()).toRotationMatrix(), prev);
      CHECK((e - prev).norm() < 0.1 + 1e-9);
      prev = e;
    }
    CHECK(prev[2] == Approx(10.0));
  }
}

// Positions from BVH-convention forward kinematics (a joint's rotation turns its children's
// offsets) with random local rotations: motion a rigid BVH represents exactly.
static std::vector<float> rigid_clip(const Skeleton& s, int frames, std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 0.4);
  std::vector<float> out(static_cast<size_t>(frames) * s.num_joints() * 3);
  for (int t = 0; t < frames; ++t) {
    std::vector<Eigen::Matrix3d> G(s.num_joints());
    std::vector<Eigen::Vector3d> P(s.num_joints());
    for (int j = 0; j < s.num_joints(); ++j) {
      const Eigen::Matrix3d L = rotation_zxy(Eigen::Vector3d(n(rng), n(rng), n(rng)));
      const int p = s.parents[j];
      P[j] = p < 0 ? Eigen::Vector3d(0.1 * t, 0.9, -0.05 * t) : Eigen::Vector3d(P[p] + G[p] * s.rest_directions[j] * s.bone_lengths[j]);
      G[j] = p < 0 ? L : Eigen::Matrix3d(G[p] * L);
      for (int a = 0; a < 3; ++a) out[(static_cast<size_t>(t) * s.num_joints() + j) * 3 + a] = static_cast<float>(P[j][a]);
    }
  }
  return out;
}

TEST_CASE("BVH export of rigid motion: the standard layout, forward kinematics returns the joints", "[data][bvh]") {
  const Skeleton& s = humanml3d_skeleton();
  std::mt19937 rng(9);
  for (int k = 0; k < 5; ++k) {
    std::vector<float> clip = rigid_clip(s, 40, rng);
    BvhExport e = clip_to_bvh(s, clip.data(), 40, 20.0);
    CHECK_FALSE(e.all_translations);
    CHECK(e.rigid_error < 1e-5);
    CHECK(e.written_error < 1e-4);
    CHECK(round_trip_error(s, clip.data(), 40, e) < 1e-4);
    CHECK_THAT(e.text, Contains("CHANNELS 3 Zrotation Xrotation Yrotation"));
    CHECK_THAT(e.text, Contains("Frame Time: 0.05000000"));
  }
  SECTION("centimetres: offsets scaled, positions the same after dividing") {
    std::vector<float> clip = rigid_clip(s, 10, rng);
    BvhOptions o;
    o.scale = 100.0;
    BvhExport e = clip_to_bvh(s, clip.data(), 10, 20.0, o);
    BvhMotion b = parse_bvh(e.text, "cm");
    REQUIRE(b.names[1] == "l_hip");  // depth-first: the root's first child
    CHECK(b.offsets[1].norm() == Approx(100.0 * s.bone_lengths[1]).epsilon(1e-6));
    CHECK(e.written_error < 1e-4);
    CHECK(round_trip_error(s, clip.data(), 10, e, 100.0) < 1e-4);
    CHECK(round_trip_error(s, clip.data(), 10, e) > 1.0);  // read without dividing: centimetres
  }
}

TEST_CASE("BVH export of fixture clips: forward kinematics of the file returns the joints", "[data][bvh]") {
  // The fixture turns each bone by its child joint's rotation (HumanML3D's convention), so the
  // pelvis's and spine3's children move independently: no rigid BVH holds them, and `auto`
  // gives every joint its offset.
  FixtureConfig c;
  c.num_clips = 12;
  c.seed = 21;
  MotionSet m = generate_fixture(c, humanml3d_skeleton());
  for (size_t i = 0; i < m.size(); ++i) {
    BvhExport e = clip_to_bvh(m.skeleton, m.clip(i), m.lengths[i], m.fps);
    INFO("clip " << m.ids[i] << " rigid fit error " << e.rigid_error);
    CHECK(e.written_error < 1e-4);
    CHECK(round_trip_error(m.skeleton, m.clip(i), m.lengths[i], e) < 1e-4);
    CHECK(e.all_translations == (e.rigid_error > 1e-4));
  }
}

TEST_CASE("BVH export of non-rigid motion: every joint translated, still exact, rigid layout reports its error",
          "[data][bvh]") {
  // Random positions: no bone keeps its length, nothing is rigid.
  MotionSet m = test::random_motion_set({30, 7}, {"sample"}, 3);
  BvhOptions rigid;
  rigid.translations = "root";
  BvhExport r = clip_to_bvh(m.skeleton, m.clip(0), m.lengths[0], m.fps, rigid);
  CHECK_FALSE(r.all_translations);
  CHECK(r.rigid_error > 0.1);
  CHECK(r.written_error == Approx(r.rigid_error).margin(1e-5));  // what the file gives is what was reported
  for (size_t i = 0; i < m.size(); ++i) {
    BvhExport e = clip_to_bvh(m.skeleton, m.clip(i), m.lengths[i], m.fps);  // auto
    CHECK(e.all_translations);
    CHECK_THAT(e.text, Contains("JOINT l_knee"));
    CHECK(e.written_error < 1e-4);
    CHECK(round_trip_error(m.skeleton, m.clip(i), m.lengths[i], e) < 1e-4);
  }
}

TEST_CASE("BVH rotations: a single-child bone gets its minimal swing, a rest pose gets zero angles", "[data][bvh]") {
  const Skeleton& s = humanml3d_skeleton();
  std::vector<Eigen::Vector3d> rest = s.rest_pose();
  std::vector<float> clip(rest.size() * 3);
  for (size_t j = 0; j < rest.size(); ++j)
    for (int a = 0; a < 3; ++a) clip[j * 3 + a] = static_cast<float>(rest[j][a] + (a == 1 ? 0.9 : 0.0));
  BvhExport e = clip_to_bvh(s, clip.data(), 1, 20.0);
  BvhMotion b = parse_bvh(e.text, "rest");
  // Root translation then all zeros.
  CHECK(b.values[1] == Approx(0.9));
  // (float32 positions: angles to a few 1e-5 degrees)
  for (size_t k = 3; k < b.values.size(); ++k) CHECK(b.values[k] == Approx(0.0).margin(1e-4));
  // Raise the left arm sideways: the shoulder (one child, the elbow) swings about Z only.
  const int sh = s.joint_index("l_shoulder"), el = s.joint_index("l_elbow"), wr = s.joint_index("l_wrist");
  const Eigen::Vector3d base(clip[sh * 3], clip[sh * 3 + 1], clip[sh * 3 + 2]);
  const Eigen::Matrix3d up = Eigen::AngleAxisd(kPi / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  for (int j : {el, wr}) {
    Eigen::Vector3d p(clip[j * 3], clip[j * 3 + 1], clip[j * 3 + 2]);
    p = base + up * (p - base);
    for (int a = 0; a < 3; ++a) clip[j * 3 + a] = static_cast<float>(p[a]);
  }
  e = clip_to_bvh(s, clip.data(), 1, 20.0);
  CHECK_FALSE(e.all_translations);
  b = parse_bvh(e.text, "raised");
  int col = 0;
  for (size_t k = 0; k < b.names.size(); ++k) {
    if (b.names[k] == "l_shoulder") {
      CHECK(b.values[col] == Approx(90.0).margin(1e-4));  // Zrotation
      CHECK(b.values[col + 1] == Approx(0.0).margin(1e-4));
      CHECK(b.values[col + 2] == Approx(0.0).margin(1e-4));
    }
    col += static_cast<int>(b.channels[k].size());
  }
  CHECK(round_trip_error(s, clip.data(), 1, e) < 1e-5);
}

TEST_CASE("BVH reader refuses malformed files naming the line", "[data][bvh]") {
  const std::string good =
      "HIERARCHY\nROOT a\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
      "Yrotation\n  JOINT b\n  {\n    OFFSET 0 1 0\n    CHANNELS 3 Zrotation Xrotation Yrotation\n    End Site\n"
      "    {\n      OFFSET 0 0.5 0\n    }\n  }\n}\nMOTION\nFrames: 2\nFrame Time: 0.05\n"
      "1 2 3 0 0 0 90 0 0\n1 2 3 0 0 0 0 0 0\n";
  BvhMotion m = parse_bvh(good, "good.bvh");
  CHECK(m.names == std::vector<std::string>{"a", "b"});
  CHECK(m.frames == 2);
  auto pos = bvh_positions(m);
  // Frame 0: b's Zrotation of 90 degrees does not move b itself (it turns b's children).
  CHECK(pos[3] == Approx(1.0));
  CHECK(pos[4] == Approx(3.0));
  auto err = [](const std::string& text) {
    try {
      parse_bvh(text, "bad.bvh");
    } catch (const UserError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  std::string short_motion = good.substr(0, good.size() - 6);
  CHECK_THAT(err(short_motion), Contains("bad.bvh") && Contains("expected 18"));
  std::string bad_channel = good;
  bad_channel.replace(bad_channel.find("Zrotation Xrotation Yrotation\n    End"), 9, "Wrotation");
  CHECK_THAT(err(bad_channel), Contains("line 9") && Contains("Wrotation"));
  CHECK_THAT(err("HIERARCHY\nROOT a\n{\n  OFFSET 0 0 x\n"), Contains("line 4") && Contains("'x'"));
  CHECK_THAT(err(""), Contains("bad.bvh"));
}

TEST_CASE("BVH export rejects bad options and non-finite joints", "[data][bvh]") {
  MotionSet m = test::random_motion_set({5}, {"sample"});
  BvhOptions o;
  o.translations = "some";
  CHECK_THROWS_AS(clip_to_bvh(m.skeleton, m.clip(0), 5, 20.0, o), UserError);
  m.at(0, 2, 3)[1] = std::nanf("");
  CHECK_THROWS_WITH(clip_to_bvh(m.skeleton, m.clip(0), 5, 20.0), Contains("frame 2") && Contains("spine1"));
}
