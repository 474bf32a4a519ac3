// Structured solver for the ProjFlow projection (eq. (7)) plus its dense reference.
#include "control/projection_solver.h"

#include <algorithm>
#include <map>
#include <set>
#include <stdexcept>
#include <string>

#include <fmt/format.h>

#include "control/active_set_qp.h"
#include "core/error.h"

namespace mc {

namespace {
using RowIter = Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator;

template <class A, class B>
bool same_array(const A* a, const B* b, Eigen::Index n) {
  return (a == nullptr) == (b == nullptr) && (n == 0 || std::equal(a, a + n, b));
}

// dst = src^T in cache-sized tiles; Eigen's plain transpose copy walks one side
// with a stride of a whole column, which dominated batched projections.
template <class Src, class Dst>
void transpose_tiled(const Src& src, Dst& dst) {
  constexpr Eigen::Index tile = 32;
  for (Eigen::Index c0 = 0; c0 < src.cols(); c0 += tile)
    for (Eigen::Index r0 = 0; r0 < src.rows(); r0 += tile) {
      const Eigen::Index nr = std::min(tile, src.rows() - r0), nc = std::min(tile, src.cols() - c0);
      dst.block(c0, r0, nc, nr) = src.block(r0, c0, nr, nc).transpose();
    }
}

// Column i = (t*J + j)*3 + c lies in block t*3 + c at joint j.
int block_of(Eigen::Index col, int J) { return static_cast<int>((col / (3 * J)) * 3 + col % 3); }
int joint_of(Eigen::Index col, int J) { return static_cast<int>((col / 3) % J); }
}  // namespace

ProjectionSolver::ProjectionSolver(KinematicMetric metric) : metric_(std::move(metric)) {}

int ProjectionSolver::largest_group() const {
  size_t n = 0;
  for (auto& g : groups_) n = std::max(n, g.rows.size());
  return static_cast<int>(n);
}

int ProjectionSolver::distinct_factors() const {
  std::vector<char> used(factors_.size(), 0);
  for (auto& g : groups_)
    if (g.factor >= 0) used[g.factor] = 1;
  return static_cast<int>(std::count(used.begin(), used.end(), 1));
}

int ProjectionSolver::inequality_groups() const {
  return static_cast<int>(std::count_if(groups_.begin(), groups_.end(), [](const Group& g) { return !g.g_rows.empty(); }));
}

int ProjectionSolver::jittered_groups() const {
  return static_cast<int>(std::count_if(groups_.begin(), groups_.end(), [&](const Group& g) {
    return g.factor >= 0 && factors_[g.factor].jittered;
  }));
}

bool ProjectionSolver::same_operator(const LinearObservation& o) const {
  auto same = [](const Eigen::SparseMatrix<double, Eigen::RowMajor>& a,
                 const Eigen::SparseMatrix<double, Eigen::RowMajor>& b) {
    return a.rows() == b.rows() && a.cols() == b.cols() && a.nonZeros() == b.nonZeros() &&
           same_array(a.outerIndexPtr(), b.outerIndexPtr(), a.outerSize() + 1) &&
           same_array(a.innerIndexPtr(), b.innerIndexPtr(), a.nonZeros()) &&
           same_array(a.valuePtr(), b.valuePtr(), a.nonZeros());
  };
  // The inequality rows' variances are part of their factors; the targets y and h are not.
  return obs_.frames == o.frames && obs_.joints == o.joints && same(obs_.A, o.A) &&
         obs_.inequalities() == o.inequalities() && (o.inequalities() == 0 || same(obs_.G, o.G)) &&
         obs_.g_variance.size() == o.g_variance.size() && obs_.g_variance == o.g_variance;
}

void ProjectionSolver::set_observation(const LinearObservation& obs) {
  if (obs.joints != metric_.joints())
    throw std::invalid_argument(
        fmt::format("projection: observation has {} joints, the metric {}", obs.joints, metric_.joints()));
  if (obs.A.cols() != obs.dim() || obs.y.size() != obs.A.rows() || obs.variance.size() != obs.A.rows())
    throw std::invalid_argument(fmt::format("projection: inconsistent observation (A {}x{}, y {}, variance {}, d {})",
                                            obs.A.rows(), obs.A.cols(), obs.y.size(), obs.variance.size(), obs.dim()));
  if (!obs.variance.allFinite() || (obs.variance.array() < 0).any())
    throw std::invalid_argument("projection: variances must be finite and >= 0");
  const int p = obs.inequalities();
  if (p > 0 && (obs.G.rows() != p || obs.G.cols() != obs.dim() || obs.g_variance.size() != p))
    throw std::invalid_argument(fmt::format("projection: inconsistent inequalities (G {}x{}, h {}, variance {}, d {})",
                                            obs.G.rows(), obs.G.cols(), p, obs.g_variance.size(), obs.dim()));
  if (p > 0 && (!obs.h.allFinite() || !obs.g_variance.allFinite() || (obs.g_variance.array() < 0).any()))
    throw std::invalid_argument("projection: inequality bounds must be finite, their variances finite and >= 0");
  LinearObservation copy = obs;
  copy.A.makeCompressed();
  if (p > 0) copy.G.makeCompressed();
  else copy.G.resize(0, obs.dim()), copy.h.resize(0), copy.g_variance.resize(0);
  if (has_obs_ && same_operator(copy)) {
    // Same A: the factors depend only on A, R and Sigma.
    Eigen::VectorXd variance = copy.variance;
    copy.variance = obs_.variance;
    obs_ = std::move(copy);
    update_variance(variance);
    return;
  }
  obs_ = std::move(copy);
  has_obs_ = true;
  build_structure();
}

void ProjectionSolver::update_targets(const Eigen::VectorXd& y) {
  if (!has_obs_ || y.size() != obs_.rows())
    throw std::invalid_argument(fmt::format("projection: update_targets needs {} targets, got {}", obs_.rows(), y.size()));
  obs_.y = y;
}

void ProjectionSolver::update_variance(const Eigen::VectorXd& variance) {
  if (!has_obs_ || variance.size() != obs_.rows())
    throw std::invalid_argument(
        fmt::format("projection: update_variance needs {} variances, got {}", obs_.rows(), variance.size()));
  if (!variance.allFinite() || (variance.array() < 0).any())
    throw std::invalid_argument("projection: variances must be finite and >= 0");
  bool any = false;
  for (Group& g : groups_) {
    bool changed = false;
    for (int r : g.rows) changed |= variance[r] != obs_.variance[r];
    if (!changed) continue;
    for (int r : g.rows) obs_.variance[r] = variance[r];
    if (!g.blocks.empty()) g.factor = factor_for(g), any = true;
  }
  obs_.variance = variance;  // rows of entry-less groups too
  if (!any) return;
  // Drop factors no group uses any more, so repeated updates do not accumulate them.
  std::vector<int> remap(factors_.size(), -1);
  std::vector<Factor> kept;
  for (auto& g : groups_) {
    if (g.factor < 0) continue;
    if (remap[g.factor] < 0) remap[g.factor] = static_cast<int>(kept.size()), kept.push_back(std::move(factors_[g.factor]));
    g.factor = remap[g.factor];
  }
  factors_ = std::move(kept);
  factor_index_.clear();
  for (size_t i = 0; i < factors_.size(); ++i) factor_index_.emplace(factors_[i].key, static_cast<int>(i));
}

namespace {
template <class T>
void append_bytes(std::string& key, T v) {
  key.append(reinterpret_cast<const char*>(&v), sizeof v);
}
}  // namespace

void ProjectionSolver::build_structure() {
  ++structure_builds_;
  groups_.clear();
  factors_.clear();
  factor_index_.clear();
  const int J = obs_.joints;
  std::vector<int> local_block(3 * obs_.frames, -1);
  auto row_groups = coupled_groups(obs_);
  groups_.reserve(row_groups.size());
  for (auto& rg : row_groups) {
    Group g;
    g.rows = std::move(rg.rows);
    g.g_rows = std::move(rg.g_rows);
    auto touch = [&](const Eigen::SparseMatrix<double, Eigen::RowMajor>& M, int r) {
      for (RowIter it(M, r); it; ++it) {
        int b = block_of(it.col(), J);
        if (local_block[b] < 0) local_block[b] = static_cast<int>(g.blocks.size()), g.blocks.push_back(b);
      }
    };
    for (int r : g.rows) touch(obs_.A, r);
    for (int r : g.g_rows) touch(obs_.G, r);
    // The group's rows relative to its blocks: everything M_c and W_c depend on
    // besides R. Two groups with the same key (e.g. the same joints at two
    // frames) get the same factorisation.
    append_bytes(g.structure, static_cast<int>(g.rows.size()));
    append_bytes(g.structure, static_cast<int>(g.g_rows.size()));
    append_bytes(g.structure, static_cast<int>(g.blocks.size()));
    auto key_row = [&](const Eigen::SparseMatrix<double, Eigen::RowMajor>& M, int r) {
      append_bytes(g.structure, static_cast<int>(M.outerIndexPtr()[r + 1] - M.outerIndexPtr()[r]));
      for (RowIter it(M, r); it; ++it) {
        append_bytes(g.structure, local_block[block_of(it.col(), J)] * J + joint_of(it.col(), J));
        append_bytes(g.structure, it.value());
      }
    };
    for (int r : g.rows) key_row(obs_.A, r);
    for (int r : g.g_rows) key_row(obs_.G, r);
    for (int b : g.blocks) local_block[b] = -1;
    if (!g.blocks.empty()) g.factor = factor_for(g);
    groups_.push_back(std::move(g));
  }
}

int ProjectionSolver::factor_for(const Group& g) {
  std::string key = g.structure;
  std::vector<double> variance;
  for (int r : g.rows) variance.push_back(obs_.variance[r]), append_bytes(key, obs_.variance[r]);
  for (int r : g.g_rows) variance.push_back(obs_.g_variance[r]), append_bytes(key, obs_.g_variance[r]);
  auto found = factor_index_.find(key);
  if (found != factor_index_.end()) return found->second;

  const int J = obs_.joints, mE = static_cast<int>(g.rows.size()), m = mE + static_cast<int>(g.g_rows.size());
  const int nb = static_cast<int>(g.blocks.size());
  // Local row k: equality row g.rows[k] for k < mE, inequality row g.g_rows[k - mE] after.
  auto row_iter = [&](int k) { return k < mE ? RowIter(obs_.A, g.rows[k]) : RowIter(obs_.G, g.g_rows[k - mE]); };
  const bool euclidean = metric_.is_euclidean();
  const Eigen::MatrixXd& k_inv = metric_.block_inverse();
  auto local = [&](Eigen::Index col) {
    const int b = block_of(col, J);
    return static_cast<int>(std::find(g.blocks.begin(), g.blocks.end(), b) - g.blocks.begin());
  };
  Factor f;
  f.key = std::move(key);
  // W = R^-1 A_c^T on the touched blocks: row k of A_c with entry a at joint j
  // of block b adds a * (column j of K^-1) to column k of W in block b.
  f.w = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(J) * nb, m);
  for (int k = 0; k < m; ++k)
    for (RowIter it = row_iter(k); it; ++it) {
      const int b = local(it.col()), j = joint_of(it.col(), J);
      if (euclidean) f.w(b * J + j, k) += it.value();
      else f.w.block(b * J, k, J, 1) += it.value() * k_inv.col(j);
    }
  // M0 = C_c W: only the rows of W that C_c's entries hit contribute.
  f.m0 = Eigen::MatrixXd::Zero(m, m);
  for (int k = 0; k < m; ++k)
    for (RowIter it = row_iter(k); it; ++it) f.m0.row(k) += it.value() * f.w.row(local(it.col()) * J + joint_of(it.col(), J));
  factorise(f, variance, mE);
  factors_.push_back(std::move(f));
  factor_index_.emplace(factors_.back().key, static_cast<int>(factors_.size()) - 1);
  return static_cast<int>(factors_.size()) - 1;
}

