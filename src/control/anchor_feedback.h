// Feedback features for an anchor adapter (issue 15, ours; not in AnchorRoute): the anchors
// said against an estimate of the clean motion the sampler is heading for, in the
// estimate's own facing frame. The paper's adapter reads the anchors only (eqs. (5)-(6),
// (13)); on our invariant tokenizer the heading is a sum of per-token yaw rates, so an
// anchor-only memory cannot tell token n which way to steer without integrating every
// earlier token (docs/choices.md, "Where the generator-only error comes from": the
// adapters' samples travel the right distance in a direction off by a median 12 degrees).
// These channels give each frame the correction it needs where it is: the next and the
// previous anchor's residual (anchor - estimate) and bearing (anchor - estimate at this
// frame), rotated into the estimate's facing frame at this frame.
#pragma once
#include <vector>

#include "control/anchors.h"

namespace mc {

struct Skeleton;

// Channels per frame t of [0, set.frames), all 0 where there is no such anchor:
//   [0:3)   next residual   mean over the anchors at the first anchor frame f >= t of
//                           (y - estimate[f, joint]) on the anchor's axes (0 on the others),
//                           x (lateral), y (up), z (forward) in the facing frame of t; metres
//   [3:6)   next bearing    mean over the same anchors of (y~ - estimate[t, joint]), y~ = y on
//                           the anchor's axes and estimate[f, joint] on the others; same frame
//   6       time to f       (f - t) / kPathFrameRate, seconds
//   7       has next        1 / 0
//   [8:16)  the same for the last anchor frame f <= t (time since it)
//   16      anchor at t     1 / 0
// The facing frame is data/features.h facing_angles of the estimate (hips and shoulders,
// smoothed); to_facing_frame rotates world xz by -theta. Every channel is unchanged when
// the anchors and the estimate are rotated about y and moved in xz together (tested).
constexpr int kFeedbackWidth = 17;
// estimate: [set.frames, num_joints, 3] world metres, row-major. UserError if an anchor's
// joint is not in the skeleton or the estimate is shorter than the set.
FeatureMatrix anchor_feedback_features(const AnchorSet& set, const float* estimate, int estimate_frames,
                                       const Skeleton& skeleton);

}  // namespace mc
