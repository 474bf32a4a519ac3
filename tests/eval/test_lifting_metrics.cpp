// 2D/3D lifting metrics (Sketch2Anim) and tokenizer reconstruction MPJPE on
// hand-computed offsets.
#include "eval_test_util.h"

using namespace mc;
using mc::test::Clip;

namespace {

constexpr int T = 3, J = 22;
constexpr double kDeg = M_PI / 180.0;

Clip ground_truth() {
  Clip g(T, J);
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < J; ++j) g.set(t, j, 0.1 * j - 1.0, 0.05 * j + 0.2 * t, -0.03 * j + t);
  return g;
}

// yaw 90 deg, pitch 0, scale 1.5: s P R_y(90) = 1.5 [[0,0,1],[0,1,0]] (image x = 1.5 z, image y = 1.5 y).
const OrthoCamera kCam{1.5, 0.0, 90.0 * kDeg, 0.0};

}  // namespace

TEST_CASE("lifting metrics are zero for the exact motion", "[eval]") {
  const Clip g = ground_truth();
  const OrthoCamera cam{1.1, 20.0 * kDeg, -30.0 * kDeg, 0.0};
  const Keypoints2D target = project_motion(cam, g.view());
  std::vector<uint8_t> controlled(T * J, 1);
  REQUIRE(mpjpe_2d(g.view(), target, cam, {0, 1, 2}) == Approx(0.0).margin(1e-12));
  REQUIRE(mpjpe_3d(g.view(), g.view(), {0, 2}) == 0.0);
  REQUIRE(avg_err_2d(g.view(), target, cam, mask_view(controlled, T, J, 1)) == Approx(0.0).margin(1e-12));
  REQUIRE(avg_err_3d(g.view(), g.view(), mask_view(controlled, T, J, 1)) == 0.0);
}

TEST_CASE("lifting metrics for one displaced joint, by hand", "[eval]") {
  const Clip g = ground_truth();
  Clip p = g;
  float* w = p.at(1, 20);  // wrist at frame 1 moved by (0.1, 0, 0.2)
  w[0] += 0.1f;
  w[2] += 0.2f;
  const Keypoints2D target = project_motion(kCam, g.view());
  std::vector<uint8_t> controlled(T * J, 0);
  controlled[1 * J + 20] = controlled[2 * J + 20] = controlled[0 * J + 0] = 1;
  const MaskView mask = mask_view(controlled, T, J, 1);
  // 2D: the x part is along the viewing direction and vanishes; 1.5 * 0.2 = 0.3 remains.
  REQUIRE(mpjpe_2d(p.view(), target, kCam, {1, 2}) == Approx(0.3 / (2 * 22)).margin(1e-7));
  REQUIRE(mpjpe_3d(p.view(), g.view(), {1, 2}) == Approx(std::sqrt(0.05) / (2 * 22)).margin(1e-7));
  REQUIRE(avg_err_2d(p.view(), target, kCam, mask) == Approx(0.3 / 3).margin(1e-7));
  REQUIRE(avg_err_3d(p.view(), g.view(), mask) == Approx(std::sqrt(0.05) / 3).margin(1e-7));
  // A keyframe set without frame 1 sees no error.
  REQUIRE(mpjpe_2d(p.view(), target, kCam, {0, 2}) == Approx(0.0).margin(1e-7));
}

TEST_CASE("MPJPE is root-aligned, Avg.Err is not", "[eval]") {
  const Clip g = ground_truth();
  Clip shifted = g;  // the whole motion translated by (1, 2, 3)
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < J; ++j) {
      shifted.at(t, j)[0] += 1.0f;
      shifted.at(t, j)[1] += 2.0f;
      shifted.at(t, j)[2] += 3.0f;
    }
  const Keypoints2D target = project_motion(kCam, g.view());
  std::vector<uint8_t> all(T * J, 1);
  const MaskView mask = mask_view(all, T, J, 1);
  REQUIRE(mpjpe_2d(shifted.view(), target, kCam, {0, 1, 2}) == Approx(0.0).margin(1e-6));
  REQUIRE(mpjpe_3d(shifted.view(), g.view(), {0, 1, 2}) == Approx(0.0).margin(1e-6));
  REQUIRE(avg_err_3d(shifted.view(), g.view(), mask) == Approx(std::sqrt(14.0)).epsilon(1e-6));
  REQUIRE(avg_err_2d(shifted.view(), target, kCam, mask) == Approx(1.5 * std::sqrt(13.0)).epsilon(1e-6));

  // Moving only the root by d shifts the 21 other joints by -d relative to it: 21/22 |d|.
  Clip root_moved = g;
  root_moved.at(0, 0)[1] += 0.5f;  // up: visible in the image (image y = 1.5 y)
  REQUIRE(mpjpe_3d(root_moved.view(), g.view(), {0}) == Approx(21.0 / 22 * 0.5).epsilon(1e-6));
  REQUIRE(mpjpe_2d(root_moved.view(), target, kCam, {0}) == Approx(21.0 / 22 * 0.75).epsilon(1e-6));
}