void ProjectionSolver::factorise(Factor& f, const std::vector<double>& variance_all, int equalities) {
  ++factorizations_;
  const int m_all = static_cast<int>(variance_all.size()), m = equalities, mI = m_all - m;
  const std::vector<double> variance(variance_all.begin(), variance_all.begin() + m);
  f.jittered = false;
  if (m == 0) {  // inequalities only: the equality update is empty
    f.gain_t.resize(0, f.w.rows());
    f.l_eq.resize(0, 0);
    f.eq_to_ineq.resize(0, mI);
    f.m = f.m0;
    for (int k = 0; k < m_all; ++k) f.m(k, k) += variance_all[k];
    return;
  }
  Eigen::MatrixXd M = f.m0.topLeftCorner(m, m);
  for (int k = 0; k < m; ++k) M(k, k) += variance[k];
  Eigen::LLT<Eigen::MatrixXd> llt(M);
  auto ill_conditioned = [&]() {
    if (llt.info() != Eigen::Success) return true;
    const Eigen::VectorXd pivots = llt.matrixLLT().diagonal();
    return pivots.minCoeff() * pivots.minCoeff() < 1e-13 * M.diagonal().maxCoeff();
  };
  if (ill_conditioned()) {
    const double mean_diag = M.diagonal().mean();
    const double jitter = 1e-8 * (mean_diag > 0 ? mean_diag : 1.0);
    for (int k = 0; k < m; ++k)
      if (variance[k] == 0.0) M(k, k) += jitter;
    llt.compute(M);
    f.jittered = true;
    if (llt.info() != Eigen::Success)
      throw std::runtime_error("projection: A R^-1 A^T + Sigma is not positive definite even with jitter");
  }
  // Kalman-style gain (transposed) M_c^-1 W_c^T, so a projection is one product per group.
  f.gain_t = llt.solve(f.w.leftCols(m).transpose());
  if (mI == 0) return;
  // The QP's data: M over all rows (the factorised equality block, jitter included),
  // its equality factor, and what the equality update does to the inequality values.
  f.m = f.m0;
  for (int k = 0; k < m_all; ++k) f.m(k, k) += variance_all[k];
  f.m.topLeftCorner(m, m) = M;
  f.l_eq = llt.matrixL();
  f.eq_to_ineq = llt.solve(f.m0.block(0, m, m, mI));
}

