// Control errors read off a compiled constraint spec: the residual y - A x of a
// motion, grouped into "entries" so that one spec drives generation and scoring.
#pragma once
#include <vector>

#include "control/linear_observation.h"

namespace mc {

// One error per controlled entry: rows of the same item whose first touched
// coordinate is the same (frame, joint) form one entry, and its error is the
// Euclidean norm of their residuals. A 3D keyframe gives the 3D distance, a
// planar-root row pair the xz distance, a camera row pair the 2D reprojection
// error, a relative-offset triple the offset error. `motion` is [T, J, 3] world,
// T = obs.frames. Soft rows count like hard ones (they are controls too).
std::vector<double> observation_entry_errors(const LinearObservation& obs, const float* motion);

}  // namespace mc
