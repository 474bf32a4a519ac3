// Structured solver for the ProjFlow projection (eq. (7)) plus its dense reference,
// and the inequality QP on top of it (issue 20).
#include "control/projection_solver.h"

#include <algorithm>
#include <numeric>
#include <set>
#include <stdexcept>
#include <string>
#include <unordered_map>

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

int ProjectionSolver::largest_component() const {
  size_t n = 0;
  for (auto& c : components_) n = std::max(n, c.g_rows.size());
  return static_cast<int>(n);
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
  // The inequality rows and their variances shape the components; the bounds h do not.
  return obs_.frames == o.frames && obs_.joints == o.joints && same(obs_.A, o.A) &&
         obs_.inequalities() == o.inequalities() && same(obs_.G, o.G) && obs_.g_variance == o.g_variance;
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
  build_components();
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
  std::vector<char> stale(components_.size(), 0);  // components whose groups got new factors
  for (size_t gi = 0; gi < groups_.size(); ++gi) {
    Group& g = groups_[gi];
    bool changed = false;
    for (int r : g.rows) changed |= variance[r] != obs_.variance[r];
    if (!changed) continue;
    for (int r : g.rows) obs_.variance[r] = variance[r];
    if (!g.blocks.empty()) g.factor = factor_for(g), any = true;
    if (!component_of_group_.empty() && component_of_group_[gi] >= 0) stale[component_of_group_[gi]] = 1;
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
  for (size_t c = 0; c < components_.size(); ++c)
    if (stale[c]) refresh_component(components_[c]);
}

// ---------------------------------------------------------------- inequality components

void ProjectionSolver::build_components() {
  components_.clear();
  const int J = obs_.joints, blocks = 3 * obs_.frames, G = static_cast<int>(groups_.size());
  group_of_block_.assign(blocks, -1);
  component_of_group_.assign(groups_.size(), -1);
  for (int gi = 0; gi < G; ++gi)
    for (int b : groups_[gi].blocks) group_of_block_[b] = gi;
  const int p = obs_.inequalities();
  if (p == 0) return;
  // Union-find over P's blocks: an equality group's blocks are one node, any other
  // (frame, axis) block its own. Rows touching a common node share a component.
  std::vector<int> parent(G + blocks);
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int a) {
    while (parent[a] != a) a = parent[a] = parent[parent[a]];
    return a;
  };
  auto node = [&](Eigen::Index col) {
    const int b = block_of(col, J);
    return group_of_block_[b] >= 0 ? group_of_block_[b] : G + b;
  };
  for (int r = 0; r < p; ++r) {
    RowIter it(obs_.G, r);
    if (!it) continue;
    int root = find(node(it.col()));
    for (++it; it; ++it) {
      const int other = find(node(it.col()));
      if (other == root) continue;
      parent[std::max(root, other)] = std::min(root, other);
      root = std::min(root, other);
    }
  }
  std::unordered_map<int, int> index_of_root;
  for (int r = 0; r < p; ++r) {
    RowIter it(obs_.G, r);
    if (!it) continue;  // an entry-less row constrains nothing (compile never emits one)
    const int root = find(node(it.col()));
    auto [pos, fresh] = index_of_root.emplace(root, static_cast<int>(components_.size()));
    if (fresh) components_.emplace_back();
    Component& c = components_[pos->second];
    c.g_rows.push_back(r);
    for (RowIter e(obs_.G, r); e; ++e) {
      const int gi = group_of_block_[block_of(e.col(), J)];
      if (gi >= 0 && std::find(c.groups.begin(), c.groups.end(), gi) == c.groups.end()) c.groups.push_back(gi);
    }
  }
  for (size_t ci = 0; ci < components_.size(); ++ci) {
    for (int gi : components_[ci].groups) component_of_group_[gi] = static_cast<int>(ci);
    build_component(components_[ci]);
    refresh_component(components_[ci]);
  }
}

