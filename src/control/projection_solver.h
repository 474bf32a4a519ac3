// The ProjFlow correction (eq. (7)): x' = x_hat + R^-1 A^T (A R^-1 A^T + Sigma)^-1 (y - A x_hat),
// solved per group of coupled rows without forming anything of size d x d, with
// the factorisations cached while A and Sigma stay the same. With inequality rows
// (G x <= h, issue 20) it is the R-metric projection onto the equality set
// intersected with the half-spaces: an exact QP over the inequality rows alone, in
// the range space the equality factorisations leave (control/active_set_qp.h).
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
// Inequalities. The equality groups stay as they are. After the equality update
// x_e, what is left is min |x - x_e|_P^-1 over G x <= h with P = R^-1 - R^-1 A^T
// M^-1 A R^-1 the equality projection's posterior covariance: P is block-diagonal
// over the equality groups (and R^-1 on blocks no row touches), so two inequality
// rows interact only when they touch a common group or block. Such "components" of
// inequality rows keep U = P G_c^T (stored per row as pieces on the blocks it
// reaches, built from the groups' W and gains: nothing new is factorised) and
// M' = G_c U + Sigma_c, sparse (rows meet only through blocks they share; its
// pattern and the pieces' layout are built once per structure, and a variance update
// only recomputes their numbers). A projection reads G x_e - h for every column and runs the
// dual active-set QP on (M', h - G x_e) only for the columns with a violated row;
// then x = x_e + U lambda. Exact: hard equalities hold to solver precision, hard
// inequalities to ~1e-11 of their residual, whatever the warm start. A hard row
// that the hard equalities and other hard rows rule out is a UserError naming them.
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
  int inequality_components() const { return static_cast<int>(components_.size()); }
  int largest_component() const;                          // inequality rows in the largest one
  int64_t qp_solves() const { return qp_solves_; }          // (component, column) QPs run so far
  int64_t qp_iterations() const { return qp_iterations_; }  // rows added or dropped in them

 private:
  // What a group's system depends on: its rows relative to its blocks.
  struct Factor {
    std::string key;         // Group::structure + the rows' variances
    Eigen::MatrixXd m0;      // A_c R^-1 A_c^T (lower triangle is what LLT reads)
    Eigen::MatrixXd w;       // W_c = R^-1 A_c^T on the touched blocks: (J * blocks) x m_c
    Eigen::MatrixXd gain_t;  // G_c^T = M_c^-1 W_c^T: m_c x (J * blocks)
    bool jittered = false;
  };
  struct Group {
    std::vector<int> rows;    // global row indices
    std::vector<int> blocks;  // (frame, axis) blocks touched: frame * 3 + axis
    std::string structure;    // key of A_c relative to the blocks (no variances)
    int factor = -1;          // index into factors_
  };
  // Inequality rows coupled through P (see the class comment).
  struct Piece {
    int block = 0;          // frame * 3 + axis
    Eigen::VectorXd value;  // J entries of P g^T on that block
  };
  // What refresh_component recomputes numbers for, fixed when the structure is built.
  struct RowEntry {  // an entry a of g at joint `joint` of the row's piece `piece`
    int piece = 0, joint = 0;
    double a = 0;
  };
  struct RowGroup {  // an equality group the row reaches
    int group = 0;
    std::vector<std::pair<int, double>> gain_cols;  // (column of the group's gain_t, entry of g)
    std::vector<int> piece_of_block;                // the group's local block -> the row's piece
  };
  struct MTerm {  // M'(k, l) (and (l, k)) += a * u[l][piece].value[joint], k <= l
    int slot = 0, mirror = 0;  // value indices of (k, l) and (l, k) in m
    int l = 0, piece = 0, joint = 0;
    double a = 0;
  };
  struct Component {
    std::vector<int> g_rows;                     // global rows of G, ascending
    std::vector<int> groups;                     // equality groups (indices into groups_) the rows reach
    std::vector<std::vector<Piece>> u;           // per row: P g^T, pieces sorted by block
    std::vector<std::vector<RowEntry>> entries;  // per row
    std::vector<std::vector<RowGroup>> reach;    // per row
    std::vector<MTerm> terms;                    // M' = G_c U, entry by entry (pairs sharing a block)
    std::vector<int> diagonal;                   // value index of (k, k) in m
    Eigen::SparseMatrix<double> m;               // M' = G_c P G_c^T + Sigma_c, sparse, both triangles
    Eigen::VectorXd scale;                       // per row g R^-1 g^T + variance: the dependency test's scale
  };
  void build_structure();
  void build_components();
  void build_component(Component& c);  // its pieces, entries and M' pattern (structure only)
  void refresh_component(Component& c);
  int factor_for(const Group& g);  // finds or computes the factor of g's structure + variances
  void factorise(Factor& f, const std::vector<double>& variance);
  bool same_operator(const LinearObservation& obs) const;
  [[noreturn]] void fail_infeasible(const Component& c, const std::vector<int>& local_rows) const;

  KinematicMetric metric_;
  LinearObservation obs_;
  bool has_obs_ = false;
  std::vector<Group> groups_;
  std::vector<Factor> factors_;
  std::unordered_map<std::string, int> factor_index_;  // structure + variances -> factor
  std::vector<int> group_of_block_;     // (frame, axis) block -> equality group holding it, -1
  std::vector<Component> components_;
  std::vector<int> component_of_group_;  // equality group -> the component whose rows reach it, -1
  int64_t factorizations_ = 0, structure_builds_ = 0;
  mutable int64_t qp_solves_ = 0, qp_iterations_ = 0;
};

// Dense reference for tests: forms R and A as dense matrices and solves eq. (7)
// directly. Only for small problems (d = 3JT of a few hundred).
Eigen::MatrixXd dense_reference_projection(const KinematicMetric& metric, const LinearObservation& obs,
                                           const Eigen::MatrixXd& x_hat);

}  // namespace mc
