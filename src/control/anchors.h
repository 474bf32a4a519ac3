// AnchorRoute's sparse anchors (§3.1): anchor sets of the three control families built
// from (and turned back into) constraint specs, the benchmark draws, the frame-level
// anchor-condition features of eqs. (5)-(6) and the support assignment of eqs. (7)-(9).
#pragma once
#include <Eigen/Dense>
#include <array>
#include <cstdint>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "control/linear_observation.h"

namespace mc {

struct Skeleton;

// The three sparse-control families of the paper. root_3d and planar_root observe
// the root joint (index 0); body_point observes x, y, z of any joint.
enum class AnchorFamily { root_3d, planar_root, body_point };
std::string family_name(AnchorFamily f);  // "root_3d", "planar_root", "body_point"
// UserError naming `what` and the accepted spellings.
AnchorFamily parse_anchor_family(const std::string& name, const std::string& what = "anchor family");

// One anchor (tau_n, m_n, y_n) of eq. (2). m_n is the pair (joint, axes): the
// projection Pi_{m_n} selects those axes of that joint.
struct Anchor {
  int frame = 0;                              // tau_n
  int joint = 0;                              // m_n: joint ...
  std::array<bool, 3> axes{true, true, true};  // ... and its controlled world axes (planar root: x, z)
  Eigen::Vector3d value = Eigen::Vector3d::Zero();  // y_n, metres; uncontrolled axes hold 0
  int dims() const { return int(axes[0]) + int(axes[1]) + int(axes[2]); }
  bool operator==(const Anchor& o) const {
    return frame == o.frame && joint == o.joint && axes == o.axes && value == o.value;
  }
};

struct AnchorSet {
  AnchorFamily family = AnchorFamily::root_3d;
  int frames = 0;               // T of the clip the anchors live on
  std::vector<Anchor> anchors;  // sorted by (frame, joint); no (frame, joint) twice

