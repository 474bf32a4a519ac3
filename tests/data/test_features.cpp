// Joint-derived features: the facing convention, invariance to world heading and
// position, known root motions, foot contacts, the mc67 inverse, and the real
// HumanML3D clip in ../shared (skipped when absent).
#include <catch2/catch.hpp>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>

#include "core/error.h"
#include "data/features.h"
#include "data_test_util.h"

using namespace mc;
using Catch::Matchers::Contains;

namespace {

constexpr double kPi = 3.14159265358979323846;

const Skeleton& skel() { return humanml3d_skeleton(); }

// Rotation about +Y by `angle` (R_y in reference-facts §3: +Z turns towards +X).
void rotate_y(double angle, double x, double z, double& ox, double& oz) {
  ox = std::cos(angle) * x + std::sin(angle) * z;
  oz = -std::sin(angle) * x + std::cos(angle) * z;
}

// The rest pose turned to `heading` (0 = facing +Z, pi/2 = +X) with its root at (x, h, z).
void put_rest_pose(float* frame, double heading, double x, double h, double z) {
  auto rest = skel().rest_pose();
  for (int j = 0; j < skel().num_joints(); ++j) {
    double rx, rz;
    rotate_y(heading, rest[j].x(), rest[j].z(), rx, rz);
    frame[j * 3 + 0] = static_cast<float>(rx + x);
    frame[j * 3 + 1] = static_cast<float>(rest[j].y() + h);
    frame[j * 3 + 2] = static_cast<float>(rz + z);
  }
}

// A walk-like clip: curving root path, turning heading, bobbing root and
// per-joint wobble, so nothing is accidentally symmetric.
std::vector<float> wandering_clip(int T, unsigned seed = 3) {
  const int J = skel().num_joints();
  std::vector<float> clip(static_cast<size_t>(T) * J * 3);
  std::mt19937 rng(seed);
  std::normal_distribution<float> wobble(0.0f, 0.03f);
  double x = 0.3, z = -0.2;
  for (int t = 0; t < T; ++t) {
    const double heading = 0.4 + 0.9 * std::sin(t * 0.07);
    x += 0.04 * std::sin(heading);
    z += 0.04 * std::cos(heading);
    float* f = clip.data() + static_cast<size_t>(t) * J * 3;
    put_rest_pose(f, heading, x, 0.9 + 0.03 * std::sin(t * 0.5), z);
    for (int k = 3; k < J * 3; ++k) f[k] += wobble(rng);
  }
  return clip;
}

std::vector<float> transformed(const std::vector<float>& clip, double angle, double dx, double dz) {
  std::vector<float> out(clip.size());
  for (size_t k = 0; k < clip.size(); k += 3) {
    double x, z;
    rotate_y(angle, clip[k], clip[k + 2], x, z);
    out[k] = static_cast<float>(x + dx);
    out[k + 1] = clip[k + 1];
    out[k + 2] = static_cast<float>(z + dz);
  }
  return out;
}

double max_abs_diff(const std::vector<float>& a, const std::vector<float>& b) {
  REQUIRE(a.size() == b.size());
  double m = 0;
  for (size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(double(a[i]) - b[i]));
  return m;
}

FeatureOptions unsmoothed() {
  FeatureOptions o;
  o.facing_smooth_sigma = 0;
  return o;
}

// Minimal .npy reader for little-endian float32 C-order arrays.
std::vector<float> read_npy_f32(const std::string& path, std::vector<size_t>& shape) {
  std::ifstream f(path, std::ios::binary);
  REQUIRE(f);
  char magic[8];
  f.read(magic, 8);
  REQUIRE(std::memcmp(magic, "\x93NUMPY", 6) == 0);
  uint32_t header_len = 0;
  if (magic[6] == 1) {
    uint16_t h;
    f.read(reinterpret_cast<char*>(&h), 2);
    header_len = h;
  } else {
    f.read(reinterpret_cast<char*>(&header_len), 4);
  }
  std::string header(header_len, ' ');
  f.read(header.data(), header_len);
  REQUIRE(header.find("'<f4'") != std::string::npos);
  REQUIRE(header.find("'fortran_order': False") != std::string::npos);
  shape.clear();
  size_t p = header.find('(') + 1, count = 1;
  while (true) {
    size_t q = header.find_first_of(",)", p);
    std::string num = header.substr(p, q - p);
    if (num.find_first_of("0123456789") != std::string::npos) {
      shape.push_back(std::stoul(num));
      count *= shape.back();
    }
    if (header[q] == ')') break;
    p = q + 1;
  }
  std::vector<float> data(count);
  f.read(reinterpret_cast<char*>(data.data()), static_cast<std::streamsize>(count * sizeof(float)));
  REQUIRE(f);
  return data;
}

}  // namespace

