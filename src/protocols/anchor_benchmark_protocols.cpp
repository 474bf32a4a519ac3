// `protocol:` types of the AnchorRoute benchmark replay: `anchors` (families x K cycled or
// crossed over clips, Tables III-VII) and `sparse_keyjoint` (Table II's six-point setting). The
// route branch's anchor_route / anchor_keyjoint (anchor_protocols.cpp) are the one-family variants.
#include <random>

#include "control/anchors.h"
#include "control/control_task.h"
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

struct AnchorsProtocol : ControlProtocol {
  std::vector<std::string> families = {"root_3d", "planar_root", "body_point"};
  std::vector<int> anchor_counts = {2, 4, 8, 16, 32};
  std::string assignment = "cycle";
  std::vector<int> body_joints = {0, 10, 11, 15, 20, 21};
  void visit(FieldVisitor& v) override {
    v("families", families, "control families (root_3d, planar_root, body_point)");
    v("anchor_counts", anchor_counts, "anchor counts K", each(at_least(1)));
    v("assignment", assignment, "cycle: clip i gets combination (family, K) i mod n; all: every clip gets every one",
      one_of({"cycle", "all"}));
    v("body_joints", body_joints, "body-point joint drawn uniformly per task from these", each(at_least(0)));
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
