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
// Rows of direction items (tangent, facing) are not entries: they are scored as
// angles by direction_errors.
std::vector<double> observation_entry_errors(const LinearObservation& obs, const float* motion);

// The largest violation max(0, g x - h) over the inequality rows, hard and soft, in
// the rows' units (metres; metres per frame for speed limits; 0 without rows).
double max_inequality_violation(const LinearObservation& obs, const float* motion);

// One angle error in degrees per direction probe (every frame of every tangent and
// facing item, imposed or score_only): the angle between the motion's direction
// (control/directions.h, the definition compile() used) and the item's; 90 where
// the motion has no direction there (a joint at rest, hips on top of each other).
std::vector<double> direction_errors(const LinearObservation& obs, const float* motion);

}  // namespace mc