TEST_CASE("facing: the rest pose faces +Z and headings follow atan2(x, z)", "[data][features]") {
  std::vector<float> clip(5 * 22 * 3);
  for (int t = 0; t < 5; ++t) put_rest_pose(clip.data() + t * 66, 0.0, 0, 0.9, 0);
  // The rest pose has its left hip at +X, as HumanML3D's.
  CHECK(clip[1 * 3] > 0.05f);
  for (double theta : facing_angles(clip.data(), 5, skel())) CHECK(theta == Approx(0.0).margin(1e-9));

  for (double heading : {kPi / 2, -kPi / 2, 1.0, 3.0}) {
    auto turned = transformed(clip, heading, 0, 0);
    for (double theta : facing_angles(turned.data(), 5, skel())) CHECK(theta == Approx(heading).margin(1e-6));
  }
}

TEST_CASE("mc67 of a standing rest pose: zero root motion, positions = rest offsets", "[data][features]") {
  const double h = 0.93;
  for (double heading : {0.0, 2.2}) {
    std::vector<float> clip(6 * 22 * 3);
    for (int t = 0; t < 6; ++t) put_rest_pose(clip.data() + t * 66, heading, 1.5, h, -0.7);
    auto f = mc67_features(clip.data(), 6, skel());
    REQUIRE(f.size() == 5u * 67);
    REQUIRE(feature_dim("mc67", skel()) == 67);
    auto rest = skel().rest_pose();
    for (int t = 0; t < 5; ++t) {
      const float* r = f.data() + t * 67;
      CHECK(r[0] == Approx(0).margin(1e-6));
      CHECK(r[1] == Approx(0).margin(1e-6));
      CHECK(r[2] == Approx(0).margin(1e-6));
      CHECK(r[3] == Approx(h).margin(1e-6));
      for (int j = 1; j < 22; ++j) {
        CHECK(r[4 + (j - 1) * 3 + 0] == Approx(rest[j].x()).margin(1e-5));
        CHECK(r[4 + (j - 1) * 3 + 1] == Approx(rest[j].y() + h).margin(1e-5));
        CHECK(r[4 + (j - 1) * 3 + 2] == Approx(rest[j].z()).margin(1e-5));
      }
    }
  }
}

TEST_CASE("features are invariant to rotating the clip about Y and moving it in xz", "[data][features]") {
  const int T = 60;
  const auto clip = wandering_clip(T);
  const double angle = GENERATE(0.5, -1.9, 3.1, kPi);
  const auto moved = transformed(clip, angle, 4.0, -2.5);
  for (const std::string layout : {"mc67", "mc67+vel+contact"}) {
    INFO(layout << " rotated by " << angle);
    auto a = compute_features(layout, clip.data(), T, skel());
    auto b = compute_features(layout, moved.data(), T, skel());
    REQUIRE(a.size() == static_cast<size_t>(T - 1) * feature_dim(layout, skel()));
    CHECK(max_abs_diff(a, b) < 1e-4);
    auto au = compute_features(layout, clip.data(), T, skel(), unsmoothed());
    auto bu = compute_features(layout, moved.data(), T, skel(), unsmoothed());
    CHECK(max_abs_diff(au, bu) < 1e-4);
    // Smoothing matters on a turning clip, so the two option sets really differ.
    CHECK(max_abs_diff(a, au) > 1e-3);
  }
}

