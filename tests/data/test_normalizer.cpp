// Normalisation statistics: train split only, hand-computed values, the std
// floor, and the affine maps in both directions.
#include <catch2/catch.hpp>
#include <cmath>
#include <random>

#include "core/error.h"
#include "data/features.h"
#include "data/normalizer.h"
#include "data_test_util.h"

using namespace mc;
using Catch::Matchers::Contains;

namespace {

// Every joint of clip i frame t at the same point.
void fill_frame(MotionSet& m, size_t i, int t, float x, float y, float z) {
  for (int j = 0; j < m.num_joints(); ++j) {
    m.at(i, t, j)[0] = x;
    m.at(i, t, j)[1] = y;
    m.at(i, t, j)[2] = z;
  }
}

// Standing rest poses: clip i stands at root height heights[i] for lengths[i] frames.
MotionSet standing_set(const std::vector<int>& lengths, const std::vector<double>& heights,
                       const std::vector<std::string>& splits) {
  MotionSet m = test::random_motion_set(lengths, splits);
  std::fill(m.joints.begin(), m.joints.end(), 0.0f);
  auto rest = m.skeleton.rest_pose();
  for (size_t i = 0; i < m.size(); ++i)
    for (int t = 0; t < lengths[i]; ++t)
      for (int j = 0; j < m.num_joints(); ++j) {
        m.at(i, t, j)[0] = static_cast<float>(rest[j].x());
        m.at(i, t, j)[1] = static_cast<float>(rest[j].y() + heights[i]);
        m.at(i, t, j)[2] = static_cast<float>(rest[j].z());
      }
  return m;
}

}  // namespace

TEST_CASE("joint stats by hand: per axis over valid frames and joints of the train split", "[data]") {
  // Clip 0 (train, 2 of 4 frames valid): x 1 then 3, y 0 then 2, z always 5.
  // Clip 1 (train, 1 frame): x 2, y 1, z 5. Clip 2 (test): huge values, must be ignored.
  MotionSet m = test::random_motion_set({2, 1, 4}, {"train", "train", "test"});
  std::fill(m.joints.begin(), m.joints.end(), 0.0f);
  fill_frame(m, 0, 0, 1, 0, 5);
  fill_frame(m, 0, 1, 3, 2, 5);
  fill_frame(m, 1, 0, 2, 1, 5);
  for (int t = 0; t < 4; ++t) fill_frame(m, 2, t, 1e4f, -1e4f, 1e4f);
  NormStats s = compute_norm_stats(m);
  // x: {1 x22, 3 x22, 2 x22} -> mean 2, population var (22 + 22 + 0) / 66 = 2/3.
  CHECK(s.joint_mean[0] == Approx(2.0));
  CHECK(s.joint_std[0] == Approx(std::sqrt(2.0 / 3.0)));
  CHECK(s.joint_mean[1] == Approx(1.0));
  CHECK(s.joint_std[1] == Approx(std::sqrt(2.0 / 3.0)));
  CHECK(s.joint_mean[2] == Approx(5.0));
  CHECK(s.joint_std[2] == Approx(1e-4));  // constant axis: floored
  CHECK(s.feature_layout == "mc67");
  CHECK(s.feature_mean.size() == 67);
}

TEST_CASE("feature stats by hand: weighted by frames, floored where constant", "[data]") {
  // Train clips stand still at root heights 0.9 (3 frames -> 2 feature frames)
  // and 1.1 (5 frames -> 4). Heights: mean (2*0.9 + 4*1.1)/6, population std below.
  MotionSet m = standing_set({3, 5, 6}, {0.9, 1.1, 40.0}, {"train", "train", "val"});
  NormStats s = compute_norm_stats(m);
  const double mean = (2 * 0.9 + 4 * 1.1) / 6;
  const double sd = std::sqrt((2 * (0.9 - mean) * (0.9 - mean) + 4 * (1.1 - mean) * (1.1 - mean)) / 6);
  CHECK(s.feature_mean[3] == Approx(mean).epsilon(1e-6));
  CHECK(s.feature_std[3] == Approx(sd).epsilon(1e-5));
  for (int d : {0, 1, 2}) {  // standing still: zero root velocities, floored std
    CHECK(s.feature_mean[d] == Approx(0).margin(1e-7));
    CHECK(s.feature_std[d] == Approx(1e-4));
  }
  auto rest = m.skeleton.rest_pose();
  for (int j = 1; j < 22; ++j) {
    CHECK(s.feature_mean[4 + (j - 1) * 3 + 0] == Approx(rest[j].x()).margin(1e-6));
    CHECK(s.feature_mean[4 + (j - 1) * 3 + 1] == Approx(rest[j].y() + mean).margin(1e-5));
    CHECK(s.feature_std[4 + (j - 1) * 3 + 1] == Approx(sd).epsilon(1e-4));
    CHECK(s.feature_std[4 + (j - 1) * 3 + 2] == Approx(1e-4));
  }

  NormOptions looser;
  looser.std_floor = 0.5;
  NormStats l = compute_norm_stats(m, looser);
  CHECK(l.feature_std[0] == Approx(0.5));
  CHECK(l.feature_std[3] == Approx(0.5));  // sd < 0.5 is floored too
}