TEST_CASE("lifting_metrics averages the per-sample values", "[eval]") {
  const Clip g = ground_truth();
  Clip p = g;
  p.at(1, 20)[2] += 0.2f;
  std::vector<uint8_t> controlled(T * J, 0);
  controlled[1 * J + 20] = 1;
  LiftingSample exact{g.view(), g.view(), project_motion(kCam, g.view()), kCam, {1}, mask_view(controlled, T, J, 1)};
  LiftingSample off = exact;
  off.prediction = p.view();
  const LiftingMetrics m = lifting_metrics({exact, off});
  REQUIRE(m.samples == 2);
  REQUIRE(m.mpjpe_2d == Approx((0.0 + 0.3 / 22) / 2).margin(1e-7));
  REQUIRE(m.mpjpe_3d == Approx((0.0 + 0.2 / 22) / 2).margin(1e-7));
  REQUIRE(m.avg_err_2d == Approx((0.0 + 0.3) / 2).margin(1e-7));
  REQUIRE(m.avg_err_3d == Approx((0.0 + 0.2) / 2).margin(1e-7));
}

TEST_CASE("lifting metrics reject bad input with clear messages", "[eval]") {
  const Clip g = ground_truth();
  const Keypoints2D target = project_motion(kCam, g.view());
  std::vector<uint8_t> none(T * J, 0), all(T * J, 1);
  REQUIRE_USER_ERROR(mpjpe_2d(g.view(), target, kCam, {}), "no keyframes");
  REQUIRE_USER_ERROR(mpjpe_2d(g.view(), target, kCam, {3}), "keyframe 3 is outside the 3 valid frames");
  const Clip other(T + 1, J);
  REQUIRE_USER_ERROR(mpjpe_3d(g.view(), other.view(), {0}), "prediction is [3, 22, 3] with length 3 but ground truth");
  REQUIRE_USER_ERROR(mpjpe_2d(other.view(), target, kCam, {0}), "2D target is [3, 22, 2]");
  REQUIRE_USER_ERROR(avg_err_3d(g.view(), g.view(), mask_view(none, T, J, 1)), "no controlled entries");
  std::vector<uint8_t> axes(T * J * 3, 1);
  REQUIRE_USER_ERROR(avg_err_2d(g.view(), target, kCam, mask_view(axes, T, J, 3)), "need [T, J, 1]");
  REQUIRE_USER_ERROR(lifting_metrics({}), "no samples");
}

TEST_CASE("reconstruction MPJPE pools valid frames and ignores padding", "[eval]") {
  const Clip g = ground_truth();  // 3 frames, all valid
  Clip r = g;                     // every joint off by (0.3, 0, 0.4): 0.5 m
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < J; ++j) {
      r.at(t, j)[0] += 0.3f;
      r.at(t, j)[2] += 0.4f;
    }
  Clip g2(4, J, 1), r2(4, J, 1);  // one valid frame, exact; padding differs wildly
  for (int t = 1; t < 4; ++t) r2.set(t, 5, 100.0, 100.0, 100.0);
  // Frame-weighted: (3 frames * 0.5 + 1 frame * 0) / 4 frames.
  REQUIRE(reconstruction_mpjpe({r.view(), r2.view()}, {g.view(), g2.view()}) == Approx(1.5 / 4).epsilon(1e-6));
  // A pure translation vanishes once each frame is root-aligned.
  REQUIRE(reconstruction_mpjpe({r.view()}, {g.view()}, true) == Approx(0.0).margin(1e-6));
  REQUIRE_USER_ERROR(reconstruction_mpjpe({r.view()}, {g.view(), g2.view()}), "1 reconstructions for 2");
  REQUIRE_USER_ERROR(reconstruction_mpjpe({r2.view()}, {g.view()}), "clip 0");
  REQUIRE_USER_ERROR(reconstruction_mpjpe({}, {}), "no clips");
}
