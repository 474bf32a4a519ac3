// `protocol:` types of the AnchorRoute benchmark replay: `anchors` (families x K cycled or
// crossed over clips, Tables III-VII) and `sparse_keyjoint` (Table II's six-point setting). The
// route branch's anchor_route / anchor_keyjoint (anchor_protocols.cpp) are the one-family variants.
#include <random>
#include <set>

#include "control/anchors.h"
#include "control/control_task.h"
#include "control/directions.h"
#include "core/error.h"
#include "data/fixture/rng.h"
#include "data/motion_set.h"

namespace mc {
namespace {

ControlTask anchor_task(const MotionSet& data, size_t c, size_t index) {
  if (c >= data.size()) fail("protocol: clip index {} is outside the data ({} clips)", c, data.size());
  ControlTask t;
  t.clip_id = data.ids[c];
  t.id = data.ids[c] + "#" + std::to_string(index);
  t.caption = data.captions[c].front();
  t.length = data.lengths[c];
  const size_t per_frame = static_cast<size_t>(data.num_joints()) * 3;
  t.source.assign(data.clip(c), data.clip(c) + t.length * per_frame);
  return t;
}

// Each task draws from its own engine, so a task does not depend on the others.
std::mt19937_64 task_rng(uint64_t seed, size_t index) {
  return std::mt19937_64(fixture::mix_seed(seed ^ (0x9E3779B97F4A7C15ull * (index + 1))));
}

void check_joints(const MotionSet& data, const std::vector<int>& joints, const std::string& key) {
  for (int j : joints)
    if (j < 0 || j >= data.num_joints())
      fail("protocol.{}: joint {} is outside the skeleton's 0..{}", key, j, data.num_joints() - 1);
}

// `protocol.directions:` (issue 20): direction cues drawn from the ground truth at the
// anchor frames, as tangent and facing items with explicit values. A tangent is drawn
// only where the anchored joint moves (speed >= 2 min_speed on the tangent's axes),
// not all of its velocity stencil's frames are anchored (that row would repeat the
// anchors') and its stencil shares no frame with an earlier tangent's; a facing only
// where the hips are apart (forward length >= 2 min_width). The ground truth therefore
// meets every drawn row and no row repeats another. score_only: the
// same items measured but not imposed, the plain counterpart on the same tasks.
// Left out of the dumped config while both kinds are off.
struct AnchorDirectionsConfig : Config {
  bool tangent = false;
  bool facing = false;
  bool score_only = false;
  std::vector<int> tangent_axes = {0, 2};
  double min_speed = 0.01;
  double min_width = 0.05;
  void visit(FieldVisitor& v) override {
    v("tangent", tangent, "a tangent item (velocity direction of the anchored joint) at the anchor frames");
    v("facing", facing, "a facing item (body forward from the hips) at the anchor frames");
    v("score_only", score_only, "measure the items (direction_error) without imposing them");
    v("tangent_axes", tangent_axes, "axes of the tangent (0 x, 1 y, 2 z; default xz: the heading)",
      each(in_range(0, 2)));
    v("min_speed", min_speed, "tangent sense row: speed along the direction >= this (metres per frame)",
      at_least(0.0));
    v("min_width", min_width, "facing sense row: hip-difference component >= this (metres)", at_least(0.0));
  }
  std::string validate() const override {
    if (tangent_axes.empty()) return "protocol.directions.tangent_axes is empty";
    return "";
  }
  bool omitted_from_dump() const override { return !tangent && !facing; }
  bool any() const { return tangent || facing; }

