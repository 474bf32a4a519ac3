// Structured solver for the ProjFlow projection (eq. (7)) plus its dense reference.
#include "control/projection_solver.h"

#include <algorithm>
#include <stdexcept>
#include <string>

#include <fmt/format.h>

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

int ProjectionSolver::jittered_groups() const {
  return static_cast<int>(std::count_if(groups_.begin(), groups_.end(), [&](const Group& g) {
    return g.factor >= 0 && factors_[g.factor].jittered;
  }));
}

bool ProjectionSolver::same_operator(const LinearObservation& o) const {
  const auto& a = obs_.A;
  const auto& b = o.A;
  return obs_.frames == o.frames && obs_.joints == o.joints && a.rows() == b.rows() && a.cols() == b.cols() &&
         a.nonZeros() == b.nonZeros() && same_array(a.outerIndexPtr(), b.outerIndexPtr(), a.outerSize() + 1) &&
         same_array(a.innerIndexPtr(), b.innerIndexPtr(), a.nonZeros()) &&
         same_array(a.valuePtr(), b.valuePtr(), a.nonZeros());
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
  LinearObservation copy = obs;
  copy.A.makeCompressed();
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
  auto row_groups = coupled_row_groups(obs_);
  groups_.reserve(row_groups.size());
  for (auto& rows : row_groups) {
    Group g;
    g.rows = std::move(rows);
    for (int r : g.rows)
      for (RowIter it(obs_.A, r); it; ++it) {
        int b = block_of(it.col(), J);
        if (local_block[b] < 0) local_block[b] = static_cast<int>(g.blocks.size()), g.blocks.push_back(b);
      }
    // The group's rows relative to its blocks: everything M_c and W_c depend on
    // besides R. Two groups with the same key (e.g. the same joints at two
    // frames) get the same factorisation.
    append_bytes(g.structure, static_cast<int>(g.rows.size()));
    append_bytes(g.structure, static_cast<int>(g.blocks.size()));
    for (int r : g.rows) {
      append_bytes(g.structure, static_cast<int>(obs_.A.outerIndexPtr()[r + 1] - obs_.A.outerIndexPtr()[r]));
      for (RowIter it(obs_.A, r); it; ++it) {
        append_bytes(g.structure, local_block[block_of(it.col(), J)] * J + joint_of(it.col(), J));
        append_bytes(g.structure, it.value());
      }
    }
    for (int b : g.blocks) local_block[b] = -1;
    if (!g.blocks.empty()) g.factor = factor_for(g);
    groups_.push_back(std::move(g));
  }
}

int ProjectionSolver::factor_for(const Group& g) {
  std::string key = g.structure;
  std::vector<double> variance;
  for (int r : g.rows) variance.push_back(obs_.variance[r]), append_bytes(key, obs_.variance[r]);
  auto found = factor_index_.find(key);
  if (found != factor_index_.end()) return found->second;

  const int J = obs_.joints, m = static_cast<int>(g.rows.size()), nb = static_cast<int>(g.blocks.size());
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
    for (RowIter it(obs_.A, g.rows[k]); it; ++it) {
      const int b = local(it.col()), j = joint_of(it.col(), J);
      if (euclidean) f.w(b * J + j, k) += it.value();
      else f.w.block(b * J, k, J, 1) += it.value() * k_inv.col(j);
    }
  // M0 = A_c W: only the rows of W that A_c's entries hit contribute.
  f.m0 = Eigen::MatrixXd::Zero(m, m);
  for (int k = 0; k < m; ++k)
    for (RowIter it(obs_.A, g.rows[k]); it; ++it) f.m0.row(k) += it.value() * f.w.row(local(it.col()) * J + joint_of(it.col(), J));
  factorise(f, variance);
  factors_.push_back(std::move(f));
  factor_index_.emplace(factors_.back().key, static_cast<int>(factors_.size()) - 1);
  return static_cast<int>(factors_.size()) - 1;
}

void ProjectionSolver::factorise(Factor& f, const std::vector<double>& variance) {
  ++factorizations_;
  const int m = static_cast<int>(variance.size());
  Eigen::MatrixXd M = f.m0;
  for (int k = 0; k < m; ++k) M(k, k) += variance[k];
  Eigen::LLT<Eigen::MatrixXd> llt(M);
  auto ill_conditioned = [&]() {
    if (llt.info() != Eigen::Success) return true;
    const Eigen::VectorXd pivots = llt.matrixLLT().diagonal();
    return pivots.minCoeff() * pivots.minCoeff() < 1e-13 * M.diagonal().maxCoeff();
  };
  f.jittered = false;
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
  f.gain_t = llt.solve(f.w.transpose());
}

void ProjectionSolver::project_in_place(Eigen::Ref<Eigen::MatrixXd> x) const {
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
  Eigen::MatrixXd rc, dt;
  for (const Group& g : groups_) {
    if (g.factor < 0) continue;
    const Factor& f = factors_[g.factor];
    const int m = static_cast<int>(g.rows.size());
    rc.resize(S, m);
    for (int k = 0; k < m; ++k) rc.col(k) = rt.col(g.rows[k]);
    dt.noalias() = rc * f.gain_t;  // eq. (7): (R^-1 A_c^T M_c^-1 r)^T
    for (size_t b = 0; b < g.blocks.size(); ++b) {
      const int t = g.blocks[b] / 3, c = g.blocks[b] % 3;
      for (int j = 0; j < J; ++j) xt.col((t * J + j) * 3 + c) += dt.col(static_cast<Eigen::Index>(b) * J + j);
    }
  }
  transpose_tiled(xt, x);
}

Eigen::MatrixXd ProjectionSolver::project(const Eigen::MatrixXd& x_hat) const {
  Eigen::MatrixXd x = x_hat;
  project_in_place(x);
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
