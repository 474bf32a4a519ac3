// Evaluator-free motion realism: mean |acceleration|, bone-length drift over time and
// toe floor penetration. Physical defects a distribution metric (FID) can hide at
// small N; the prior health check reads them beside the ground truth's values.
#include <cmath>

#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

namespace {

void check_clip(const JointsView& clip, const char* what) {
  if (!clip.data) fail("{}: clip has no data", what);
  if (clip.length < 0 || clip.length > clip.frames)
    fail("{}: length {} is outside the {} stored frames", what, clip.length, clip.frames);
}

}  // namespace

double mean_abs_acceleration(const JointsView& clip, double fps) {
  check_clip(clip, "mean_abs_acceleration");
  if (!(fps > 0.0)) fail("mean_abs_acceleration: fps must be > 0, got {}", fps);
  if (clip.length < 3) fail("mean_abs_acceleration: need at least 3 valid frames, got {}", clip.length);
  double sum = 0.0;
  for (int t = 1; t + 1 < clip.length; ++t)
    for (int j = 0; j < clip.joints; ++j)
      sum += (clip.at(t + 1, j) - 2.0 * clip.at(t, j) + clip.at(t - 1, j)).norm();
  // Second difference over a frame step of 1 / fps: divide by (1 / fps)^2.
  return sum / (static_cast<double>(clip.length - 2) * clip.joints) * fps * fps;
}

double mean_abs_acceleration(const std::vector<JointsView>& clips, double fps) {
  double sum = 0.0;
  int n = 0;
  for (const auto& c : clips) {
    check_clip(c, "mean_abs_acceleration");
    if (c.length < 3) continue;  // no interior frame
    sum += mean_abs_acceleration(c, fps);
    ++n;
  }
  if (n == 0) fail("mean_abs_acceleration: none of the {} clips has 3 valid frames", clips.size());
  return sum / n;
}

double bone_length_std_mm(const JointsView& clip, const Skeleton& skeleton) {
  check_clip(clip, "bone_length_std_mm");
  if (clip.joints != skeleton.num_joints())
    fail("bone_length_std_mm: clip has {} joints, skeleton '{}' has {}", clip.joints, skeleton.name,
         skeleton.num_joints());
  if (clip.length < 1) fail("bone_length_std_mm: clip has no valid frame");
  double sum = 0.0;
  int bones = 0;
  for (int j = 0; j < clip.joints; ++j) {
    const int p = skeleton.parents[j];
    if (p < 0) continue;
    // Two-pass population variance: lengths are ~0.1-0.5 m and their drift can be
    // micrometres, where sum(x^2) - n mean^2 would cancel catastrophically.
    double mean = 0.0;
    for (int t = 0; t < clip.length; ++t) mean += (clip.at(t, j) - clip.at(t, p)).norm();
    mean /= clip.length;
    double var = 0.0;
    for (int t = 0; t < clip.length; ++t) {
      const double d = (clip.at(t, j) - clip.at(t, p)).norm() - mean;
      var += d * d;
    }
    sum += std::sqrt(var / clip.length);
    ++bones;
  }
  if (bones == 0) fail("bone_length_std_mm: skeleton '{}' has no bones", skeleton.name);
  return sum / bones * 1000.0;
}

double bone_length_std_mm(const std::vector<JointsView>& clips, const Skeleton& skeleton) {
  if (clips.empty()) fail("bone_length_std_mm: no clips");
  double sum = 0.0;
  for (const auto& c : clips) sum += bone_length_std_mm(c, skeleton);
  return sum / clips.size();
}

FloorPenetration toe_floor_penetration(const std::vector<JointsView>& clips, const Skeleton& skeleton) {
  if (clips.empty()) fail("toe_floor_penetration: no clips");
  const std::vector<int>& toes = skeleton.role("toes");
  if (toes.empty()) fail("toe_floor_penetration: skeleton '{}' has an empty 'toes' role", skeleton.name);
  FloorPenetration out;
  int64_t frames = 0, below = 0;
  for (const auto& c : clips) {
    check_clip(c, "toe_floor_penetration");
    for (int j : toes)
      if (j < 0 || j >= c.joints) fail("toe_floor_penetration: toe joint {} is outside [0, {})", j, c.joints);
    if (c.length < 1) fail("toe_floor_penetration: a clip has no valid frame");
    double lowest = INFINITY;
    for (int t = 0; t < c.length; ++t) {
      bool any_below = false;
      for (int j : toes) {
        const double y = c.at(t, j).y();
        lowest = std::min(lowest, y);
        any_below = any_below || y < 0.0;
      }
      below += any_below;
    }
    frames += c.length;
    out.depth += std::max(0.0, -lowest);
  }
  out.depth /= clips.size();
  out.frame_fraction = static_cast<double>(below) / static_cast<double>(frames);
  return out;
}

}  // namespace mc
