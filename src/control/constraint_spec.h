// A constraint spec: the user's list of spatial controls (YAML by hand, HDF5 for
// dense targets) as written, before compile() turns it into rows of y = A x + eps.
// Format reference: docs/constraints.md.
#pragma once
#include <string>
#include <vector>

namespace mc {

// A joint as the user wrote it: an index or a name; resolved against the skeleton
// by compile(), so a spec file does not depend on one skeleton's numbering.
struct JointRef {
  int index = -1;
  std::string name;  // non-empty: refer by name
  bool set() const { return index >= 0 || !name.empty(); }
  std::string text() const { return name.empty() ? std::to_string(index) : "'" + name + "'"; }
  bool operator==(const JointRef& o) const { return index == o.index && name == o.name; }
};

// Frames as written; resolved against the clip length T by compile().
struct FrameSelection {
  enum class Kind { unset, list, range, all };
  Kind kind = Kind::unset;  // unset: the item type's default
  std::vector<int> list;    // Kind::list
  int start = 0;            // Kind::range: start, start+step, ... < stop
  int stop = -1;            // -1: T
  int step = 1;
  bool operator==(const FrameSelection& o) const {
    return kind == o.kind && list == o.list && start == o.start && stop == o.stop && step == o.step;
  }
};

// An orthographic camera for camera_2d items; angles in degrees in files.
struct CameraParams {
  double scale = 1.0;
  double pitch_deg = 0.0;
  double yaw_deg = 0.0;
  double roll_deg = 0.0;
  bool operator==(const CameraParams& o) const {
    return scale == o.scale && pitch_deg == o.pitch_deg && yaw_deg == o.yaw_deg && roll_deg == o.roll_deg;
  }
};

// A dense array as written (row-major) with its shape; empty shape = not given.
struct TargetArray {
  std::vector<double> data;
  std::vector<int> shape;
  bool given() const { return !shape.empty(); }
  bool operator==(const TargetArray& o) const { return data == o.data && shape == o.shape; }
};

// One control. Which fields apply depends on `type` (docs/constraints.md):
//   keyframe        joints, frames (required), axes, values [F, Jk, A] | from_source
//   trajectory      joints, frames (default all), axes, values [F, Jk, A] (or [F, A] for one joint) | from_source
//   planar_root     frames (default all), values [F, 2] (root x, z) | from_source
//   camera_2d       joints, frames (default all), camera, values [F, Jk, 2] | from_source
//   relative        joints (exactly two: a, b), frames (default all), axes, values [F, A] or [A] | from_source
//   loop            joints (default all), axes, frames (optional [first, last]), up_to_root_translation
//   upper_body_edit role (default lower_body), frames (default all), axes; always from the source motion
// Inequality items (rows G x <= h, docs/constraints.md "Inequalities"):
//   floor           joints (default role toes), frames (default all), height: y >= height
//   half_space      joints, frames (default all), normal, offset, relative_to: n.(x_j [- x_ref]) >= offset
//   box             joints, frames (default all), axes, min and/or max per axis
//   speed_limit     joints, frames (default all transitions), axes, max: |x[t+1] - x[t]| <= max per axis
// Direction items (equality rows for the direction, one inequality row for its sense):
//   tangent         joints (one, default the root), frames, axes (default xz), values [F, A] or [A] | from_source,
//                   min_speed: the joint's velocity at each frame points along the value
//   facing          joints (two: right, left; default the first two of role face), frames, values [F, 2] or [2]
//                   (x, z) | from_source, min_width: the body faces the value (hip-difference rows)
struct ConstraintItem {
  std::string type;
  std::string name;          // for messages; may be empty
  double variance = 0.0;     // 0 = hard; otherwise observation units squared (m^2, or 2D units^2)
  std::vector<JointRef> joints;
  FrameSelection frames;
  std::vector<int> axes;     // subset of {0, 1, 2} = {x, y, z}; empty = the type's default
  TargetArray values;
  bool from_source = false;
  bool has_camera = false;
  CameraParams camera;
  bool up_to_root_translation = false;
  std::string role;          // upper_body_edit; empty = "lower_body"
  // Inequality and direction items.
  double height = 0.0;               // floor: y >= height (m)
  std::vector<double> normal;        // half_space: [3], normalised by compile
  double offset = 0.0;               // half_space: n . x >= offset (m, along the unit normal)
  JointRef relative_to;              // half_space: n . (x_j - x_ref) >= offset when set (index >= 0 or a name)
  std::vector<double> lower, upper;  // box: `min`, `max` ([A] or one number); speed_limit: `max` in upper
  double min_speed = 0.01;           // tangent: velocity along the direction >= this (metres per frame)
  double min_width = 0.05;           // facing: hip-difference component that orients the body >= this (m)
  bool score_only = false;           // measured by the metrics, never imposed: compile() emits no rows
  int line = 0;              // YAML line of the item (0 = unknown), for messages

  bool hard() const { return variance == 0.0; }
  bool operator==(const ConstraintItem& o) const;
};

struct ConstraintSpec {
  std::vector<ConstraintItem> items;
  std::string source = "<spec>";  // file (or description) for messages

  // "item 2 'left wrist path' (keyframe)", used in every message about the item.
  std::string item_label(int index) const;
};

// The item types that compile to equality rows (A x = y), in documentation order.
const std::vector<std::string>& constraint_types();
// Types that compile to inequality rows only (G x <= h): floor, half_space, box, speed_limit.
const std::vector<std::string>& inequality_constraint_types();
// Direction types (equality rows plus one inequality row per frame): tangent, facing.
const std::vector<std::string>& direction_constraint_types();
// All of the above: what a spec may name.
const std::vector<std::string>& all_constraint_types();
bool is_inequality_type(const std::string& type);
bool is_direction_type(const std::string& type);

// Parses a spec from YAML text: either a list of items or a map with key
// `constraints:`. Syntax, unknown keys (with "did you mean"), bad axes, negative
// or non-finite variances, ragged or non-finite values: UserError naming the
// source, the item and the key.
ConstraintSpec parse_constraint_spec_yaml(const std::string& text, const std::string& source = "<string>");
// By extension: .h5/.hdf5 -> load_constraint_spec_h5, anything else -> YAML.
ConstraintSpec load_constraint_spec(const std::string& path);
// The HDF5 layout of docs/constraints.md (group `group`, one subgroup per item).
ConstraintSpec load_constraint_spec_h5(const std::string& path, const std::string& group = "constraints");
// Writes `spec` in that layout to a new file at `path` (atomic: temporary + rename).
void save_constraint_spec_h5(const ConstraintSpec& spec, const std::string& path,
                             const std::string& group = "constraints");

}  // namespace mc
