// 2D-to-3D lifting metrics (Sketch2Anim protocol, reference-facts §3 and §5):
// root-aligned MPJPE in 2D and 3D over keypose frames, Avg.Err over controlled entries.
#include <cmath>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

namespace {

void check_motion(const JointsView& m, const char* what) {
  if (!m.data) fail("{}: no data", what);
}

void check_same_shape(const JointsView& a, const JointsView& b, const char* what) {
  check_motion(a, what);
  check_motion(b, what);
  if (a.frames != b.frames || a.joints != b.joints || a.length != b.length)
    fail("{}: prediction is [{}, {}, 3] with length {} but ground truth is [{}, {}, 3] with length {}", what,
         a.frames, a.joints, a.length, b.frames, b.joints, b.length);
}

void check_target(const JointsView& pred, const Keypoints2D& target, const char* what) {
  check_motion(pred, what);
  if (target.frames != pred.frames || target.joints != pred.joints ||
      target.xy.size() != static_cast<size_t>(target.frames) * target.joints * 2)
    fail("{}: prediction is [{}, {}, 3] but the 2D target is [{}, {}, 2] with {} values", what, pred.frames,
         pred.joints, target.frames, target.joints, target.xy.size());
}

void check_keyframes(const JointsView& pred, const std::vector<int>& keyframes, int root, const char* what) {
  if (keyframes.empty()) fail("{}: no keyframes", what);
  for (int t : keyframes)
    if (t < 0 || t >= pred.length) fail("{}: keyframe {} is outside the {} valid frames", what, t, pred.length);
  if (root < 0 || root >= pred.joints) fail("{}: root joint {} is outside [0, {})", what, root, pred.joints);
}

void check_mask(const JointsView& pred, const MaskView& m, const char* what) {
  if (!m.data || m.frames != pred.frames || m.joints != pred.joints || m.channels != 1)
    fail("{}: prediction is [{}, {}, 3] but the controlled-entry mask is [{}, {}, {}] (need [T, J, 1])", what,
         pred.frames, pred.joints, m.frames, m.joints, m.channels);
}

}  // namespace

Keypoints2D project_motion(const OrthoCamera& camera, const JointsView& motion) {
  check_motion(motion, "project_motion");
  Keypoints2D k;
  k.frames = motion.frames;
  k.joints = motion.joints;
  k.xy.resize(static_cast<size_t>(k.frames) * k.joints * 2);
  const Eigen::Matrix<double, 2, 3> p = camera.matrix();
  for (int t = 0; t < k.frames; ++t)
    for (int j = 0; j < k.joints; ++j) {
      const Eigen::Vector2d y = p * motion.at(t, j);
      const size_t o = (static_cast<size_t>(t) * k.joints + j) * 2;
      k.xy[o] = y.x();
      k.xy[o + 1] = y.y();
    }
  return k;
}

double mpjpe_2d(const JointsView& prediction, const Keypoints2D& target, const OrthoCamera& camera,
                const std::vector<int>& keyframes, int root) {
  check_target(prediction, target, "mpjpe_2d");
  check_keyframes(prediction, keyframes, root, "mpjpe_2d");
  const Eigen::Matrix<double, 2, 3> p = camera.matrix();
  double sum = 0.0;
  for (int t : keyframes) {
    const Eigen::Vector2d pr = p * prediction.at(t, root), tr = target.at(t, root);
    for (int j = 0; j < prediction.joints; ++j)
      sum += ((p * prediction.at(t, j) - pr) - (target.at(t, j) - tr)).norm();
  }
  return sum / (static_cast<double>(keyframes.size()) * prediction.joints);
}

double mpjpe_3d(const JointsView& prediction, const JointsView& ground_truth, const std::vector<int>& keyframes,
                int root) {
  check_same_shape(prediction, ground_truth, "mpjpe_3d");
  check_keyframes(prediction, keyframes, root, "mpjpe_3d");
  double sum = 0.0;
  for (int t : keyframes) {
    const Eigen::Vector3d pr = prediction.at(t, root), gr = ground_truth.at(t, root);
    for (int j = 0; j < prediction.joints; ++j)
      sum += ((prediction.at(t, j) - pr) - (ground_truth.at(t, j) - gr)).norm();
  }
  return sum / (static_cast<double>(keyframes.size()) * prediction.joints);
}

double avg_err_2d(const JointsView& prediction, const Keypoints2D& target, const OrthoCamera& camera,
                  const MaskView& controlled) {
  check_target(prediction, target, "avg_err_2d");
  check_mask(prediction, controlled, "avg_err_2d");
  const Eigen::Matrix<double, 2, 3> p = camera.matrix();
  double sum = 0.0;
  size_t n = 0;
  for (int t = 0; t < prediction.frames; ++t)
    for (int j = 0; j < prediction.joints; ++j) {
      if (!controlled.at(t, j)) continue;
      if (t >= prediction.length) fail("avg_err_2d: controlled frame {} is beyond length {}", t, prediction.length);
      sum += (p * prediction.at(t, j) - target.at(t, j)).norm();  // not root-aligned
      ++n;
    }
  if (n == 0) fail("avg_err_2d: no controlled entries");
  return sum / n;
}

double avg_err_3d(const JointsView& prediction, const JointsView& ground_truth, const MaskView& controlled) {
  check_same_shape(prediction, ground_truth, "avg_err_3d");
  check_mask(prediction, controlled, "avg_err_3d");
  double sum = 0.0;
  size_t n = 0;
  for (int t = 0; t < prediction.frames; ++t)
    for (int j = 0; j < prediction.joints; ++j) {
      if (!controlled.at(t, j)) continue;
      if (t >= prediction.length) fail("avg_err_3d: controlled frame {} is beyond length {}", t, prediction.length);
      sum += (prediction.at(t, j) - ground_truth.at(t, j)).norm();
      ++n;
    }
  if (n == 0) fail("avg_err_3d: no controlled entries");
  return sum / n;
}

LiftingMetrics lifting_metrics(const std::vector<LiftingSample>& samples, int root) {
  if (samples.empty()) fail("lifting_metrics: no samples");
  LiftingMetrics r;
  for (const LiftingSample& s : samples) {
    r.mpjpe_2d += mpjpe_2d(s.prediction, s.target_2d, s.camera, s.keyframes, root);
    r.mpjpe_3d += mpjpe_3d(s.prediction, s.ground_truth, s.keyframes, root);
    r.avg_err_2d += avg_err_2d(s.prediction, s.target_2d, s.camera, s.controlled);
    r.avg_err_3d += avg_err_3d(s.prediction, s.ground_truth, s.controlled);
  }
  r.samples = static_cast<int>(samples.size());
  r.mpjpe_2d /= r.samples;
  r.mpjpe_3d /= r.samples;
  r.avg_err_2d /= r.samples;
  r.avg_err_3d /= r.samples;
  return r;
}

}  // namespace mc
