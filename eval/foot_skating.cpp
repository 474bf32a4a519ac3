// Foot skating ratio (GMD/OmniControl definition, reference-facts §5): share of
// frame transitions in which a grounded toe slides horizontally.
#include <cmath>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

namespace {

int frames_evaluated(const JointsView& clip, const FootSkatingOptions& opt) {
  if (opt.padded_196) {
    if (clip.frames < opt.padded_length)
      fail("foot skating (padded_196): the clip stores {} frames, fewer than padded_length = {}", clip.frames,
           opt.padded_length);
    return opt.padded_length;
  }
  return clip.length;
}

}  // namespace

std::vector<uint8_t> foot_skating_flags(const JointsView& clip, const std::vector<int>& toes,
                                        const FootSkatingOptions& opt) {
  if (!clip.data) fail("foot skating: clip has no data");
  if (toes.empty()) fail("foot skating: no toe joints given");
  for (int j : toes)
    if (j < 0 || j >= clip.joints) fail("foot skating: toe joint {} is outside [0, {})", j, clip.joints);
  if (opt.window < 1 || opt.window % 2 == 0)
    fail("foot skating: window must be a positive odd number of frames, got {}", opt.window);
  if (!(opt.fps > 0.0)) fail("foot skating: fps must be > 0, got {}", opt.fps);
  const int n = frames_evaluated(clip, opt);
  if (n < 2) fail("foot skating: need at least 2 frames, got {}", n);

  const int m = n - 1;  // transitions t -> t+1
  const int half = opt.window / 2;
  std::vector<uint8_t> flags(m, 0);
  std::vector<double> v(m);
  for (int j : toes) {
    // Horizontal speed v[t] = ||xz(t+1) - xz(t)|| * fps (m/s).
    for (int t = 0; t < m; ++t) {
      const Eigen::Vector3d d = clip.at(t + 1, j) - clip.at(t, j);
      v[t] = std::hypot(d.x(), d.z()) * opt.fps;
    }
    for (int t = 0; t < m; ++t) {
      // Centred moving average, zero padded, always divided by the full window
      // (scipy uniform_filter1d(size=5, mode='constant', origin=0)): the first and
      // last `half` transitions average in zeros.
      double sum = 0.0;
      for (int k = t - half; k <= t + half; ++k)
        if (k >= 0 && k < m) sum += v[k];
      const double v_avg = sum / opt.window;
      const bool grounded = clip.at(t, j).y() < opt.height_threshold && clip.at(t + 1, j).y() < opt.height_threshold;
      if (grounded && v[t] > opt.speed_threshold && v_avg > opt.avg_speed_threshold) flags[t] = 1;  // either toe
    }
  }
  return flags;
}

double foot_skating_ratio(const JointsView& clip, const std::vector<int>& toes, const FootSkatingOptions& opt) {
  const std::vector<uint8_t> flags = foot_skating_flags(clip, toes, opt);
  size_t count = 0;
  for (uint8_t f : flags) count += f;
  return static_cast<double>(count) / flags.size();  // / (T - 1), or / (padded_length - 1)
}

double foot_skating_ratio(const std::vector<JointsView>& clips, const Skeleton& skeleton,
                          const FootSkatingOptions& opt) {
  if (clips.empty()) fail("foot skating: no clips");
  const std::vector<int>& toes = skeleton.role("toes");
  double sum = 0.0;
  for (size_t i = 0; i < clips.size(); ++i) {
    if (clips[i].joints != skeleton.num_joints())
      fail("foot skating: clip {} has {} joints but skeleton '{}' has {}", i, clips[i].joints, skeleton.name,
           skeleton.num_joints());
    sum += foot_skating_ratio(clips[i], toes, opt);
  }
  return sum / clips.size();
}

}  // namespace mc
