// Goldfarb-Idnani dual active-set method in range space, with an updated Cholesky
// factor of the active rows' M block (see active_set_qp.h).
#include "control/active_set_qp.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace mc {

void ActiveCholesky::reset(const Eigen::MatrixXd& l, int capacity) {
  k_ = static_cast<int>(l.rows());
  capacity_ = std::max(capacity, k_);
  const int n = std::min(capacity_, std::max(k_ + 8, 2 * k_));
  l_ = Eigen::MatrixXd::Zero(n, n);
  if (k_ > 0) l_.topLeftCorner(k_, k_) = l.triangularView<Eigen::Lower>();
}

Eigen::VectorXd ActiveCholesky::forward(const Eigen::VectorXd& v) const {
  if (k_ == 0) return Eigen::VectorXd(0);
  return l_.topLeftCorner(k_, k_).triangularView<Eigen::Lower>().solve(v);
}

void ActiveCholesky::backward_in_place(Eigen::Ref<Eigen::VectorXd> w) const {
  if (k_ == 0) return;
  l_.topLeftCorner(k_, k_).transpose().triangularView<Eigen::Upper>().solveInPlace(w);
}

void ActiveCholesky::solve_in_place(Eigen::Ref<Eigen::VectorXd> b) const {
  if (k_ == 0) return;
  auto L = l_.topLeftCorner(k_, k_);
  L.triangularView<Eigen::Lower>().solveInPlace(b);
  L.transpose().triangularView<Eigen::Upper>().solveInPlace(b);
}

void ActiveCholesky::append(const Eigen::VectorXd& w, double s) {
  if (k_ >= capacity_) throw std::logic_error("ActiveCholesky: capacity exceeded");
  if (k_ >= l_.rows()) {  // grow, keeping the factor (the rest of the storage stays zero)
    const int n = std::min(capacity_, std::max(k_ + 8, 2 * k_));
    Eigen::MatrixXd grown = Eigen::MatrixXd::Zero(n, n);
    grown.topLeftCorner(k_, k_) = l_.topLeftCorner(k_, k_);
    l_.swap(grown);
  }
  if (k_ > 0) l_.row(k_).head(k_) = w.transpose();
  l_(k_, k_) = std::sqrt(s);
  ++k_;
}

void ActiveCholesky::remove(int q) {
  if (q < 0 || q >= k_) throw std::logic_error("ActiveCholesky: no such active row");
  // Without row q, the trailing block must absorb its column: L33' L33'^T = L33 L33^T + l l^T.
  const int n = k_ - q - 1;
  Eigen::VectorXd x = l_.col(q).segment(q + 1, n);
  for (int j = 0; j < n; ++j) {
    const int jj = q + 1 + j;
    const double d = l_(jj, jj);
    const double r = std::hypot(d, x[j]);
    const double c = r / d, s = x[j] / d;
    l_(jj, jj) = r;
    for (int i = j + 1; i < n; ++i) {
      const int ii = q + 1 + i;
      l_(ii, jj) = (l_(ii, jj) + s * x[i]) / c;
      x[i] = c * x[i] - s * l_(ii, jj);
    }
  }
  for (int i = q + 1; i < k_; ++i) {
    for (int j = 0; j < q; ++j) l_(i - 1, j) = l_(i, j);
    for (int j = q + 1; j <= i; ++j) l_(i - 1, j - 1) = l_(i, j);
  }
  l_.row(k_ - 1).setZero();
  l_.col(k_ - 1).setZero();
  --k_;
}

namespace {

constexpr double kDependent = 1e-10;  // Schur complement / M_pp below this: the row depends on the active ones

}  // namespace