// The layout of U = P G_c^T and the pattern of M', fixed by A's groups and G: row k's
// pieces sit on the blocks its entries touch and on every block of each equality
// group it reaches (P's block there is dense); M'(k, l) is non-zero only when row k
// has an entry on a block of row l's pieces.
void ProjectionSolver::build_component(Component& c) {
  const int J = obs_.joints, n = static_cast<int>(c.g_rows.size());
  c.u.assign(n, {});
  c.entries.assign(n, {});
  c.reach.assign(n, {});
  for (int k = 0; k < n; ++k) {
    const int r = c.g_rows[k];
    std::vector<int> blocks, reached;
    for (RowIter it(obs_.G, r); it; ++it) {
      const int b = block_of(it.col(), J), gi = group_of_block_[b];
      blocks.push_back(b);
      if (gi >= 0 && std::find(reached.begin(), reached.end(), gi) == reached.end()) {
        reached.push_back(gi);
        blocks.insert(blocks.end(), groups_[gi].blocks.begin(), groups_[gi].blocks.end());
      }
    }
    std::sort(blocks.begin(), blocks.end());
    blocks.erase(std::unique(blocks.begin(), blocks.end()), blocks.end());
    auto piece_at = [&](int b) {
      return static_cast<int>(std::lower_bound(blocks.begin(), blocks.end(), b) - blocks.begin());
    };
    for (int b : blocks) c.u[k].push_back({b, Eigen::VectorXd::Zero(J)});
    for (RowIter it(obs_.G, r); it; ++it)
      c.entries[k].push_back({piece_at(block_of(it.col(), J)), joint_of(it.col(), J), it.value()});
    for (int gi : reached) {
      const Group& g = groups_[gi];
      RowGroup rg;
      rg.group = gi;
      for (RowIter it(obs_.G, r); it; ++it) {
        const int b = block_of(it.col(), J);
        if (group_of_block_[b] != gi) continue;
        const int lb = static_cast<int>(std::find(g.blocks.begin(), g.blocks.end(), b) - g.blocks.begin());
        rg.gain_cols.push_back({lb * J + joint_of(it.col(), J), it.value()});
      }
      for (int b : g.blocks) rg.piece_of_block.push_back(piece_at(b));
      c.reach[k].push_back(std::move(rg));
    }
  }
  // The pattern: block -> (row l, piece) covering it; pairs (k, l), k <= l, that meet.
  std::unordered_map<int, std::vector<std::pair<int, int>>> covering;
  for (int l = 0; l < n; ++l)
    for (int pi = 0; pi < static_cast<int>(c.u[l].size()); ++pi) covering[c.u[l][pi].block].push_back({l, pi});
  struct Raw {
    int k, l, piece, joint;
    double a;
  };
  std::vector<Raw> raw;
  std::vector<Eigen::Triplet<double>> pattern;
  for (int k = 0; k < n; ++k) {
    pattern.emplace_back(k, k, 0.0);
    for (const RowEntry& e : c.entries[k])
      for (const auto& [l, pi] : covering[c.u[k][e.piece].block]) {
        if (l < k) continue;
        raw.push_back({k, l, pi, e.joint, e.a});
        pattern.emplace_back(k, l, 0.0);
        pattern.emplace_back(l, k, 0.0);
      }
  }
  c.m.resize(n, n);
  c.m.setFromTriplets(pattern.begin(), pattern.end());  // duplicates sum to 0: the pattern only
  c.m.makeCompressed();
  auto slot = [&](int row, int col) {
    const int* begin = c.m.innerIndexPtr() + c.m.outerIndexPtr()[col];
    const int* end = c.m.innerIndexPtr() + c.m.outerIndexPtr()[col + 1];
    return static_cast<int>(std::lower_bound(begin, end, row) - c.m.innerIndexPtr());
  };
  c.terms.clear();
  c.terms.reserve(raw.size());
  for (const Raw& t : raw) c.terms.push_back({slot(t.k, t.l), slot(t.l, t.k), t.l, t.piece, t.joint, t.a});
  c.diagonal.resize(n);
  for (int k = 0; k < n; ++k) c.diagonal[k] = slot(k, k);
}