void ProjectionSolver::project_in_place(Eigen::Ref<Eigen::MatrixXd> x, ActiveSets* warm) const {
  if (!has_obs_) throw std::logic_error("projection: set_observation() first");
  if (x.rows() != obs_.dim())
    throw std::invalid_argument(fmt::format("projection: x has {} rows, the observation needs d = {}", x.rows(), obs_.dim()));
  const int J = obs_.joints;
  const Eigen::Index S = x.cols();
  // Samples x d: one coordinate of every sample is a contiguous column.
  Eigen::MatrixXd xt(S, x.rows());
  transpose_tiled(x, xt);
  // Residuals y - A x_hat, all taken before any update: groups touch disjoint blocks.
  Eigen::MatrixXd rt(S, obs_.rows());
  for (int r = 0; r < obs_.rows(); ++r) {
    auto col = rt.col(r);
    col.setConstant(obs_.y[r]);
    for (RowIter it(obs_.A, r); it; ++it) col -= it.value() * xt.col(it.col());
  }
  // The same for the inequality rows: h - G x_hat.
  const int p = obs_.inequalities();
  Eigen::MatrixXd gt(S, p);
  for (int r = 0; r < p; ++r) {
    auto col = gt.col(r);
    col.setConstant(obs_.h[r]);
    for (RowIter it(obs_.G, r); it; ++it) col -= it.value() * xt.col(it.col());
  }
  std::vector<std::vector<int>> active(warm ? S : 0);
  if (warm && static_cast<Eigen::Index>(warm->columns.size()) != S) warm->columns.assign(S, {});
  Eigen::MatrixXd rc, dt, ri, ci;
  Eigen::VectorXd r_all, lambda_eq, delta, dx;
  std::vector<int> warm_local;
  for (const Group& g : groups_) {
    if (g.factor < 0) continue;
    const Factor& f = factors_[g.factor];
    const int m = static_cast<int>(g.rows.size()), mI = static_cast<int>(g.g_rows.size());
    auto scatter = [&](Eigen::Index row0, Eigen::Index rows, const auto& update) {  // update: rows x (J * blocks)
      for (size_t b = 0; b < g.blocks.size(); ++b) {
        const int t = g.blocks[b] / 3, c = g.blocks[b] % 3;
        for (int j = 0; j < J; ++j)
          xt.col((t * J + j) * 3 + c).segment(row0, rows) += update.col(static_cast<Eigen::Index>(b) * J + j);
      }
    };
    rc.resize(S, m);
    for (int k = 0; k < m; ++k) rc.col(k) = rt.col(g.rows[k]);
    if (m > 0) {
      dt.noalias() = rc * f.gain_t;  // eq. (7): (R^-1 A_c^T M_c^-1 r)^T
      scatter(0, S, dt);
    }
    if (mI == 0) continue;
    // Inequality values after the equality update: c_I = r_E M_EE^-1 M_EI - r_I (<= 0 is feasible).
    ri.resize(S, mI);
    for (int k = 0; k < mI; ++k) ri.col(k) = gt.col(g.g_rows[k]);
    ci = -ri;
    if (m > 0) ci.noalias() += rc * f.eq_to_ineq;
    for (Eigen::Index s = 0; s < S; ++s) {
      bool violated = false;
      for (int k = 0; k < mI && !violated; ++k) violated = ci(s, k) > inequality_tolerance(ri(s, k));
      // Feasible after the equality update: that is the optimum, with nothing active.
      if (!violated) continue;
      warm_local.clear();
      if (warm)
        for (int row : warm->columns[s]) {
          auto pos = std::lower_bound(g.g_rows.begin(), g.g_rows.end(), row);
          if (pos != g.g_rows.end() && *pos == row) warm_local.push_back(m + static_cast<int>(pos - g.g_rows.begin()));
        }
      r_all.resize(m + mI);
      r_all.head(m) = rc.row(s).transpose();
      r_all.tail(mI) = ri.row(s).transpose();
      // The equality projection's multipliers M_EE^-1 r_E, through the group's factor.
      lambda_eq = r_all.head(m);
      if (m > 0) {
        f.l_eq.triangularView<Eigen::Lower>().solveInPlace(lambda_eq);
        f.l_eq.transpose().triangularView<Eigen::Upper>().solveInPlace(lambda_eq);
      }
      DualQpResult res = solve_dual_qp(f.m, r_all, m, f.l_eq, lambda_eq, warm_local);
      ++qp_solves_;
      qp_iterations_ += res.iterations;
      if (!res.feasible) fail_infeasible(g, res.conflict);
      delta = res.lambda;
      delta.head(m) -= lambda_eq;
      dx.noalias() = f.w * delta;  // the QP's correction on top of the equality update
      scatter(s, 1, dx.transpose());
      if (warm)
        for (int k : res.active) active[s].push_back(g.g_rows[k - m]);
    }
  }
  if (warm)
    for (Eigen::Index s = 0; s < S; ++s) {
      std::sort(active[s].begin(), active[s].end());
      warm->columns[s] = std::move(active[s]);
    }
  transpose_tiled(xt, x);
}