TEST_CASE("a root walking forward at 1 m/s has velocity z = 1/20 per frame in its own frame", "[data][features]") {
  const int T = 30;
  const double heading = GENERATE(0.0, 1.0, -2.4, kPi);
  std::vector<float> clip(T * 66);
  for (int t = 0; t < T; ++t) {
    const double d = t / 20.0;  // metres walked at 1 m/s, 20 fps
    put_rest_pose(clip.data() + t * 66, heading, 2.0 + d * std::sin(heading), 0.9, -1.0 + d * std::cos(heading));
  }
  auto f = mc67_features(clip.data(), T, skel());
  auto vel = joint_velocities(clip.data(), T, skel());
  for (int t = 0; t < T - 1; ++t) {
    INFO("heading " << heading << " frame " << t);
    CHECK(f[t * 67 + 0] == Approx(0).margin(1e-6));
    CHECK(f[t * 67 + 1] == Approx(0).margin(1e-5));
    CHECK(f[t * 67 + 2] == Approx(0.05).margin(1e-5));
    for (int j = 0; j < 22; ++j) {  // every joint moves with the root
      CHECK(vel[(t * 22 + j) * 3 + 0] == Approx(0).margin(1e-5));
      CHECK(vel[(t * 22 + j) * 3 + 1] == Approx(0).margin(1e-6));
      CHECK(vel[(t * 22 + j) * 3 + 2] == Approx(0.05).margin(1e-5));
    }
  }
}

TEST_CASE("turning at a constant rate gives a constant angular velocity", "[data][features]") {
  const int T = 200;
  const double omega = 0.05;  // rad per frame, turning towards +X (to the character's left)
  std::vector<float> clip(T * 66);
  for (int t = 0; t < T; ++t) put_rest_pose(clip.data() + t * 66, 0.3 + omega * t, 0.5, 0.9, 0.5);

  // HumanML3D's convention: half the heading change, negative for a left turn.
  auto raw = mc67_features(clip.data(), T, skel(), unsmoothed());
  for (int t = 0; t < T - 1; ++t) {
    REQUIRE(raw[t * 67 + 0] == Approx(-omega / 2).margin(1e-6));
    REQUIRE(raw[t * 67 + 2] == Approx(0).margin(1e-6));
  }
  // Smoothed (sigma 20, kernel radius 80): exact away from the clip ends.
  auto smooth = mc67_features(clip.data(), T, skel());
  for (int t = 81; t < T - 82; ++t) REQUIRE(smooth[t * 67 + 0] == Approx(-omega / 2).margin(1e-6));
}

TEST_CASE("foot contacts: stationary feet touch, sliding feet do not", "[data][features]") {
  const int T = 10;
  std::vector<float> clip(T * 66);
  const double speed = GENERATE(0.0, 0.8, 1.0);  // m/s of the left foot; 0.002 m^2/frame = 0.894 m/s
  for (int t = 0; t < T; ++t) {
    float* f = clip.data() + t * 66;
    put_rest_pose(f, 0.0, 0, 0.9, 0);
    for (int j : {7, 10}) f[j * 3 + 0] += static_cast<float>(speed * t / 20.0);
  }
  auto c = foot_contacts(clip.data(), T, skel());
  REQUIRE(c.size() == static_cast<size_t>(T - 1) * 4);
  const float left = speed < 0.894 ? 1.0f : 0.0f;
  for (int t = 0; t < T - 1; ++t) {
    INFO("speed " << speed << " frame " << t);
    CHECK(c[t * 4 + 0] == left);  // l_ankle
    CHECK(c[t * 4 + 1] == left);  // l_foot
    CHECK(c[t * 4 + 2] == 1.0f);  // r_ankle stands still
    CHECK(c[t * 4 + 3] == 1.0f);  // r_foot
  }
  FeatureOptions strict;
  strict.contact_threshold = 0.001;  // 0.632 m/s
  auto cs = foot_contacts(clip.data(), T, skel(), strict);
  CHECK(cs[0] == (speed < 0.632 ? 1.0f : 0.0f));
  CHECK(cs[2] == 1.0f);
}

