// The ProjFlow correction (eq. (7)): x' = x_hat + R^-1 A^T (A R^-1 A^T + Sigma)^-1 (y - A x_hat),
// solved per group of coupled rows without forming anything of size d x d, with
// the factorisations cached while A and Sigma stay the same. With inequality rows
// (G x <= h, issue 20) it is the R-metric projection onto the equality set
// intersected with the half-spaces: an exact QP per coupled group
// (control/active_set_qp.h) started from the equality projection.
#pragma once
#include <Eigen/Dense>
#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

#include "control/kinematic_metric.h"
#include "control/linear_observation.h"

namespace mc {

// Usage:
//   ProjectionSolver solver(KinematicMetric::kinematic(skeleton));
//   solver.set_observation(obs);                  // factorises
//   Eigen::MatrixXd x1 = solver.project(x1_hat);  // d x S, one column per sample
//
// Structure. R^-1 is block-diagonal over (frame, axis) blocks with dense J x J
// blocks, so rows interact only through blocks they share. Rows are grouped by
// union-find over blocks (coupled_row_groups). Per group c the small dense
// M_c = A_c R^-1 A_c^T + Sigma_c is assembled from the sparse rows (W_c = R^-1 A_c^T
// is built from columns of K^-1, M_c = A_c W_c touches only A_c's entries) and
// Cholesky-factorised, and the gain G_c = W_c M_c^-1 is kept, so a projection is
// one small product per group. Frame-local rows give per-(frame, axis) systems,
// camera rows per-frame ones; loop and relative rows couple only what they touch.
//
// Sharing. Groups whose local structure is identical (same rows relative to
// their blocks, same coefficients, same variances) have identical M_c and G_c: a
// trajectory over all frames, one camera over all frames, keyframes of the same
// joints. They share one factorisation, so a dense observation costs a handful
// of factorisations, not one per frame.
//
// Jitter. When LLT fails or its smallest pivot squared is below 1e-13 of the
// largest diagonal entry (rank-deficient hard rows that skipped check_hard_rows,
// e.g. built by hand), 1e-8 * mean(diag M_c) is added to the diagonal of the hard
// rows only and the group is refactorised; jittered_groups() counts such groups.
// Soft rows never need it: their variance already makes M_c positive definite.
//
// Batches. project() works on the transpose (samples x d), where one coordinate
// of all samples is contiguous, so every group's update is a dense GEMM.
//
// Inequalities. Rows of G join the union-find like rows of A; a group with
// inequality rows keeps, besides the equality gain, M = C R^-1 C^T + Sigma over
// all its rows (C = [A_c; G_c]), W = R^-1 C^T and the Cholesky factor of M's
// equality block. A projection first applies the equality update to every column
// (one GEMM, as without inequalities), reads the inequality values off it (one
// more small GEMM) and runs the dual active-set QP only for the columns where a
// row is violated or a warm start names active rows. The QP is exact: hard
// equalities hold to solver precision, hard inequalities to ~1e-11 of their
// residual, and the answer does not depend on the warm start. A hard set that no
// motion meets is a UserError naming the items.
class ProjectionSolver {
 public:
  explicit ProjectionSolver(KinematicMetric metric);

  // Keeps the factorisations when `obs` has the same A (pattern and values),
  // frames and joints: then only y is replaced, and changed variances take the
  // update_variance path.
  void set_observation(const LinearObservation& obs);
  // Refactorises only the groups whose variances changed (e.g. the adaptive
  // pseudo-observation variances of eq. (18) at each sampling step).
  void update_variance(const Eigen::VectorXd& variance);
  void update_targets(const Eigen::VectorXd& y);

  // Active inequality rows (global rows of G) per sample column, carried from one
  // projection of a column to the next (ProjFlow: from one sampling step to the
  // next) to warm-start the QP. Empty: cold start.
  struct ActiveSets {
    std::vector<std::vector<int>> columns;
  };

  // eq. (7)-(8) for every column of x_hat (d x S); with inequality rows, the QP.
  // `warm` (optional) is read as the start and overwritten with the final active sets.
  Eigen::MatrixXd project(const Eigen::MatrixXd& x_hat, ActiveSets* warm = nullptr) const;
  void project_in_place(Eigen::Ref<Eigen::MatrixXd> x, ActiveSets* warm = nullptr) const;

  const KinematicMetric& metric() const { return metric_; }
  const LinearObservation& observation() const { return obs_; }
  bool has_observation() const { return has_obs_; }

  // Bookkeeping for tests and benchmarks.
  int64_t factorizations() const { return factorizations_; }  // LLTs computed so far
  int64_t structure_builds() const { return structure_builds_; }
  int groups() const { return static_cast<int>(groups_.size()); }
  int distinct_factors() const;  // factorisations the current groups use
  int largest_group() const;
  int jittered_groups() const;
  int inequality_groups() const;            // groups that hold inequality rows
  int64_t qp_solves() const { return qp_solves_; }          // (group, column) QPs run so far
  int64_t qp_iterations() const { return qp_iterations_; }  // rows added or dropped in them

 private:
  // What a group's system depends on: its rows relative to its blocks.
  struct Factor {
    std::string key;         // Group::structure + the rows' variances
    Eigen::MatrixXd m0;      // C_c R^-1 C_c^T over all rows, equalities first (lower triangle is what LLT reads)
    Eigen::MatrixXd w;       // W_c = R^-1 C_c^T on the touched blocks: (J * blocks) x m_c
    Eigen::MatrixXd gain_t;  // equality rows: M_EE^-1 W_E^T: m_E x (J * blocks)
    bool jittered = false;
    // Groups with inequality rows only.
    Eigen::MatrixXd m;           // M = m0 + Sigma over all rows
    Eigen::MatrixXd l_eq;        // Cholesky factor (lower) of M_EE as factorised (jitter included)
    Eigen::MatrixXd eq_to_ineq;  // M_EE^-1 M_EI: inequality values after the equality update, plus -r_I
  };
  struct Group {
    std::vector<int> rows;    // global row indices of A
    std::vector<int> g_rows;  // global row indices of G (empty: no inequalities)
    std::vector<int> blocks;  // (frame, axis) blocks touched: frame * 3 + axis
    std::string structure;    // key of C_c relative to the blocks (no variances)
    int factor = -1;          // index into factors_
  };
  void build_structure();
  int factor_for(const Group& g);  // finds or computes the factor of g's structure + variances
  void factorise(Factor& f, const std::vector<double>& variance, int equalities);
  bool same_operator(const LinearObservation& obs) const;
  [[noreturn]] void fail_infeasible(const Group& g, const std::vector<int>& local_rows) const;

  KinematicMetric metric_;
  LinearObservation obs_;
  bool has_obs_ = false;
  std::vector<Group> groups_;
  std::vector<Factor> factors_;
  std::unordered_map<std::string, int> factor_index_;  // structure + variances -> factor
  int64_t factorizations_ = 0, structure_builds_ = 0;
  mutable int64_t qp_solves_ = 0, qp_iterations_ = 0;
};

// Dense reference for tests: forms R and A as dense matrices and solves eq. (7)
// directly. Only for small problems (d = 3JT of a few hundred).
Eigen::MatrixXd dense_reference_projection(const KinematicMetric& metric, const LinearObservation& obs,
                                           const Eigen::MatrixXd& x_hat);

}  // namespace mc