TEST_CASE("stats come from the train split only", "[data]") {
  MotionSet m = test::random_motion_set({9, 7, 12, 5, 8, 11}, {"train", "val", "test", "train", "train", "test"}, 5);
  const NormStats base = compute_norm_stats(m);
  // Put absurd motion into every non-train clip.
  for (size_t i : m.indices_of_split("val"))
    for (int t = 0; t < m.lengths[i]; ++t) fill_frame(m, i, t, 1e5f, 3e5f * t, -1e5f);
  for (size_t i : m.indices_of_split("test"))
    for (int t = 0; t < m.lengths[i]; ++t) fill_frame(m, i, t, -7e4f * t, 1e6f, 2e5f * t);
  const NormStats after = compute_norm_stats(m);
  CHECK(test::same_stats(base, after));
  // The same as computing on the train clips alone.
  CHECK(test::same_stats(base, compute_norm_stats(m.subset(m.indices_of_split("train")))));
  // And really different from stats over everything.
  NormOptions all_val;
  all_val.split = "val";
  CHECK(compute_norm_stats(m, all_val).joint_std[1] > 1e4);

  NormOptions none;
  none.split = "sample";
  try {
    compute_norm_stats(m, none);
    FAIL("no UserError");
  } catch (const UserError& e) {
    CHECK_THAT(e.what(), Contains("'sample'"));
  }
}

TEST_CASE("normalised train joints have zero mean and unit std per axis", "[data]") {
  MotionSet m = test::random_motion_set({9, 7, 12}, {"train"}, 21);
  NormStats s = compute_norm_stats(m);
  std::vector<double> sum(3, 0), sq(3, 0);
  size_t n = 0;
  for (size_t i = 0; i < m.size(); ++i) {
    std::vector<float> clip(m.clip(i), m.clip(i) + static_cast<size_t>(m.lengths[i]) * 66);
    normalize_joints(s, clip.data(), clip.size() / 3);
    for (size_t k = 0; k < clip.size(); k += 3, ++n)
      for (int a = 0; a < 3; ++a) {
        sum[a] += clip[k + a];
        sq[a] += double(clip[k + a]) * clip[k + a];
      }
  }
  for (int a = 0; a < 3; ++a) {
    CHECK(sum[a] / n == Approx(0).margin(1e-5));
    CHECK(sq[a] / n == Approx(1).epsilon(1e-4));
  }
}

TEST_CASE("normalise then denormalise is the identity, the affine maps are explicit", "[data]") {
  NormStats s;
  s.joint_mean = {0.00016f, 0.3766f, 0.3102f};  // HumanML3D's values (reference-facts §2)
  s.joint_std = {0.5148f, 0.6101f, 0.8716f};
  s.feature_mean = {0.1f, -2.0f, 30.0f, 0.0f};
  s.feature_std = {0.01f, 1.0f, 4.0f, 1e-4f};
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> u(-3, 3);

  std::vector<float> xyz(22 * 3 * 10);
  for (auto& v : xyz) v = u(rng);
  auto work = xyz;
  normalize_joints(s, work.data(), work.size() / 3);
  // The explicit map gives the same numbers: scale 1/std, offset -mean/std.
  AxisAffine n = joint_normalizer(s);
  for (size_t k = 0; k < xyz.size(); ++k) {
    const int a = static_cast<int>(k % 3);
    REQUIRE(work[k] == Approx((xyz[k] - s.joint_mean[a]) / s.joint_std[a]).epsilon(1e-5).margin(1e-6));
    REQUIRE(work[k] == Approx(n.scale[a] * xyz[k] + n.offset[a]).epsilon(1e-6).margin(1e-6));
  }
  denormalize_joints(s, work.data(), work.size() / 3);
  for (size_t k = 0; k < xyz.size(); ++k) REQUIRE(work[k] == Approx(xyz[k]).margin(1e-5));

  // inverse() of the normaliser is the denormaliser.
  AxisAffine inv = n.inverse(), d = joint_denormalizer(s);
  for (int a = 0; a < 3; ++a) {
    CHECK(inv.scale[a] == Approx(d.scale[a]).epsilon(1e-12));
    CHECK(inv.offset[a] == Approx(d.offset[a]).epsilon(1e-7).margin(1e-12));
  }

  std::vector<float> feats(4 * 25);
  for (auto& v : feats) v = u(rng);
  auto f = feats;
  normalize_features(s, f.data(), 25, 4);
  CHECK(f[2] == Approx((feats[2] - 30.0f) / 4.0f));
  denormalize_features(s, f.data(), 25, 4);
  for (size_t k = 0; k < feats.size(); ++k) REQUIRE(f[k] == Approx(feats[k]).margin(1e-5));

  CHECK_THROWS_AS(normalize_features(s, f.data(), 25, 67), UserError);
}