// U = P G_c^T with P = R^-1 - sum over groups W_g M_g^-1 W_g^T, one row at a time:
// R^-1 g^T from columns of K^-1, then per equality group the row reaches, the group's
// part W_g (M_g^-1 A_g R^-1 g^T) = W_g (gain_g^T restricted to g's entries) removed.
// M' = G_c U + Sigma_c on the pattern build_component laid out. Only the groups'
// existing factors are used.
void ProjectionSolver::refresh_component(Component& c) {
  const int J = obs_.joints, n = static_cast<int>(c.g_rows.size());
  const bool euclidean = metric_.is_euclidean();
  const Eigen::MatrixXd& k_inv = metric_.block_inverse();
  c.scale.resize(n);
  Eigen::VectorXd coef, wc;
  for (int k = 0; k < n; ++k) {
    std::vector<Piece>& pieces = c.u[k];
    for (Piece& pc : pieces) pc.value.setZero();
    for (const RowEntry& e : c.entries[k]) {
      if (euclidean) pieces[e.piece].value[e.joint] += e.a;
      else pieces[e.piece].value += e.a * k_inv.col(e.joint);
    }
    double norm = 0;  // g R^-1 g^T
    for (const RowEntry& e : c.entries[k]) norm += e.a * pieces[e.piece].value[e.joint];
    c.scale[k] = norm + obs_.g_variance[c.g_rows[k]];
    // Condition on each equality group the row reaches.
    for (const RowGroup& rg : c.reach[k]) {
      const Factor& f = factors_[groups_[rg.group].factor];
      coef.setZero(f.gain_t.rows());  // M_g^-1 A_g R^-1 g^T
      for (const auto& [col, a] : rg.gain_cols) coef += a * f.gain_t.col(col);
      wc.noalias() = f.w * coef;
      for (size_t lb = 0; lb < rg.piece_of_block.size(); ++lb)
        pieces[rg.piece_of_block[lb]].value -= wc.segment(static_cast<Eigen::Index>(lb) * J, J);
    }
  }
  double* values = c.m.valuePtr();
  std::fill(values, values + c.m.nonZeros(), 0.0);
  for (const MTerm& t : c.terms) values[t.slot] += t.a * c.u[t.l][t.piece].value[t.joint];
  for (const MTerm& t : c.terms) values[t.mirror] = values[t.slot];
  for (int k = 0; k < n; ++k) values[c.diagonal[k]] += obs_.g_variance[c.g_rows[k]];
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
  // Inequalities on top of the equality update x_e: per component, the values
  // G x_e - h of every column, and the QP (M', h - G x_e) where a row is violated.
  if (warm && static_cast<Eigen::Index>(warm->columns.size()) != S) warm->columns.assign(S, {});
  std::vector<std::vector<int>> active(warm ? S : 0);
  Eigen::MatrixXd values;
  std::vector<int> warm_local;
  for (const Component& c : components_) {
    const int n = static_cast<int>(c.g_rows.size());
    values.resize(S, n);
    for (int k = 0; k < n; ++k) {
      auto col = values.col(k);
      col.setConstant(-obs_.h[c.g_rows[k]]);
      for (RowIter it(obs_.G, c.g_rows[k]); it; ++it) col += it.value() * xt.col(it.col());
    }
    for (Eigen::Index s = 0; s < S; ++s) {
      bool violated = false;
      for (int k = 0; k < n && !violated; ++k) violated = values(s, k) > inequality_tolerance(values(s, k));
      // x_e meets every row: it is the optimum, with nothing active.
      if (!violated) continue;
      warm_local.clear();
      if (warm)
        for (int row : warm->columns[s]) {
          auto pos = std::lower_bound(c.g_rows.begin(), c.g_rows.end(), row);
          if (pos != c.g_rows.end() && *pos == row) warm_local.push_back(static_cast<int>(pos - c.g_rows.begin()));
        }
      const Eigen::VectorXd r = -values.row(s).transpose();
      DualQpResult res = solve_dual_qp(c.m, r, warm_local, c.scale);
      ++qp_solves_;
      qp_iterations_ += res.iterations;
      if (!res.feasible) fail_infeasible(c, res.conflict);
      for (int k = 0; k < n; ++k) {  // x = x_e + U lambda
        const double lk = res.lambda[k];
        if (lk == 0.0) continue;
        for (const Piece& pc : c.u[k]) {
          const int t = pc.block / 3, ax = pc.block % 3;
          for (int j = 0; j < J; ++j) xt(s, (t * J + j) * 3 + ax) += lk * pc.value[j];
        }
      }
      if (warm)
        for (int k : res.active) active[s].push_back(c.g_rows[k]);
    }
  }
  if (warm)
    for (Eigen::Index s = 0; s < S; ++s) {
      std::sort(active[s].begin(), active[s].end());
      warm->columns[s] = std::move(active[s]);
    }
  transpose_tiled(xt, x);
}

void ProjectionSolver::fail_infeasible(const Component& c, const std::vector<int>& local_rows) const {
  const int J = obs_.joints;
  std::set<int> items, frames;
  auto note = [&](const Eigen::SparseMatrix<double, Eigen::RowMajor>& M, const std::vector<int>& owner, int row) {
    if (row < static_cast<int>(owner.size())) items.insert(owner[row]);
    for (RowIter it(M, row); it; ++it) frames.insert(static_cast<int>(it.col() / (3 * J)));
  };
  for (int k : local_rows) {
    const int r = c.g_rows[k];
    note(obs_.G, obs_.item_of_g_row, r);
    // The hard equality rows this row depends on: M_g^-1 A_g R^-1 g^T's large entries.
    for (int gi : c.groups) {
      const Group& g = groups_[gi];
      const Factor& f = factors_[g.factor];
      Eigen::VectorXd coef = Eigen::VectorXd::Zero(f.gain_t.rows());
      for (RowIter it(obs_.G, r); it; ++it) {
        const int b = block_of(it.col(), J);
        if (group_of_block_[b] != gi) continue;
        const int lb = static_cast<int>(std::find(g.blocks.begin(), g.blocks.end(), b) - g.blocks.begin());
        coef += it.value() * f.gain_t.col(static_cast<Eigen::Index>(lb) * J + joint_of(it.col(), J));
      }
      const double top = coef.size() ? coef.cwiseAbs().maxCoeff() : 0.0;
      for (Eigen::Index q = 0; q < coef.size(); ++q)
        if (top > 0 && std::abs(coef[q]) > 1e-6 * top && obs_.is_hard(g.rows[q])) note(obs_.A, obs_.item_of_row, g.rows[q]);
    }
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