TEST_CASE("recover_joints_from_mc67 inverts mc67 up to the frame-0 heading and position", "[data][features]") {
  const int T = 50;
  const auto clip = wandering_clip(T, 9);
  for (const FeatureOptions& opt : {FeatureOptions{}, unsmoothed()}) {
    auto f = mc67_features(clip.data(), T, skel(), opt);
    auto rec = recover_joints_from_mc67(f.data(), T - 1, 22);
    // Expected: the clip moved so root 0 is at x = z = 0 and turned to face +Z.
    const double theta0 = facing_angles(clip.data(), T, skel(), opt)[0];
    std::vector<float> expected = transformed(clip, 0.0, -clip[0], -clip[2]);
    expected = transformed(expected, -theta0, 0, 0);
    expected.resize(rec.size());
    CHECK(max_abs_diff(rec, expected) < 1e-4);
  }
}

TEST_CASE("feature layouts: dimensions, unknown names, batches respect lengths", "[data][features]") {
  CHECK(feature_dim("mc67", skel()) == 67);
  CHECK(feature_dim("mc67+vel+contact", skel()) == 67 + 66 + 4);
  try {
    feature_dim("mc76", skel());
    FAIL("no UserError");
  } catch (const UserError& e) {
    CHECK_THAT(e.what(), Contains("mc76") && Contains("did you mean 'mc67'"));
  }

  MotionSet m = test::random_motion_set({8, 1, 5}, {"train"});
  for (size_t i = 0; i < m.size(); ++i) {  // random joints would have no facing: use the wanderer
    auto w = wandering_clip(m.lengths[i], static_cast<unsigned>(i));
    std::copy(w.begin(), w.end(), m.clip(i));
  }
  FeatureSet fs = compute_features(m, "mc67+vel+contact");
  CHECK(fs.dim == 137);
  CHECK(fs.t_max == 7);
  CHECK(fs.lengths == std::vector<int>{7, 0, 4});
  REQUIRE(fs.values.size() == 3u * 7 * 137);
  for (size_t i = 0; i < m.size(); ++i) {
    auto one = compute_features("mc67+vel+contact", m.clip(i), m.lengths[i], skel());
    std::vector<float> got(fs.clip(i), fs.clip(i) + one.size());
    CHECK(got == one);
    for (size_t k = one.size(); k < 7u * 137; ++k) REQUIRE(fs.clip(i)[k] == 0.0f);
  }
}

TEST_CASE("degenerate poses still give finite features", "[data][features]") {
  std::vector<float> clip(4 * 66, 0.0f);  // every joint at the origin: no facing
  put_rest_pose(clip.data() + 2 * 66, 1.0, 0, 0.9, 0);
  auto theta = facing_angles(clip.data(), 4, skel(), unsmoothed());
  CHECK(theta[0] == Approx(1.0));  // borrows the first valid frame
  CHECK(theta[3] == Approx(1.0));  // and later ones the previous frame
  auto f = compute_features("mc67+vel+contact", clip.data(), 4, skel());
  for (float v : f) REQUIRE(std::isfinite(v));
}