void ProjectionSolver::fail_infeasible(const Group& g, const std::vector<int>& local_rows) const {
  const int J = obs_.joints, m = static_cast<int>(g.rows.size());
  std::set<int> items, frames;
  for (int k : local_rows) {
    const bool eq = k < m;
    const int row = eq ? g.rows[k] : g.g_rows[k - m];
    const auto& owner = eq ? obs_.item_of_row : obs_.item_of_g_row;
    if (row < static_cast<int>(owner.size())) items.insert(owner[row]);
    for (RowIter it(eq ? obs_.A : obs_.G, row); it; ++it) frames.insert(static_cast<int>(it.col() / (3 * J)));
  }
  std::string names;
  int count = 0;
  for (int i : items) {
    ++count;
    names += (names.empty() ? "" : count == static_cast<int>(items.size()) ? " and " : ", ") +
             (i < static_cast<int>(obs_.item_labels.size()) ? obs_.item_labels[i] : fmt::format("item {}", i));
  }
  if (names.empty()) names = "hand-built rows";
  std::string frame_list;
  int shown = 0;
  for (int t : frames) {
    if (shown++ == 8) {
      frame_list += fmt::format(", ... ({} in all)", frames.size());
      break;
    }
    frame_list += (frame_list.empty() ? "" : ", ") + std::to_string(t);
  }
  fail("{}: infeasible constraints: no motion meets the hard rows of {} together (at frame{} {}); widen or remove "
       "one of the bounds, or make an item soft (variance > 0)",
       obs_.source, names, frames.size() > 1 ? "s" : "", frame_list);
}

Eigen::MatrixXd ProjectionSolver::project(const Eigen::MatrixXd& x_hat, ActiveSets* warm) const {
  Eigen::MatrixXd x = x_hat;
  project_in_place(x, warm);
  return x;
}

Eigen::MatrixXd dense_reference_projection(const KinematicMetric& metric, const LinearObservation& obs,
                                           const Eigen::MatrixXd& x_hat) {
  const Eigen::MatrixXd R = metric.dense(obs.frames);
  const Eigen::MatrixXd A = obs.A.toDense();
  const Eigen::MatrixXd r_inv_at = R.llt().solve(A.transpose());  // R^-1 A^T
  Eigen::MatrixXd M = A * r_inv_at;
  M.diagonal() += obs.variance;
  Eigen::MatrixXd residual = -(A * x_hat);
  residual.colwise() += obs.y;
  return x_hat + r_inv_at * M.ldlt().solve(residual);  // eq. (7)-(8)
}

}  // namespace mc
