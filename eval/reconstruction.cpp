// Tokenizer reconstruction error: MPJPE in metres over the valid frames.
#include "core/error.h"
#include "eval/metrics.h"

namespace mc {

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
