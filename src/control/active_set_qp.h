// The inequality part of the ProjFlow projection (issue 20, beyond both papers): the
// R-metric projection onto {A x = y} ∩ {G x <= h}, solved exactly in range space by
// the dual active-set method of Goldfarb and Idnani (Math. Programming 27, 1983),
// warm-startable from a previous active set.
//
// Range space. For rows C (equalities first, then inequalities) with W = R^-1 C^T and
// M = C R^-1 C^T + Sigma, every candidate is x = x_hat + W lambda and row i's value is
// c_i = (M lambda)_i - r_i with r = b - C x_hat: c_i = 0 for an active row, c_i <= 0 for
// a feasible inequality; an active inequality's multiplier has lambda_i <= 0 (it
// pushes x back into its half-space). ProjectionSolver calls it with the inequality
// rows alone, after the equality projection: then R^-1 is replaced by that
// projection's posterior covariance P and M is G P G^T + Sigma (a Schur complement),
// which is the same problem. A soft row (Sigma_ii > 0) is the same row of an
// augmented problem with a slack whose penalty is 1 / Sigma_ii, so one method covers
// hard and soft rows (docs/constraints.md). Nothing of size d is touched here.
#pragma once
#include <Eigen/Dense>
#include <vector>

namespace mc {

// The Cholesky factor of M restricted to an ordered active set, updated when rows
// enter (one new row of L, O(k^2)) and leave (a rank-one update of the trailing
// block, O(k^2)) instead of refactorised.
class ActiveCholesky {
 public:
  // Starts from the factor `l` (lower, k x k) of the first k active rows; at most
  // `capacity` rows ever (storage grows on demand: most solves activate a few rows).
  void reset(const Eigen::MatrixXd& l, int capacity);
  int size() const { return k_; }
  // w = L^-1 v for the active rows (v has size()).
  Eigen::VectorXd forward(const Eigen::VectorXd& v) const;
  // b <- M_AA^-1 b.
  void solve_in_place(Eigen::Ref<Eigen::VectorXd> b) const;
  // Appends a row with L^-1 M_{A,new} = w and Schur complement s > 0.
  void append(const Eigen::VectorXd& w, double s);
  // Removes active position q.
  void remove(int q);

 private:
  Eigen::MatrixXd l_;
  int k_ = 0, capacity_ = 0;
};

struct DualQpResult {
  Eigen::VectorXd lambda;   // m multipliers (0 for inactive inequalities)
  std::vector<int> active;  // active inequality rows (local indices >= equalities), ascending
  int iterations = 0;       // rows added or dropped
  bool feasible = true;
  std::vector<int> conflict;  // infeasible: the local rows whose hard constraints contradict
};

// Solves the group. `M` is m x m (rows [0, equalities) equalities, the rest
// inequalities), `r` the residuals b - C x_hat, `l_eq` the Cholesky factor of M's
// equality block (possibly jittered), `lambda_eq` = M_EE^-1 r_E (the equality
// projection's multipliers, the method's starting point). `warm` lists inequality
// rows (local) to try first: they enter when independent of the rows before them,
// and leave again while their multipliers have the wrong sign, which leaves an
// optimum of a subproblem, the method's invariant, so the answer is the same as a
// cold start's (up to rounding). Infeasible sets (a violated hard row that is a
// combination of active rows none of which may give way) come back with
// feasible = false and the rows involved.
// `scale` (empty: M's diagonal) is each row's size before conditioning on the rest,
// e.g. g R^-1 g^T + variance when M is a Schur complement: a row depends on the
// active ones when its remaining variance falls below 1e-10 of that.
DualQpResult solve_dual_qp(const Eigen::MatrixXd& M, const Eigen::VectorXd& r, int equalities,
                           const Eigen::MatrixXd& l_eq, const Eigen::VectorXd& lambda_eq,
                           const std::vector<int>& warm = {}, const Eigen::VectorXd& scale = Eigen::VectorXd());

// Tolerance on c_i for "violated": relative to the row's residual scale.
inline double inequality_tolerance(double r) { return 1e-11 * (1.0 + std::abs(r)); }

}  // namespace mc
