// write_motion_file with more groups in the same atomic write (defined in
// data/motion_set.cpp). Kept out of motion_set.h, which nearly every file includes.
#pragma once
#include <cstdint>
#include <functional>
#include <string>

#include "data/motion_set.h"

namespace mc {

// Writes `m` as write_motion_file does, then `extra(file_id)` (the HDF5 hid_t of the
// open file) adds its groups, e.g. the per-sample constraint specs
// (control/sample_constraints.h), before the file is renamed into place. Readers of
// the motion format ignore groups they do not know.
void write_motion_file(const std::string& path, const MotionSet& m, const std::function<void(int64_t)>& extra);

}  // namespace mc
