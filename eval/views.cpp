// Checked constructors of the read-only joint and mask views the metrics take.
#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

JointsView joints_view(const std::vector<float>& data, int frames, int joints, int length, const std::string& what) {
  if (frames < 0 || joints < 1) fail("{}: invalid shape [{}, {}, 3]", what, frames, joints);
  const size_t expected = static_cast<size_t>(frames) * joints * 3;
  if (data.size() != expected)
    fail("{}: {} values do not form [{}, {}, 3] (expected {})", what, data.size(), frames, joints, expected);
  if (length < 0) length = frames;
  if (length > frames) fail("{}: length {} exceeds the {} stored frames", what, length, frames);
  return JointsView{data.data(), frames, joints, length};
}

JointsView joints_view(const MotionSet& set, size_t i) {
  if (i >= set.size()) fail("motion set has {} clips, no clip {}", set.size(), i);
  if (set.lengths[i] > set.t_max) fail("clip {}: length {} exceeds t_max {}", i, set.lengths[i], set.t_max);
  return JointsView{set.clip(i), set.t_max, set.num_joints(), set.lengths[i]};
}

MaskView mask_view(const std::vector<uint8_t>& data, int frames, int joints, int channels, const std::string& what) {
  if (frames < 0 || joints < 1 || channels < 1) fail("{}: invalid shape [{}, {}, {}]", what, frames, joints, channels);
  const size_t expected = static_cast<size_t>(frames) * joints * channels;
  if (data.size() != expected)
    fail("{}: {} values do not form [{}, {}, {}] (expected {})", what, data.size(), frames, joints, channels,
         expected);
  return MaskView{data.data(), frames, joints, channels};
}

}  // namespace mc