DualQpResult solve_dual_qp(const Eigen::SparseMatrix<double>& M, const Eigen::VectorXd& r,
                           const std::vector<int>& warm, const Eigen::VectorXd& scale_in) {
  using ColIter = Eigen::SparseMatrix<double>::InnerIterator;
  const int m = static_cast<int>(M.rows());
  if (M.cols() != m || r.size() != m || (scale_in.size() != 0 && scale_in.size() != m))
    throw std::invalid_argument("solve_dual_qp: inconsistent sizes");
  Eigen::VectorXd diag = Eigen::VectorXd::Zero(m);
  for (int j = 0; j < m; ++j)
    for (ColIter it(M, j); it; ++it)
      if (it.row() == j) diag[j] = it.value();
  const Eigen::VectorXd& scale = scale_in.size() ? scale_in : diag;
  DualQpResult out;
  Eigen::VectorXd& lambda = out.lambda;
  lambda = Eigen::VectorXd::Zero(m);
  std::vector<int> act;  // active rows in the factor's order
  std::vector<int> position(m, -1);  // row -> its position in act, -1 inactive
  ActiveCholesky chol;
  chol.reset(Eigen::MatrixXd(0, 0), m);
  auto column = [&](int p) {  // M_{A, p}: column p's entries at the active rows
    Eigen::VectorXd v = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(act.size()));
    for (ColIter it(M, p); it; ++it)
      if (position[it.row()] >= 0) v[position[it.row()]] = it.value();
    return v;
  };
  auto remove_position = [&](size_t q) {
    lambda[act[q]] = 0.0;
    position[act[q]] = -1;
    chol.remove(static_cast<int>(q));
    act.erase(act.begin() + static_cast<std::ptrdiff_t>(q));
    for (size_t k = q; k < act.size(); ++k) position[act[k]] = static_cast<int>(k);
    ++out.iterations;
  };

  // Warm start: the previous active rows, kept while independent and correctly signed.
  if (!warm.empty()) {
    for (int i : warm) {
      if (i < 0 || i >= m || position[i] >= 0) continue;
      Eigen::VectorXd w = chol.forward(column(i));
      const double s = diag[i] - w.squaredNorm();
      if (!(s > kDependent * scale[i])) continue;
      chol.append(w, s);
      position[i] = static_cast<int>(act.size());
      act.push_back(i);
    }
    while (true) {
      Eigen::VectorXd b(act.size());
      for (size_t k = 0; k < act.size(); ++k) b[static_cast<Eigen::Index>(k)] = r[act[k]];
      chol.solve_in_place(b);
      for (size_t k = 0; k < act.size(); ++k) lambda[act[k]] = b[static_cast<Eigen::Index>(k)];
      // An active row must push (lambda <= 0); drop the worst offender and re-solve.
      size_t worst = act.size();
      double worst_value = 0.0;
      for (size_t k = 0; k < act.size(); ++k)
        if (lambda[act[k]] > worst_value) worst_value = lambda[act[k]], worst = k;
      if (worst == act.size()) break;
      remove_position(worst);
    }
  }

  Eigen::VectorXd m_lambda = M * lambda;  // kept current: c = M lambda - r
  auto add_column = [&](int j, double a) {  // m_lambda += a M_{:, j}
    for (ColIter it(M, j); it; ++it) m_lambda[it.row()] += a * it.value();
  };
  const int max_iterations = 10 * (m + 10);
  while (true) {
    // The most violated inactive row, measured in the row's own norm.
    int p = -1;
    double best = 0.0;
    for (int i = 0; i < m; ++i) {
      if (position[i] >= 0) continue;
      const double c = m_lambda[i] - r[i];
      if (c <= inequality_tolerance(r[i])) continue;
      const double score = c / std::sqrt(std::max(diag[i], 1e-300));
      if (score > best) best = score, p = i;
    }
    if (p < 0) break;
    // Add p, dropping active rows that would change sign on the way.
    while (true) {
      if (++out.iterations > max_iterations)
        throw std::runtime_error("solve_dual_qp: no convergence (cycling active set); please report this input");
      const Eigen::VectorXd w = chol.forward(column(p));
      Eigen::VectorXd z = w;
      chol.backward_in_place(z);  // z = M_AA^-1 M_Ap
      const double s = diag[p] - w.squaredNorm();
      // lambda_A(t) = lambda_A + t z, lambda_p(t) = lambda_p - t; an active row blocks at lambda = 0.
      double t2 = std::numeric_limits<double>::infinity();
      size_t block = act.size();
      const double z_tol = 1e-12 * std::max(1.0, z.size() ? z.cwiseAbs().maxCoeff() : 0.0);
      for (size_t k = 0; k < act.size(); ++k) {
        const double zk = z[static_cast<Eigen::Index>(k)];
        if (zk <= z_tol) continue;
        const double ratio = -lambda[act[k]] / zk;
        if (ratio < t2) t2 = ratio, block = k;
      }
      const double c_p = m_lambda[p] - r[p];
      const bool dependent = !(s > kDependent * scale[p]);
      if (dependent && block == act.size()) {
        // p is a combination of active rows, none of which may give way: no point meets them all.
        out.feasible = false;
        out.conflict.push_back(p);
        const double zmax = z.size() ? z.cwiseAbs().maxCoeff() : 0.0;
        for (size_t k = 0; k < act.size(); ++k)
          if (std::abs(z[static_cast<Eigen::Index>(k)]) > 1e-9 * std::max(zmax, 1e-300)) out.conflict.push_back(act[k]);
        std::sort(out.conflict.begin(), out.conflict.end());
        return out;
      }
      const double t1 = dependent ? std::numeric_limits<double>::infinity() : std::max(0.0, c_p / s);
      const double t = std::min(t1, t2);
      // lambda and M lambda change by t (z on A, -1 at p): sparse columns only.
      for (size_t k = 0; k < act.size(); ++k) {
        const double dz = t * z[static_cast<Eigen::Index>(k)];
        lambda[act[k]] += dz;
        if (dz != 0.0) add_column(act[k], dz);
      }
      lambda[p] -= t;
      add_column(p, -t);
      if (t1 <= t2) {
        chol.append(w, s);
        position[p] = static_cast<int>(act.size());
        act.push_back(p);
        ++out.iterations;
        break;
      }
      // The blocking multiplier is (up to rounding) 0 after the step; set it exactly.
      add_column(act[block], -lambda[act[block]]);
      remove_position(block);
    }
  }
  out.active = act;
  std::sort(out.active.begin(), out.active.end());
  return out;
}

}  // namespace mc
