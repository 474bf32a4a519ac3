// Feedback features (issue 15, ours): see anchor_feedback.h.
#include "control/anchor_feedback.h"

#include <cmath>
#include <cstdlib>
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
  // One side's block: residual, bearing, |f - t| in seconds and a presence flag from column `col`.
  auto side = [&](int f, int t, int col) {
    double res[3], bear[3];
    terms(f, t, res, bear);
    put(t, col, res);
    put(t, col + 3, bear);
    out(t, col + 6) = static_cast<float>(std::abs(f - t) / kPathFrameRate);
    out(t, col + 7) = 1.0f;
  };
  size_t next = 0;  // index of the first anchor frame >= t
  for (int t = 0; t < T; ++t) {
    while (next < frames.size() && frames[next] < t) ++next;
    const bool at = next < frames.size() && frames[next] == t;
    if (next < frames.size()) side(frames[next], t, 0);
    const long prev = at ? static_cast<long>(next) : static_cast<long>(next) - 1;
    if (prev >= 0) side(frames[prev], t, 8);
    if (at) out(t, 16) = 1.0f;
  }
  return out;
}

}  // namespace mc
