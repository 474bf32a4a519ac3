// `protocol:` types of the spatial-control experiments: OmniControl keyframe /
// trajectory inpainting, Sketch2Anim 2D-to-3D lifting, and ProjFlow's other
// applications (upper-body editing, relative body-part control, loop closure).
// Every task is a ConstraintSpec over the ground-truth clip (from_source targets),
// so the same tasks drive every method and the metrics.
#include <algorithm>
#include <cmath>
#include <random>

#include "control/camera.h"
#include "control/control_task.h"
#include "core/error.h"
#include "data/fixture/rng.h"
#include "data/motion_set.h"

namespace mc {
namespace {
using fixture::Rng;
using fixture::mix_seed;

ControlTask base_task(const MotionSet& data, size_t c, const std::string& suffix) {
  if (c >= data.size()) fail("protocol: clip index {} is outside the data ({} clips)", c, data.size());
  ControlTask t;
  t.clip_id = data.ids[c];
  t.id = suffix.empty() ? data.ids[c] : data.ids[c] + "#" + suffix;
  t.caption = data.captions[c].front();
  t.length = data.lengths[c];
  const size_t per_frame = static_cast<size_t>(data.num_joints()) * 3;
  t.source.assign(data.clip(c), data.clip(c) + t.length * per_frame);
  return t;
}

// `count` distinct sorted frames of 0..T-1 drawn without replacement.
std::vector<int> draw_frames(Rng& rng, int T, int count) {
  std::vector<int> all(T);
  for (int i = 0; i < T; ++i) all[i] = i;
  count = std::clamp(count, 1, T);
  for (int i = 0; i < count; ++i) std::swap(all[i], all[rng.integer(i, T - 1)]);
  std::vector<int> out(all.begin(), all.begin() + count);
  std::sort(out.begin(), out.end());
  return out;
}

// A density is a keyframe count or a fraction of the frames. OmniControl's 1, 2, 5,
// 25%, 100% are counts [1, 2, 5] and fractions [0.25, 1.0]; at T = 196 the
// fractions give 49 and 196 frames.
struct Density {
  int count = 0;          // > 0: this many frames
  double fraction = 0.0;  // else this fraction of the frames (at least one)
  // Fractions floor, as OmniControl's int(length * ratio) does (49 of 196 frames at 25%,
  // 24 of 99 where rounding gave 25); at least one frame.
  int frames(int T) const { return count > 0 ? std::min(count, T) : std::max(1, static_cast<int>(fraction * T)); }
  std::string label() const { return count > 0 ? std::to_string(count) : fmt::format("{:g}%", fraction * 100); }
};
std::vector<Density> densities_of(const std::vector<int>& counts, const std::vector<double>& fractions) {
  std::vector<Density> d;
  for (int c : counts) d.push_back({c, 0.0});
  for (double f : fractions) d.push_back({0, f});
  return d;
}

// Combinations (joint set, density) of one protocol; `cycle` gives clip i the
// combination i mod n, `all` gives every clip every combination.
struct Combination {
  std::vector<int> joints;
  Density density;
  std::string group;
};

std::vector<std::pair<size_t, Combination>> assign(const std::vector<size_t>& clips,
                                                   const std::vector<Combination>& combos,
                                                   const std::string& assignment) {
  std::vector<std::pair<size_t, Combination>> out;
  for (size_t i = 0; i < clips.size(); ++i) {
    if (assignment == "all")
      for (auto& c : combos) out.push_back({clips[i], c});
    else
      out.push_back({clips[i], combos[i % combos.size()]});
  }
  return out;
}

std::string joint_group(const MotionSet& data, const std::vector<int>& joints) {
  std::string s;
  for (int j : joints) s += (s.empty() ? "" : "+") + data.skeleton.joint_names[j];
  return s;
}

void check_joints(const MotionSet& data, const std::vector<int>& joints, const std::string& key) {
  for (int j : joints)
    if (j < 0 || j >= data.num_joints())
      fail("protocol.{}: joint {} is outside the skeleton's 0..{}", key, j, data.num_joints() - 1);
}

// ---------------------------------------------------------------- OmniControl

struct OmniControlProtocol : ControlProtocol {
  std::vector<int> joints = {0, 10, 11, 15, 20, 21};
  std::vector<int> keyframe_counts = {1, 2, 5};
  std::vector<double> fractions = {0.25, 1.0};
  std::string mode = "each";  // each: one joint per task; cross: a random subset of `joints` per task
  std::string assignment = "cycle";
  std::vector<int> axes = {0, 1, 2};
  void visit(FieldVisitor& v) override {
    v("joints", joints, "controlled joints (OmniControl: pelvis, feet, head, wrists)", each(at_least(0)));
    v("keyframe_counts", keyframe_counts, "densities given as keyframe counts (1, 2, 5)", each(at_least(1)));
    v("fractions", fractions, "densities given as fractions of the frames (0.25, 1.0 = 49 and 196 at T = 196)",
      each(in_range(1e-6, 1.0)));
    v("mode", mode, "each: one joint per task (Average); cross: a random non-empty subset per task (Cross)",
      one_of({"each", "cross"}));
    v("assignment", assignment, "cycle: clip i gets combination i mod n; all: every clip gets every combination",
      one_of({"cycle", "all"}));
    v("axes", axes, "controlled axes (0 x, 1 y, 2 z)", each(in_range(0, 2)));
  }
  std::string validate() const override {
    if (joints.empty()) return "protocol.joints is empty";
    if (keyframe_counts.empty() && fractions.empty()) return "give at least one keyframe count or fraction";
    if (axes.empty()) return "protocol.axes is empty";
    return "";
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override {
    check_joints(data, joints, "joints");
    std::vector<Combination> combos;
    for (const Density& d : densities_of(keyframe_counts, fractions)) {
      if (mode == "each") {
        for (int j : joints)
          combos.push_back({{j}, d, fmt::format("joint={}/density={}", data.skeleton.joint_names[j], d.label())});
      } else {
        combos.push_back({{}, d, fmt::format("density={}", d.label())});
      }
    }
    std::vector<ControlTask> out;
    Rng rng(seed);
    for (auto& [c, combo] : assign(clips, combos, assignment)) {
      ControlTask t = base_task(data, c, fmt::format("{}", out.size()));
      std::vector<int> js = combo.joints;
      if (js.empty()) {  // cross: each joint with probability 1/2, at least one
        for (int j : joints)
          if (rng.chance(0.5)) js.push_back(j);
        if (js.empty()) js.push_back(joints[rng.integer(0, static_cast<int>(joints.size()) - 1)]);
      }
      ConstraintItem item;
      item.type = "keyframe";
      item.name = "omnicontrol " + joint_group(data, js) + " " + combo.density.label();
      for (int j : js) item.joints.push_back(JointRef{j, ""});
      item.frames.kind = FrameSelection::Kind::list;
      item.frames.list = draw_frames(rng, t.length, combo.density.frames(t.length));
      item.axes = axes;
      item.from_source = true;
      t.spec.items.push_back(item);
      t.spec.source = "omnicontrol protocol (" + t.id + ")";
      t.group = combo.group;
      out.push_back(std::move(t));
    }
    return out;
  }
};
MC_REGISTER_PROTOCOL("omnicontrol", OmniControlProtocol,
                     "OmniControl keyframe/trajectory inpainting: joints x densities, targets from the clip");

// ---------------------------------------------------------------- Sketch2Anim lifting

struct LiftingProtocol : ControlProtocol {
  std::vector<int> joints = {0, 10, 11, 15, 20, 21};
  std::vector<int> keyframe_counts = {1, 2, 5};
  std::vector<double> fractions = {0.25, 1.0};
  std::vector<int> keypose_frames = {0};
  std::string mode = "each";
  std::string assignment = "cycle";
  void visit(FieldVisitor& v) override {
    v("joints", joints, "joints whose 2D trajectory is given", each(at_least(0)));
    v("keyframe_counts", keyframe_counts, "trajectory densities as frame counts", each(at_least(1)));
    v("fractions", fractions, "trajectory densities as fractions of the frames", each(in_range(1e-6, 1.0)));
    v("keypose_frames", keypose_frames, "frames with a full 2D keypose (all joints); negative = from the end");
    v("mode", mode, "each: one trajectory joint per task (Average); cross: a random subset (Cross)",
      one_of({"each", "cross"}));
    v("assignment", assignment, "cycle or all (as in omnicontrol)", one_of({"cycle", "all"}));
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override {
    check_joints(data, joints, "joints");
    std::vector<Combination> combos;
    for (const Density& d : densities_of(keyframe_counts, fractions)) {
      if (mode == "each")
        for (int j : joints)
          combos.push_back({{j}, d, fmt::format("joint={}/density={}", data.skeleton.joint_names[j], d.label())});
      else
        combos.push_back({{}, d, fmt::format("density={}", d.label())});
    }
    std::vector<ControlTask> out;
    Rng rng(seed);
    std::mt19937_64 cam_rng(mix_seed(seed ^ 0xca3e7au));
    for (auto& [c, combo] : assign(clips, combos, assignment)) {
      ControlTask t = base_task(data, c, fmt::format("{}", out.size()));
      OrthoCamera cam = sample_protocol_camera(cam_rng);
      CameraParams cp{cam.scale, cam.pitch * 180.0 / M_PI, cam.yaw * 180.0 / M_PI, cam.roll * 180.0 / M_PI};
      std::vector<int> js = combo.joints;
      if (js.empty()) {
        for (int j : joints)
          if (rng.chance(0.5)) js.push_back(j);
        if (js.empty()) js.push_back(joints[rng.integer(0, static_cast<int>(joints.size()) - 1)]);
      }
      // The keypose comes first: the lifting metrics read MPJPE-2D/3D on its frames.
      if (!keypose_frames.empty()) {
        ConstraintItem kp;
        kp.type = "camera_2d";
        kp.name = "2D keypose";
        kp.frames.kind = FrameSelection::Kind::list;
        for (int f : keypose_frames) {
          int fr = f < 0 ? t.length + f : f;
          if (fr < 0 || fr >= t.length)
            fail("protocol.keypose_frames: frame {} is outside clip '{}' of {} frames", f, t.clip_id, t.length);
          kp.frames.list.push_back(fr);
        }
        kp.has_camera = true;
        kp.camera = cp;
        kp.from_source = true;
        t.spec.items.push_back(kp);
      }
      ConstraintItem tr;
      tr.type = "camera_2d";
      tr.name = "2D trajectory " + joint_group(data, js);
      for (int j : js) tr.joints.push_back(JointRef{j, ""});
      tr.frames.kind = FrameSelection::Kind::list;
      const std::vector<int> keyposes = t.spec.items.empty() ? std::vector<int>{} : t.spec.items[0].frames.list;
      for (int f : draw_frames(rng, t.length, combo.density.frames(t.length)))  // a keypose frame already fixes every joint
        if (std::find(keyposes.begin(), keyposes.end(), f) == keyposes.end()) tr.frames.list.push_back(f);
      tr.has_camera = true;
      tr.camera = cp;
      tr.from_source = true;
      if (!tr.frames.list.empty()) t.spec.items.push_back(tr);
      t.spec.source = "sketch2anim lifting protocol (" + t.id + ")";
      t.group = combo.group;
      out.push_back(std::move(t));
    }
    return out;
  }
};
MC_REGISTER_PROTOCOL("lifting", LiftingProtocol,
                     "Sketch2Anim 2D-to-3D lifting: known orthographic camera, 2D keypose + 2D joint trajectories");

// ---------------------------------------------------------------- ProjFlow's other applications

// The clip whose caption an upper-body edit of clip c asks for: the next clip of c's
// split (cyclic, in file order) with a different motion program label and a different
// first caption; without labels, the next one with a different first caption.
// Deterministic in the data alone, so every row edits towards the same text.
size_t edit_caption_clip(const MotionSet& data, size_t c) {
  const std::vector<size_t> split = data.indices_of_split(data.splits[c]);
  const size_t n = split.size();
  const size_t at = static_cast<size_t>(std::find(split.begin(), split.end(), c) - split.begin());
  auto label_of = [&](size_t i) { return i < data.labels.size() ? data.labels[i] : std::string(); };
  for (bool need_label : {true, false})
    for (size_t k = 1; k < n; ++k) {
      const size_t o = split[(at + k) % n];
      if (data.captions[o].front() == data.captions[c].front()) continue;
      if (need_label && (label_of(c).empty() || label_of(o) == label_of(c))) continue;
      return o;
    }
  fail("protocol upper_body_edit: no clip of split '{}' other than '{}' has a different caption to edit towards "
       "({} clips in the split)",
       data.splits[c], data.ids[c], n);
}

struct ApplicationProtocol : ControlProtocol {
  std::string application = "upper_body_edit";
  std::vector<int> relative_joints = {20, 21};  // relative: the two hands
  std::vector<int> loop_joints = {};            // loop: empty = all joints
  bool up_to_root_translation = true;
  void visit(FieldVisitor& v) override {
    v("application", application,
      "upper_body_edit (lower body fixed to the clip, caption of another clip of the split), relative (the "
      "clip's first-frame joint offset held at every frame), "
      "loop (first frame = last frame)",
      one_of({"upper_body_edit", "relative", "loop"}));
    v("relative_joints", relative_joints, "relative: joints a, b with x_a - x_b held at the clip's first-frame offset");
    v("loop_joints", loop_joints, "loop: joints that close the loop (empty = all)");
    v("up_to_root_translation", up_to_root_translation, "loop: allow the pose to close up to a root translation");
  }
  std::string validate() const override {
    if (application == "relative" && relative_joints.size() != 2) return "protocol.relative_joints needs two joints";
    return "";
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t) const override {
    std::vector<ControlTask> out;
    for (size_t c : clips) {
      ControlTask t = base_task(data, c, "");
      ConstraintItem item;
      item.type = application;
      item.name = application;
      if (application == "upper_body_edit") {
        item.from_source = true;
        // An edit asks the upper body for a different motion than the clip's: the
        // caption of another clip (a paraphrase of the clip's own motion would not edit).
        t.caption = data.captions[edit_caption_clip(data, c)].front();
      } else if (application == "relative") {
        check_joints(data, relative_joints, "relative_joints");
        for (int j : relative_joints) item.joints.push_back(JointRef{j, ""});
        // Fig. 1c holds one offset over the whole motion: the clip's offset at its first
        // frame (which the clip itself reaches there), kept at every frame.
        item.axes = {0, 1, 2};
        item.values.shape = {3};
        for (int k = 0; k < 3; ++k)
          item.values.data.push_back(static_cast<double>(data.at(c, 0, relative_joints[0])[k]) -
                                     data.at(c, 0, relative_joints[1])[k]);
      } else {
        check_joints(data, loop_joints, "loop_joints");
        for (int j : loop_joints) item.joints.push_back(JointRef{j, ""});
        item.up_to_root_translation = up_to_root_translation;
        if (up_to_root_translation) item.axes = {0, 1, 2};
      }
      t.spec.items.push_back(item);
      t.spec.source = application + " protocol (" + t.id + ")";
      t.group = application;
      out.push_back(std::move(t));
    }
    return out;
  }
};
MC_REGISTER_PROTOCOL("application", ApplicationProtocol,
                     "ProjFlow applications on each clip: upper-body editing, relative joints, loop closure");

}  // namespace
}  // namespace mc
