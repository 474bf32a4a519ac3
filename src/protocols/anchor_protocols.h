// AnchorRoute's benchmark protocols as `protocol:` components: the main sparse-anchor
// protocol (one family, K in {2, 4, 8, 16, 32}) and Table II's six-point keyjoint protocol.
// Tasks carry their anchors as constraint specs (anchors_to_spec), so every method reads them.
#pragma once
#include <string>
#include <vector>

#include "control/control_task.h"

namespace mc {

// protocol: {type: anchor_route, family: root_3d, anchor_counts: [2, 4, 8, 16, 32]}
// One task per clip and K ("<clip id>#K<k>", group "family=<f>/K=<k>"); the anchors of a
// task are drawn by draw_anchor_set from a generator seeded by (seed, clip index, K).
struct AnchorRouteProtocol : ControlProtocol {
  std::string family = "root_3d";
  std::vector<int> anchor_counts = {2, 4, 8, 16, 32};
  std::vector<int> body_joints = {0, 10, 11, 15, 20, 21};
  void visit(FieldVisitor& v) override {
    v("family", family, "anchor family: root_3d, planar_root or body_point",
      one_of({"root_3d", "planar_root", "body_point"}));
    v("anchor_counts", anchor_counts, "anchor counts K; one task per clip and K (results averaged over K)",
      each(at_least(1)));
    v("body_joints", body_joints, "body_point: candidate joints, one drawn per task", each(at_least(0)));
  }
  std::string validate() const override {
    if (anchor_counts.empty()) return "anchor_counts must not be empty";
    if (family == "body_point" && body_joints.empty()) return "body_joints must not be empty for body_point";
    return "";
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override;
};

// protocol: {type: anchor_keyjoint}: joints [0, 10, 11, 15, 20, 21] in xyz at the same
// round(0.3 T) random frames ("all6-r30", our reading; docs/choices.md). One task per clip.
struct AnchorKeyjointProtocol : ControlProtocol {
  double frame_ratio = 0.3;
  std::vector<int> joints = {0, 10, 11, 15, 20, 21};
  void visit(FieldVisitor& v) override {
    v("frame_ratio", frame_ratio, "fraction of frames that carry the keyjoints", in_range(1e-6, 1.0));
    v("joints", joints, "controlled joints (all at every keyframe)", each(at_least(0)));
  }
  std::string validate() const override { return joints.empty() ? "joints must not be empty" : ""; }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override;
};

}  // namespace mc
