// Checked joint views and the tokenizer reconstruction error (MPJPE in metres over
// the valid frames).
#include "data/joints_view.h"

#include "core/error.h"

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

double reconstruction_mpjpe(const std::vector<JointsView>& reconstruction, const std::vector<JointsView>& ground_truth,
                            bool root_aligned, int root) {
  if (ground_truth.empty()) fail("reconstruction_mpjpe: no clips");
  if (reconstruction.size() != ground_truth.size())
    fail("reconstruction_mpjpe: {} reconstructions for {} ground-truth clips", reconstruction.size(),
         ground_truth.size());
  double sum = 0.0;
  size_t n = 0;
  for (size_t i = 0; i < ground_truth.size(); ++i) {
    const JointsView& r = reconstruction[i];
    const JointsView& g = ground_truth[i];
    if (!r.data || !g.data) fail("reconstruction_mpjpe: clip {} has no data", i);
    if (r.joints != g.joints || r.length != g.length)
      fail("reconstruction_mpjpe: clip {}: reconstruction has {} joints x {} valid frames, ground truth {} x {}", i,
           r.joints, r.length, g.joints, g.length);
    if (root < 0 || root >= g.joints) fail("reconstruction_mpjpe: root joint {} is outside [0, {})", root, g.joints);
    for (int t = 0; t < g.length; ++t) {
      const Eigen::Vector3d ro = root_aligned ? r.at(t, root) : Eigen::Vector3d::Zero();
      const Eigen::Vector3d go = root_aligned ? g.at(t, root) : Eigen::Vector3d::Zero();
      for (int j = 0; j < g.joints; ++j) sum += ((r.at(t, j) - ro) - (g.at(t, j) - go)).norm();
      n += g.joints;
    }
  }
  if (n == 0) fail("reconstruction_mpjpe: no valid frames");
  return sum / n;
}

}  // namespace mc
