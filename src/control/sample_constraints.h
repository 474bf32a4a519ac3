// What every generated sample was constrained to, stored inside its motion file
// (group /control, docs/formats.md "Constraints of generated samples"), so that
// `motionctl score` and outside tools re-score a file from the file alone: no
// protocol, seed or ground-truth file needed.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "data/skeleton.h"

namespace mc {

// The HDF5 layout of a spec (docs/constraints.md) inside an open file, so a spec can
// travel inside another file (defined in constraint_spec.cpp). `parent` is an HDF5
// location id (hid_t); `group` is created (its parent groups must exist) or read
// relative to it; `path` names the file in messages.
void write_constraint_spec_group(int64_t parent, const std::string& group, const ConstraintSpec& spec,
                                 const std::string& path);
ConstraintSpec read_constraint_spec_group(int64_t parent, const std::string& group, const std::string& path);

// A copy of `spec` that no longer needs the source motion: every from_source item
// gets, as `values`, exactly the targets compile() took from `source_motion`, and an
// upper_body_edit item becomes a trajectory of its role's joints (indices, explicit
// frame list and axes) with those targets. compile() of the copy without a source
// gives the same rows (A, y, variances) as compile() of `spec` with it.
ConstraintSpec with_explicit_targets(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                                     const float* source_motion);

// Writes /control into an open HDF5 file (`file` is its hid_t): attrs `format`
// ("motionctl.sample_constraints") and `format_version` (1), dataset `frames`
// (int32 [N], the length each spec was compiled for) and one group `sample_<i>` per
// sample in the layout of docs/constraints.md ("HDF5 layout"). `path` is for messages.
void write_sample_constraints(int64_t file, const std::vector<ConstraintSpec>& specs, const std::vector<int>& frames,
                              const std::string& path);

// The /control group of a motion file: one spec per clip and the frame count each
// was compiled for. Both empty when the file has no /control group (files written
// before it existed, datasets). UserError naming the file when it is malformed.
struct SampleConstraints {
  std::vector<ConstraintSpec> specs;
  std::vector<int> frames;
};
SampleConstraints read_sample_constraints(const std::string& path);

// True when some spec has at least one item.
bool any_constraints(const std::vector<ConstraintSpec>& specs);

}  // namespace mc