TEST_CASE("mc67 on the real HumanML3D clip matches its rotation-invariant parts", "[data][features]") {
  namespace fs = std::filesystem;
  const fs::path dir = fs::path(MOTIONCTL_SOURCE_DIR) / ".." / "shared" / "reference" / "humanml3d";
  if (!fs::exists(dir / "012314_new_joints.npy")) {
    WARN("../shared/reference/humanml3d absent: skipped");
    return;
  }
  std::vector<size_t> js, vs;
  auto joints = read_npy_f32((dir / "012314_new_joints.npy").string(), js);
  auto vecs = read_npy_f32((dir / "012314_new_joint_vecs.npy").string(), vs);
  REQUIRE(js == std::vector<size_t>{170, 22, 3});
  REQUIRE(vs == std::vector<size_t>{170, 263});
  const int T = 170;
  auto f = mc67_features(joints.data(), T, skel());
  // HumanML3D's own facing frame cannot be recomputed from new_joints (on this clip
  // it departs from the raw and the smoothed hip/shoulder facing by 0.4-0.7 rad),
  // so compare what does not depend on it: root height, root speed, joint heights and distances
  // from the root axis.
  double worst = 0;
  for (int t = 0; t < T - 1; ++t) {
    const float* a = f.data() + t * 67;
    const float* b = vecs.data() + t * 263;
    worst = std::max(worst, std::abs(double(a[3]) - b[3]));
    worst = std::max(worst, std::abs(std::hypot(double(a[1]), double(a[2])) - std::hypot(double(b[1]), double(b[2]))));
    for (int j = 0; j < 21; ++j) {
      const float* pa = a + 4 + j * 3;
      const float* pb = b + 4 + j * 3;
      worst = std::max(worst, std::abs(double(pa[1]) - pb[1]));
      worst = std::max(worst, std::abs(std::hypot(double(pa[0]), double(pa[2])) - std::hypot(double(pb[0]), double(pb[2]))));
    }
  }
  CHECK(worst < 1e-5);
  // Foot contacts use world displacements only, so they match HumanML3D's exactly.
  auto c = foot_contacts(joints.data(), T, skel());
  int mismatches = 0;
  for (int t = 0; t < T - 1; ++t)
    for (int k = 0; k < 4; ++k) mismatches += c[t * 4 + k] != vecs[t * 263 + 259 + k];
  CHECK(mismatches == 0);
}

TEST_CASE("inv67: exact round trip in the clip's own world frame, whatever its start", "[data][features][invariant]") {
  const int T = 57;
  const auto clip = wandering_clip(T, 4);  // starts away from the origin, facing 0.4 rad
  for (const std::string layout : {"inv67", "inv67+vel+contact"}) {
    for (const FeatureOptions& opt : {FeatureOptions{}, unsmoothed()}) {
      INFO(layout);
      auto f = compute_features(layout, clip.data(), T, skel(), opt);
      REQUIRE(feature_frames(layout, T) == T);
      REQUIRE(f.size() == static_cast<size_t>(T) * feature_dim(layout, skel()));
      auto rec = recover_joints_from_invariant(f.data(), T, 22, feature_dim(layout, skel()));
      CHECK(max_abs_diff(rec, clip) < 1e-4);
    }
  }
  CHECK(feature_dim("inv67", skel()) == 67);
  CHECK(feature_dim("inv67+vel+contact", skel()) == 137);
}

TEST_CASE("inv67: rows after the first are invariant to rotating and moving the clip", "[data][features][invariant]") {
  const int T = 60;
  const auto clip = wandering_clip(T);
  const double angle = GENERATE(0.5, -1.9, kPi);
  const auto moved = transformed(clip, angle, 4.0, -2.5);
  for (const std::string layout : {"inv67", "inv67+vel+contact"}) {
    INFO(layout << " rotated by " << angle);
    const int D = feature_dim(layout, skel());
    auto a = compute_features(layout, clip.data(), T, skel());
    auto b = compute_features(layout, moved.data(), T, skel());
    // Row 0 is the step from the canonical frame -1 (it holds the world pose of frame 0).
    std::vector<float> a1(a.begin() + D, a.end()), b1(b.begin() + D, b.end());
    CHECK(max_abs_diff(a1, b1) < 1e-4);
    // A crop's rows are the whole clip's rows: features of frames 10.. equal rows 10.. of the clip's.
    auto tail = compute_features(layout, clip.data() + 10 * 22 * 3, T - 10, skel(), unsmoothed());
    auto whole = compute_features(layout, clip.data(), T, skel(), unsmoothed());
    std::vector<float> t1(tail.begin() + D, tail.end()), w1(whole.begin() + 11 * D, whole.end());
    CHECK(max_abs_diff(t1, w1) < 1e-4);
  }
  // mc67 and inv67 hold the same root height and local positions.
  auto mc = compute_features("mc67", clip.data(), T, skel());
  auto inv = compute_features("inv67", clip.data(), T, skel());
  for (int t = 0; t + 1 < T; ++t)
    for (int d = 3; d < 67; ++d) REQUIRE(mc[t * 67 + d] == Approx(inv[t * 67 + d]).margin(1e-6));
}