  int size() const { return static_cast<int>(anchors.size()); }
  std::vector<int> times() const;   // distinct anchor frames, ascending
  std::vector<int> joints() const;  // distinct anchored joints, ascending
  // Sorts the anchors and checks them against the family and a skeleton of
  // `num_joints` joints; UserError naming `what`, the anchor and the problem.
  void normalize_and_check(int num_joints, const std::string& what);
  bool operator==(const AnchorSet& o) const { return family == o.family && frames == o.frames && anchors == o.anchors; }
};

// ------------------------------------------------------------------ spec <-> anchors

// Anchors from compiled rows. Every row must be hard and select one coordinate
// (a single entry equal to 1); the rows of one (frame, joint) must cover x, y, z
// (or x, z for the root: a planar-root anchor). `family` unset: root_3d when every
// anchor is root xyz, planar_root when every anchor is root xz, body_point when
// every anchor is xyz. Anything else is a UserError naming the item and the row.
AnchorSet anchors_from_observation(const LinearObservation& obs, std::optional<AnchorFamily> family = {});
// Only keyframe, trajectory and planar_root items can be anchors; other types
// (camera_2d, relative, loop, upper_body_edit) are rejected by name before compiling.
// Inequality and direction items (floor, tangent, ...) are skipped: they are not
// anchors, and AnchorRoute reads them separately (RouteSolver residuals, exact projection).
AnchorSet anchors_from_spec(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                            const float* source_motion = nullptr, std::optional<AnchorFamily> family = {});
// The reverse: root_3d -> one keyframe item on the root; planar_root -> one
// planar_root item; body_point -> one keyframe item per joint. Compiling the
// result and converting it back gives the same set.
ConstraintSpec anchors_to_spec(const AnchorSet& set, const std::string& source = "<anchors>");

// Euclidean error of each anchor in its control subspace (xz only for planar
// root): ||Pi_m(x[tau]) - y||, for a motion [frames, J, 3] (world, row-major).
// The AnchorRoute control error is their mean (eval: control_metrics_from_errors).
std::vector<double> anchor_errors(const AnchorSet& set, const float* motion, int num_joints);
// Eq. (3): sum of the squared errors.
double anchor_loss(const AnchorSet& set, const float* motion, int num_joints);

// ------------------------------------------------------------------ benchmark draws

// K distinct frames of [0, frames) drawn uniformly without replacement (partial
// Fisher-Yates with unbiased rejection draws from the engine, so the result is the
// same on every standard library), returned ascending. UserError if K > frames.
std::vector<int> draw_anchor_frames(std::mt19937_64& rng, int frames, int K);
// The main protocol's anchor set for one clip: K frames from draw_anchor_frames,
// values read from the ground-truth motion [frames, J, 3]. body_point draws one
// joint uniformly from `body_joints` for the whole set (after the frames).
AnchorSet draw_anchor_set(AnchorFamily family, int K, const float* motion, int frames, int num_joints,
                          std::mt19937_64& rng, const std::vector<int>& body_joints = {0, 10, 11, 15, 20, 21});
// Table II's six-point sparse keyjoint protocol ("all6-r30", our reading, docs/choices.md):
// the joints `joints` (default 0, 10, 11, 15, 20, 21) all controlled in xyz at the
// same max(1, round(ratio * frames)) frames drawn as in draw_anchor_frames.
AnchorSet draw_sparse_keyjoint_set(const float* motion, int frames, int num_joints, std::mt19937_64& rng,
                                   double ratio = 0.3, const std::vector<int>& joints = {0, 10, 11, 15, 20, 21});

// ------------------------------------------------------------------ interpolation prior

// Endpoint-inclusive interpolation through the points (times[i], values.row(i))
// (times strictly ascending), evaluated at every integer frame of [times.front(),
// times.back()]: row k of the result is frame times.front() + k. Not-a-knot cubic
// spline with >= 4 points (scipy's interp1d(kind='cubic')), piecewise linear with
// 2 or 3, the constant with 1.
Eigen::MatrixXd interpolate_anchor_values(const std::vector<int>& times, const Eigen::MatrixXd& values);

// ------------------------------------------------------------------ condition features

// Channel layout of anchor_features() (docs/choices.md). The controlled channels
// are, for each group joint in order, its controlled axes (root_3d / body_point:
// x, y, z; planar_root: x, z): d_f = sum of those, G = number of groups. Columns:
//   [0, d_f)              m^a (.) a   anchor values at anchored frames, else 0
//   [d_f, 2 d_f)          m^p (.) p   interpolation prior where defined, else 0
//   [2 d_f, 3 d_f)        Delta p     p_t - p_{t-1} where both are defined, else 0 (eq. (6))
//   [3 d_f, 3 d_f + G)    m^p         per group: prior defined at t
//   [3 d_f + G, 3 d_f + 2G) m^a       per group: anchored at t
// With one group (root families, one body joint) this is eq. (5)'s 3 d_f + 2.
struct AnchorFeatureLayout {
  AnchorFamily family = AnchorFamily::root_3d;
  std::vector<int> joints;  // one group per joint
  std::vector<std::array<bool, 3>> axes;  // per group
  int d_f = 0;
  int groups() const { return static_cast<int>(joints.size()); }
  int width() const { return 3 * d_f + 2 * groups(); }
};
// The layout for `family` (also of anchor_path_features); body_point needs the group joints (e.g. the protocol's
// six), fixed so every sample of a model has the same width.
AnchorFeatureLayout anchor_feature_layout(AnchorFamily family, const std::vector<int>& body_joints = {});

using FeatureMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
// Eqs. (5)-(6): [set.frames, layout.width()] features. UserError if an anchor's
// joint or family is not in the layout.
FeatureMatrix anchor_features(const AnchorSet& set, const AnchorFeatureLayout& layout);

// ------------------------------------------------------------------ path-frame features (issue 15, ours)

// The same anchors said in the frame of the interpolation prior's own path instead of
// the world's: what a translation-invariant token encodes locally (heading change, root
// displacement in the facing frame, height), so a token-aligned memory need not
// integrate the heading over earlier tokens. Every channel is unchanged when the whole
// anchor set is rotated about y and translated in xz (height and vertical channels also
// under any xz translation; nothing is invariant to a vertical shift of the floor).
// Per group, defined on the prior's range [first anchor, last anchor] and 0 elsewhere:
//   speed        |v_xz| * kPathFrameRate (m/s), v = p_t - p_{t-1} (at the first prior
//                frame the forward difference, so the range starts at its speed)
//   turn         the change of the path heading psi_t = atan2(v_x, v_z) from t - 1 to t
//                (wrapped to (-pi, pi]) * kPathFrameRate (rad/s), scaled by
//                min(1, speed / kPathMinSpeed) of the slower frame so a standing path's
//                jitter reads as no turn; 0 at the first prior frame
//   [vy, height] (groups with y) v_y * kPathFrameRate (m/s), p_y (m)
//   next         the next anchor strictly after t, minus p_t, in the path frame at t:
//                x' (lateral), [y (up)], z' (along the path), metres; then the time to
//                it, seconds (frames / kPathFrameRate); all 0 when there is none
//   prev         the same for the last anchor strictly before t (time since it)
//   m^p, m^a     as in anchor_features
//   [rel root]   (body_point groups) p_t minus the root group's prior, in the root
//                path's frame (x', y, z'), where both priors are defined (the layout
//                lists joint 0 and the set anchors it), else 0
// The path frame at t rotates world xz by -psi_t (the tokenizer's facing-frame
// convention, data/features.*: heading 0 faces +Z). psi_t is kept from the last frame
// moving at kPathMinSpeed or more (a standing path has no direction); frames before the
// first such frame take its heading, and a path that never moves that fast takes the
// heading of its fastest frame.
constexpr double kPathFrameRate = 20.0;  // frames per second the rate channels are said in (HumanML3D's rate)
constexpr double kPathMinSpeed = 0.005;  // m per frame (0.1 m/s at 20 fps): slower reads as standing
// Channels of group g's block, and the whole block's width (groups side by side).
int path_group_width(const AnchorFeatureLayout& layout, int g);
int path_feature_width(const AnchorFeatureLayout& layout);
// [set.frames, path_feature_width(layout)]. UserError as anchor_features.
FeatureMatrix anchor_path_features(const AnchorSet& set, const AnchorFeatureLayout& layout);

// ------------------------------------------------------------------ support (eqs. (7)-(9))

// n*(t) of eq. (8) for every frame of [0, frames): the index into `times` of the
// nearest anchor time within `delta` (ties go to the earlier anchor), -1 outside
// the support set U_delta of eq. (7).
std::vector<int> nearest_anchor_assignment(const std::vector<int>& times, int frames, int delta);

// One term of eq. (10): frame t and the anchor n*(t) whose subspace it is scored in.
struct SupportEntry {
  int frame = 0;
  int anchor = 0;  // index into set.anchors
};
// The support entries of a set: per anchored joint, eqs. (7)-(8) over that joint's
// anchor times (so several body points at one frame each keep their own support).
// Sorted by (frame, joint).
std::vector<SupportEntry> support_entries(const AnchorSet& set, int delta);
// Eq. (9) targets: the ground-truth observation of each entry's anchor subspace,
// as anchors (frame = entry frame, joint/axes of the assigned anchor, value from
// `gt_motion` [frames, J, 3]). Eq. (10) is then anchor_loss of this set.
AnchorSet support_targets(const AnchorSet& set, int delta, const float* gt_motion, int num_joints);

}  // namespace mc
