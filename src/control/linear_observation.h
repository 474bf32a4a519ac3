// The one constraint type every method consumes: y = A x + eps, eps ~ N(0, Sigma)
// (eq. (4)) over the vectorised motion, compiled from a ConstraintSpec in world
// units (metres), plus the inequality rows G x <= h of floor, half-space, box,
// speed and direction items (beyond both papers, issue 20). Samplers, guidance,
// anchors and metrics all read this.
#pragma once
#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <array>
#include <string>
#include <vector>

#include "control/constraint_spec.h"

namespace mc {

struct Skeleton;

// What a tangent or facing item asks at one frame, kept beside the rows so metrics
// score the angle the item meant (eval/observation_errors.h), imposed or score_only.
struct DirectionProbe {
  int item = 0;          // index into item_labels
  bool facing = false;   // false: tangent
  int frame = 0;
  int joint = 0;         // tangent: the joint; facing: the right joint
  int other = -1;        // facing: the left joint
  std::vector<int> axes;     // tangent: the item's axes; facing: {0, 2}
  Eigen::VectorXd target;    // unit direction on `axes` (facing: forward x, z)
};

struct LinearObservation {
  // m x d with d = 3 * J * T; column (t * J + j) * 3 + c is joint j's axis c at frame t
  // (frame-major, the paper's order, §3.1).
  Eigen::SparseMatrix<double, Eigen::RowMajor> A;
  Eigen::VectorXd y;         // m targets
  Eigen::VectorXd variance;  // m; 0 = hard row (Sigma = diag(variance))
  std::vector<int> item_of_row;          // m; index into item_labels
  std::vector<std::string> item_labels;  // one per spec item: "item 2 'left wrist' (keyframe)"
  std::string source;                    // spec source, for messages
  int frames = 0, joints = 0;
  // Inequality rows G x <= h (p x d, same column order as A). A hard row (variance
  // 0) must hold; a soft one adds the one-sided penalty max(0, g x - h)^2 / (2 var),
  // the MAP of a half-Gaussian observation. Methods that cannot honour them (the
  // guidance and DNO baselines) ignore them; ProjFlow's projection is the QP.
  Eigen::SparseMatrix<double, Eigen::RowMajor> G;
  Eigen::VectorXd h;
  Eigen::VectorXd g_variance;       // p; 0 = hard
  std::vector<int> item_of_g_row;   // p; index into item_labels
  std::vector<DirectionProbe> directions;  // one per frame of every tangent / facing item

  int rows() const { return static_cast<int>(y.size()); }
  int inequalities() const { return static_cast<int>(h.size()); }
  bool is_hard_inequality(int row) const { return g_variance[row] == 0.0; }
  int dim() const { return 3 * joints * frames; }
  bool is_hard(int row) const { return variance[row] == 0.0; }
  static int index(int frame, int joint, int axis, int num_joints) { return (frame * num_joints + joint) * 3 + axis; }
};

// Compiles `spec` for a clip of `frames` frames on `skeleton`. `source_motion`
// ([frames, J, 3] world, row-major) is needed by from_source items and by
// upper_body_edit. Throws UserError naming the item, the key and the value for:
// joint/frame/axis out of range, unknown joint or role names (with "did you mean"),
// target shape mismatches, non-finite targets or source values, a missing source
// motion, contradictory or redundant hard constraints (check_hard_rows), and hard
// inequalities that no motion can meet together with the hard equalities
// (check_feasible). Rows come item by item, frame-major within an item, in spec
// order; score_only items are checked but emit no rows.
LinearObservation compile(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                          const float* source_motion = nullptr);

// Rows coupled through R^-1, which is block-diagonal over (frame, axis) blocks
// with dense J x J blocks (eq. (11)): two rows are coupled when they touch a
// common block. Union-find over blocks; groups are sorted, and ordered by their
// smallest row. `only_hard` restricts to rows with variance 0. Rows without any
// entry form singleton groups.
std::vector<std::vector<int>> coupled_row_groups(const LinearObservation& obs, bool only_hard = false);

// The hard rows must have full row rank, or A_hard R^-1 A_hard^T is singular and
// the projection (eq. (7)) undefined. Rank does not depend on R (R^-1 is SPD), so
// each coupled group of hard rows is tested through the Gram matrix of its
// normalised rows. Throws UserError naming the items whose rows are dependent and
// the frames involved, and whether they contradict (targets disagree) or only
// repeat each other.
void check_hard_rows(const LinearObservation& obs);

// The hard rows (equalities and inequalities) must admit a motion: a feasibility
// solve of the QP (projection_solver.h, Euclidean metric). Throws UserError naming
// the items whose rows contradict each other and the frames involved.
void check_feasible(const LinearObservation& obs);

// The inequality rows of `obs` as an equality-shaped observation (A = G, y = h,
// variance = g_variance), for code that evaluates G x - h with the A x - y tools.
LinearObservation inequality_rows(const LinearObservation& obs);
// Only the equality rows (G, h emptied): what the inequality-blind baselines see.
LinearObservation without_inequalities(const LinearObservation& obs);

// The normaliser's per-axis affine map x_world = scale (.) x_model + offset moved
// inside the operator: A_m = A diag(scale), y_m = y - A offset, and the same for
// G and h (a substitution of variables, so no inequality flips sign). Variances
// are in observation units and stay as they are. Users never see normalised units.
LinearObservation affine_to_model(const LinearObservation& obs, const std::array<double, 3>& axis_scale,
                                  const std::array<double, 3>& axis_offset);

}  // namespace mc