  // The items for one task's anchors (values from its source clip).
  std::vector<ConstraintItem> items(const AnchorSet& set, const ControlTask& t, const MotionSet& data) const {
    std::vector<ConstraintItem> out;
    const int J = data.num_joints(), T = t.length;
    const float* gt = t.source.data();
    if (tangent && T >= 2) {
      for (int joint : set.joints()) {
        std::set<int> pinned;  // frames where the anchors pin every tangent axis of this joint
        for (const auto& a : set.anchors) {
          bool all = a.joint == joint;
          for (int c : tangent_axes) all = all && a.axes[c];
          if (all) pinned.insert(a.frame);
        }
        ConstraintItem it;
        it.type = "tangent";
        it.name = fmt::format("heading of joint {}", joint);
        it.joints = {JointRef{joint, ""}};
        it.axes = tangent_axes;
        it.min_speed = min_speed;
        it.score_only = score_only;
        it.frames.kind = FrameSelection::Kind::list;
        std::set<int> used;  // stencil frames of the tangents drawn so far
        for (const auto& a : set.anchors) {
          if (a.joint != joint) continue;
          bool free = false, overlaps = false;
          for (auto [f, w] : tangent_stencil(a.frame, T)) {
            free = free || !pinned.count(f);
            overlaps = overlaps || used.count(f);
          }
          Eigen::VectorXd v = joint_velocity(gt, T, J, joint, a.frame, tangent_axes);
          // Disjoint stencils keep every drawn row independent of the others and of the
          // anchors (two parallel headings sharing a frame would repeat each other).
          if (!free || overlaps || !(v.norm() >= 2 * min_speed)) continue;
          for (auto [f, w] : tangent_stencil(a.frame, T)) used.insert(f);
          it.frames.list.push_back(a.frame);
          for (Eigen::Index k = 0; k < v.size(); ++k) it.values.data.push_back(v[k] / v.norm());
        }
        if (it.frames.list.empty()) continue;
        it.values.shape = {static_cast<int>(it.frames.list.size()), static_cast<int>(tangent_axes.size())};
        out.push_back(std::move(it));
      }
    }
    if (facing) {
      const auto& face = data.skeleton.role("face");
      if (face.size() < 2) fail("protocol.directions.facing: the skeleton's 'face' role needs the two hips");
      ConstraintItem it;
      it.type = "facing";
      it.name = "facing";
      it.joints = {JointRef{face[0], ""}, JointRef{face[1], ""}};
      it.min_width = min_width;
      it.score_only = score_only;
      it.frames.kind = FrameSelection::Kind::list;
      for (int f : set.times()) {
        Eigen::Vector2d fw = body_forward(gt, J, face[0], face[1], f);
        if (!(fw.norm() >= 2 * min_width)) continue;
        it.frames.list.push_back(f);
        it.values.data.push_back(fw[0] / fw.norm());
        it.values.data.push_back(fw[1] / fw.norm());
      }
      if (!it.frames.list.empty()) {
        it.values.shape = {static_cast<int>(it.frames.list.size()), 2};
        out.push_back(std::move(it));
      }
    }
    return out;
  }
};

struct AnchorsProtocol : ControlProtocol {
  std::vector<std::string> families = {"root_3d", "planar_root", "body_point"};
  std::vector<int> anchor_counts = {2, 4, 8, 16, 32};
  std::string assignment = "cycle";
  std::vector<int> body_joints = {0, 10, 11, 15, 20, 21};
  AnchorDirectionsConfig directions;
  void visit(FieldVisitor& v) override {
    v("families", families, "control families (root_3d, planar_root, body_point)");
    v("anchor_counts", anchor_counts, "anchor counts K", each(at_least(1)));
    v("assignment", assignment, "cycle: clip i gets combination (family, K) i mod n; all: every clip gets every one",
      one_of({"cycle", "all"}));
    v("body_joints", body_joints, "body-point joint drawn uniformly per task from these", each(at_least(0)));
    v("directions", directions, "tangent / facing cues from the ground truth at the anchor frames (issue 20)");
  }
  std::string validate() const override {
    if (families.empty()) return "protocol.families is empty";
    for (auto& f : families) parse_anchor_family(f, "protocol.families");
    if (anchor_counts.empty()) return "protocol.anchor_counts is empty";
    if (body_joints.empty()) return "protocol.body_joints is empty";
    return "";
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override {
    check_joints(data, body_joints, "body_joints");
    std::vector<std::pair<AnchorFamily, int>> combos;
    for (auto& f : families)
      for (int k : anchor_counts) combos.push_back({parse_anchor_family(f, "protocol.families"), k});
    std::vector<std::pair<size_t, std::pair<AnchorFamily, int>>> work;
    for (size_t i = 0; i < clips.size(); ++i) {
      if (assignment == "all")
        for (auto& c : combos) work.push_back({clips[i], c});
      else
        work.push_back({clips[i], combos[i % combos.size()]});
    }
    std::vector<ControlTask> out;
    for (auto& [c, combo] : work) {
      ControlTask t = anchor_task(data, c, out.size());
      auto [family, K] = combo;
      if (K > t.length)
        fail("protocol anchors: K = {} anchors do not fit clip '{}' of {} frames; lower protocol.anchor_counts", K,
             t.clip_id, t.length);
      auto rng = task_rng(seed, out.size());
      AnchorSet set = draw_anchor_set(family, K, t.source.data(), t.length, data.num_joints(), rng, body_joints);
      t.spec = anchors_to_spec(set, "anchors protocol (" + t.id + ")");
      if (directions.any())
        for (auto& item : directions.items(set, t, data)) t.spec.items.push_back(std::move(item));
      t.group = fmt::format("family={}/K={}", family_name(family), K);
      out.push_back(std::move(t));
    }
    return out;
  }
};
MC_REGISTER_PROTOCOL("anchors", AnchorsProtocol,
                     "AnchorRoute sparse anchors: family (root_3d | planar_root | body_point) x K, values from the clip");

struct SparseKeyjointProtocol : ControlProtocol {
  double ratio = 0.3;
  std::vector<int> joints = {0, 10, 11, 15, 20, 21};
  void visit(FieldVisitor& v) override {
    v("ratio", ratio, "fraction of frames controlled (all joints at the same frames)", in_range(1e-6, 1.0));
    v("joints", joints, "controlled joints (SFControl's six: pelvis, feet, head, wrists)", each(at_least(0)));
  }
  std::string validate() const override { return joints.empty() ? "protocol.joints is empty" : ""; }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override {
    check_joints(data, joints, "joints");
    std::vector<ControlTask> out;
    for (size_t c : clips) {
      ControlTask t = anchor_task(data, c, out.size());
      auto rng = task_rng(seed, out.size());
      AnchorSet set = draw_sparse_keyjoint_set(t.source.data(), t.length, data.num_joints(), rng, ratio, joints);
      t.spec = anchors_to_spec(set, "sparse_keyjoint protocol (" + t.id + ")");
      t.group = fmt::format("sparse_keyjoint/ratio={:g}", ratio);
      out.push_back(std::move(t));
    }
    return out;
  }
};
MC_REGISTER_PROTOCOL("sparse_keyjoint", SparseKeyjointProtocol,
                     "Table II six-point sparse keyjoint control: all joints at round(ratio T) shared frames");

}  // namespace
}  // namespace mc
