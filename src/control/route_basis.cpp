// Interval basis, activities and the routed projection of RouteSolver (eqs. (30)-(34)).
#include "control/route_basis.h"

#include <algorithm>
#include <cmath>

#include "core/error.h"

namespace mc {

namespace {

double basis_value(BasisKind k, int f, double s) {
  const double xi = 2 * s - 1;
  const double p[4] = {1.0, xi, 0.5 * (3 * xi * xi - 1), 0.5 * (5 * xi * xi * xi - 3 * xi)};
  switch (k) {
    case BasisKind::transport: return p[0];
    case BasisKind::slope: return p[1];
    default: return p[f];  // affine, quadratic, cubic: the first 2, 3, 4 Legendre polynomials
  }
}

// Columns and rows of interval i: its tokens and its `per_interval` columns.
struct Block {
  std::vector<int> tokens;
  Eigen::MatrixXd Bi;  // [tokens.size(), per_interval]
};

std::vector<Block> blocks_of(const IntervalBasis& b) {
  std::vector<Block> out(b.intervals());
  for (int l = 0; l < b.tokens; ++l)
    if (b.interval_of_token[l] >= 0) out[b.interval_of_token[l]].tokens.push_back(l);
  for (int i = 0; i < b.intervals(); ++i) {
    auto& blk = out[i];
    blk.Bi.resize(blk.tokens.size(), b.per_interval);
    for (size_t r = 0; r < blk.tokens.size(); ++r)
      blk.Bi.row(r) = b.B.block(blk.tokens[r], i * b.per_interval, 1, b.per_interval);
  }
  return out;
}

// (B_i^T B_i + ridge I)^+ for one interval.
Eigen::MatrixXd block_inverse(const Eigen::MatrixXd& Bi, double ridge) {
  Eigen::MatrixXd G = Bi.transpose() * Bi;
  G.diagonal().array() += ridge;
  return G.completeOrthogonalDecomposition().pseudoInverse();
}

void check_activity(const IntervalBasis& b, const std::vector<double>& a, double lambda) {
  if (static_cast<int>(a.size()) != b.intervals())
    fail("routed projection: {} activities for {} intervals", a.size(), b.intervals());
  if (!(lambda >= 0)) fail("routed projection: lambda must be >= 0, got {}", lambda);
}

}  // namespace

BasisKind parse_basis_kind(const std::string& name, const std::string& what) {
  if (name == "affine") return BasisKind::affine;
  if (name == "transport") return BasisKind::transport;
  if (name == "slope") return BasisKind::slope;
  if (name == "quadratic") return BasisKind::quadratic;
  if (name == "cubic") return BasisKind::cubic;
  fail("{}: unknown basis '{}' (use affine, transport, slope, quadratic or cubic)", what, name);
}

int basis_functions(BasisKind k) {
  switch (k) {
    case BasisKind::affine: return 2;
    case BasisKind::transport:
    case BasisKind::slope: return 1;
    case BasisKind::quadratic: return 3;
    case BasisKind::cubic: return 4;
  }
  return 2;
}

IntervalBasis build_interval_basis(const std::vector<int>& anchor_times, int frames, int tokens, int stride,
                                   BasisKind kind) {  // eqs. (30)-(31)
  if (frames < 2) fail("interval basis: the clip needs at least 2 frames, got {}", frames);
  if (stride < 1 || tokens < 1) fail("interval basis: bad token grid ({} tokens of stride {})", tokens, stride);
  if (static_cast<int64_t>(tokens) * stride < frames)
    fail("interval basis: {} tokens of {} frames cannot cover a clip of {} frames", tokens, stride, frames);
  IntervalBasis b;
  b.kind = kind;
  b.frames = frames;
  b.tokens = tokens;
  b.stride = stride;
  b.per_interval = basis_functions(kind);
  b.boundaries = {0, frames - 1};
  for (int t : anchor_times) {
    if (t < 0 || t >= frames) fail("interval basis: anchor time {} outside the clip [0, {})", t, frames);
    b.boundaries.push_back(t);
  }
  std::sort(b.boundaries.begin(), b.boundaries.end());
  b.boundaries.erase(std::unique(b.boundaries.begin(), b.boundaries.end()), b.boundaries.end());
  for (int x : b.boundaries)
    b.observed.push_back(std::find(anchor_times.begin(), anchor_times.end(), x) != anchor_times.end());

  const int I = b.intervals();
  b.B = Eigen::MatrixXd::Zero(tokens, b.per_interval * I);
  b.interval_of_token.assign(tokens, -1);
  for (int l = 0; l < tokens; ++l) {
    if (static_cast<int64_t>(l) * stride >= frames) continue;  // all padding
    const double c = l * stride + 0.5 * (stride - 1);
    // Interval i with b_i <= c < b_{i+1}; centres at or past the last boundary go to the last interval.
    int i = static_cast<int>(std::upper_bound(b.boundaries.begin(), b.boundaries.end(), c) - b.boundaries.begin()) - 1;
    i = std::clamp(i, 0, I - 1);
    const double s = std::clamp((c - b.boundaries[i]) / (b.boundaries[i + 1] - b.boundaries[i]), 0.0, 1.0);
    b.interval_of_token[l] = i;
    for (int f = 0; f < b.per_interval; ++f) b.B(l, i * b.per_interval + f) = basis_value(kind, f, s);
  }
  return b;
}

std::vector<double> interval_activities(const IntervalBasis& b, const std::vector<double>& frame_error,
                                        double rho_f) {  // eq. (32)
  if (!(rho_f > 0)) fail("residual tolerance rho_f must be > 0, got {}", rho_f);
  std::vector<double> a(b.intervals(), 0.0);
  for (int i = 0; i < b.intervals(); ++i) {
    double e = 0;
    for (int k : {i, i + 1})
      if (b.observed[k]) {
        const int t = b.boundaries[k];
        if (t >= static_cast<int>(frame_error.size())) fail("interval activities: no control error for frame {}", t);
        e = std::max(e, frame_error[t]);
      }
    a[i] = std::clamp(e / rho_f, 0.0, 1.0);
  }
  return a;
}

Eigen::MatrixXd routed_coefficients(const IntervalBasis& b, const std::vector<double>& activity, double lambda,
                                    const Eigen::MatrixXd& delta) {  // eq. (33)
  check_activity(b, activity, lambda);
  if (delta.rows() != b.tokens) fail("routed projection: update has {} rows for {} tokens", delta.rows(), b.tokens);
  const auto blocks = blocks_of(b);
  Eigen::MatrixXd alpha = Eigen::MatrixXd::Zero(b.B.cols(), delta.cols());
  for (int i = 0; i < b.intervals(); ++i) {
    const auto& blk = blocks[i];
    if (blk.tokens.empty()) continue;
    Eigen::MatrixXd Di(blk.tokens.size(), delta.cols());
    for (size_t r = 0; r < blk.tokens.size(); ++r) Di.row(r) = delta.row(blk.tokens[r]);
    alpha.middleRows(i * b.per_interval, b.per_interval) =
        block_inverse(blk.Bi, lambda * (1 - activity[i])) * (blk.Bi.transpose() * Di);
  }
  return alpha;
}

Eigen::MatrixXd routing_operator(const IntervalBasis& b, const std::vector<double>& activity, double lambda) {
  check_activity(b, activity, lambda);
  const auto blocks = blocks_of(b);
  Eigen::MatrixXd R = Eigen::MatrixXd::Zero(b.tokens, b.tokens);
  for (int i = 0; i < b.intervals(); ++i) {
    const auto& blk = blocks[i];
    if (blk.tokens.empty()) continue;
    Eigen::MatrixXd Ri = blk.Bi * block_inverse(blk.Bi, lambda * (1 - activity[i])) * blk.Bi.transpose();
    for (size_t r = 0; r < blk.tokens.size(); ++r)
      for (size_t c = 0; c < blk.tokens.size(); ++c) R(blk.tokens[r], blk.tokens[c]) = Ri(r, c);
  }
  return R;
}

}  // namespace mc
