// Feedback features (issue 15, ours): see anchor_feedback.h.
#include "control/anchor_feedback.h"

#include <map>

#include "core/error.h"
#include "data/features.h"
#include "data/skeleton.h"

namespace mc {

FeatureMatrix anchor_feedback_features(const AnchorSet& set, const float* estimate, int estimate_frames,
                                       const Skeleton& skeleton) {
  const int T = set.frames, J = skeleton.num_joints();
  if (estimate_frames < T)
    fail("feedback features: the estimate has {} frames, the anchor set {}", estimate_frames, T);
  FeatureMatrix out = FeatureMatrix::Zero(T, kFeedbackWidth);
  if (T == 0 || set.size() == 0) return out;
  auto est = [&](int t, int j, int a) { return static_cast<double>(estimate[(static_cast<size_t>(t) * J + j) * 3 + a]); };
  // Anchors grouped by frame (sorted ascending).
  std::map<int, std::vector<const Anchor*>> by_frame;
  for (const auto& a : set.anchors) {
    if (a.joint < 0 || a.joint >= J)
      fail("feedback features: anchor joint {} is not in the {}-joint skeleton", a.joint, J);
    if (a.frame < 0 || a.frame >= T) fail("feedback features: anchor frame {} is outside [0, {})", a.frame, T);
    by_frame[a.frame].push_back(&a);
  }
  std::vector<int> frames;
  for (auto& kv : by_frame) frames.push_back(kv.first);
  const std::vector<double> theta = facing_angles(estimate, T, skeleton);
  // Residual and bearing of anchor frame f seen from frame t, world axes.
  auto terms = [&](int f, int t, double res[3], double bear[3]) {
    const auto& as = by_frame.at(f);
    for (int k = 0; k < 3; ++k) res[k] = bear[k] = 0.0;
    for (const Anchor* a : as)
      for (int k = 0; k < 3; ++k) {
        const double target = a->axes[k] ? a->value[k] : est(f, a->joint, k);
        res[k] += a->axes[k] ? a->value[k] - est(f, a->joint, k) : 0.0;
        bear[k] += target - est(t, a->joint, k);
      }
    for (int k = 0; k < 3; ++k) {
      res[k] /= static_cast<double>(as.size());
      bear[k] /= static_cast<double>(as.size());
    }
  };
  auto put = [&](int t, int col, const double v[3]) {
    double x, z;
    to_facing_frame(theta[t], v[0], v[2], x, z);
    out(t, col) = static_cast<float>(x);
    out(t, col + 1) = static_cast<float>(v[1]);
    out(t, col + 2) = static_cast<float>(z);
  };
  size_t next = 0;  // index of the first anchor frame >= t
  for (int t = 0; t < T; ++t) {
    while (next < frames.size() && frames[next] < t) ++next;
    double res[3], bear[3];
    if (next < frames.size()) {
      const int f = frames[next];
      terms(f, t, res, bear);
      put(t, 0, res);
      put(t, 3, bear);
      out(t, 6) = static_cast<float>((f - t) / kPathFrameRate);
      out(t, 7) = 1.0f;
      if (f == t) out(t, 16) = 1.0f;
    }
    const bool at = next < frames.size() && frames[next] == t;
    const long prev = at ? static_cast<long>(next) : static_cast<long>(next) - 1;
    if (prev >= 0) {
      const int f = frames[prev];
      terms(f, t, res, bear);
      put(t, 8, res);
      put(t, 11, bear);
      out(t, 14) = static_cast<float>((t - f) / kPathFrameRate);
      out(t, 15) = 1.0f;
    }
  }
  return out;
}

}  // namespace mc
