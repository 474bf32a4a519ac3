// The inequality part of the ProjFlow projection (issue 20, beyond both papers): the
// metric projection onto half-spaces {G x <= h}, solved exactly in range space by the
// dual active-set method of Goldfarb and Idnani (Math. Programming 27, 1983),
// warm-startable from a previous active set.
//
// Range space. For rows G with U = P G^T (P the metric's inverse) and M = G P G^T +
// Sigma, every candidate is x = x_hat + U lambda and row i's value is
// c_i = (M lambda)_i - r_i with r = h - G x_hat: c_i <= 0 for a feasible row, c_i = 0 for
// an active one, whose multiplier has lambda_i <= 0 (it pushes x back into its
// half-space). ProjectionSolver calls it after the equality projection, with P that
// projection's posterior covariance, so M is a Schur complement and the equalities
// stay met (docs/constraints.md). A soft row (Sigma_ii > 0) is the same row of an
// augmented problem with a slack whose penalty is 1 / Sigma_ii, so one method covers
// hard and soft rows. M is sparse (rows interact only through blocks of P they share:
// a speed limit's chain is banded), and every step touches only the active rows'
// columns of it and the active block's Cholesky factor: nothing of size d, and no dense
// m x m matrix, is touched here.
#pragma once
#include <Eigen/Dense>
#include <Eigen/Sparse>
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
  // w <- L^-T w: after forward(), M_AA^-1 v in one more triangular solve.
  void backward_in_place(Eigen::Ref<Eigen::VectorXd> w) const;
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
  Eigen::VectorXd lambda;   // one multiplier per row (0 for inactive rows)
  std::vector<int> active;  // active rows, ascending
  int iterations = 0;       // rows added or dropped
  bool feasible = true;
  std::vector<int> conflict;  // infeasible: the rows whose hard constraints contradict
};

// Solves min over lambda of the dual for `M` (m x m, symmetric, both triangles stored)
// and residuals `r` = h - G x_hat. `warm` lists rows to try first: they enter when
// independent of the rows before them, and leave again while their multipliers have
// the wrong sign, which leaves an optimum of a subproblem, the method's invariant, so
// the answer is the same as a cold start's (up to rounding). Infeasible sets (a
// violated hard row that is a combination of active rows none of which may give way)
// come back with feasible = false and the rows involved.
// `scale` (empty: M's diagonal) is each row's size before conditioning on the rest,
// e.g. g R^-1 g^T + variance when M is a Schur complement: a row depends on the
// active ones when its remaining variance falls below 1e-10 of that.
DualQpResult solve_dual_qp(const Eigen::SparseMatrix<double>& M, const Eigen::VectorXd& r,
                           const std::vector<int>& warm = {}, const Eigen::VectorXd& scale = Eigen::VectorXd());

// Tolerance on c_i for "violated": relative to the row's residual scale.
inline double inequality_tolerance(double r) { return 1e-11 * (1.0 + std::abs(r)); }

}  // namespace mc
