// RouteSolver's scaffold on the token grid (AnchorRoute §3.4): the anchor-defined
// interval basis of eqs. (30)-(31), residual activities eq. (32) and the routed
// closed-form projection eqs. (33)-(34). Plain Eigen; the solver applies it to torch updates.
#pragma once
#include <Eigen/Dense>
#include <string>
#include <vector>

namespace mc {

// Local basis functions per interval, in s in [0, 1] with xi = 2 s - 1:
//   affine    {1, xi}            eq. (30): transport and slope (the paper's RouteSolver)
//   transport {1}                Table VI ablation
//   slope     {xi}               Table VI ablation
//   quadratic {1, xi, P2(xi)}    Table VI ablation, P2 = (3 xi^2 - 1) / 2 (Legendre)
//   cubic     {1, xi, P2, P3}    Table VI ablation, P3 = (5 xi^3 - 3 xi) / 2
enum class BasisKind { affine, transport, slope, quadratic, cubic };
BasisKind parse_basis_kind(const std::string& name, const std::string& what = "basis");
int basis_functions(BasisKind k);

struct IntervalBasis {
  BasisKind kind = BasisKind::affine;
  int frames = 0, tokens = 0, stride = 1;
  int per_interval = 2;                // basis functions per interval
  std::vector<int> boundaries;         // ascending distinct frames: 0, the anchor times, frames - 1
  std::vector<bool> observed;          // per boundary: an anchor time (has a control error)
  std::vector<int> interval_of_token;  // per token: its interval, -1 for tokens past the clip
  Eigen::MatrixXd B;                   // [tokens, per_interval * intervals()], eq. (31)

  int intervals() const { return static_cast<int>(boundaries.size()) - 1; }
};

// Eqs. (30)-(31), built once per sample from the anchor times. Intervals are
// I_i = [b_i, b_{i+1}] between consecutive boundaries (sequence ends and anchor
// times). Token l covers frames [l stride, (l + 1) stride) and belongs to the
// interval containing its centre frame c_l = l stride + (stride - 1) / 2 (the last
// interval also takes centres past frames - 1, clamped to s = 1); s = (c_l - b_i) /
// (b_{i+1} - b_i). So every row of B has its nonzeros in one interval's columns.
// `frames` is the clip's valid length (>= 2); tokens whose frames all lie past it
// get zero rows (never updated).
IntervalBasis build_interval_basis(const std::vector<int>& anchor_times, int frames, int tokens, int stride,
                                   BasisKind kind = BasisKind::affine);

// Eq. (32): a_i = clip(max(e_i^L, e_i^R) / rho_f, 0, 1), where only observed
// endpoints (anchor times) contribute; an interval without any gets 0.
// frame_error[t] = the largest control error of the anchors at frame t (read only at
// observed boundaries).
std::vector<double> interval_activities(const IntervalBasis& basis, const std::vector<double>& frame_error,
                                        double rho_f);

// Eq. (33) in closed form: the objective separates over intervals (their columns
// have disjoint rows), so alpha_i = (B_i^T B_i + lambda (1 - a_i) I)^+ B_i^T Delta.
// The pseudo-inverse (complete orthogonal decomposition) gives the minimum-norm
// solution when an interval has fewer tokens than basis functions and no ridge.
// delta [tokens, D] -> alpha [per_interval * intervals(), D].
Eigen::MatrixXd routed_coefficients(const IntervalBasis& basis, const std::vector<double>& activity, double lambda,
                                    const Eigen::MatrixXd& delta);
// The linear map of eq. (34): Delta* = R Delta with R = B (B^T B + lambda W)^+ B^T,
// [tokens, tokens], so a batch of updates is routed by one matrix product.
Eigen::MatrixXd routing_operator(const IntervalBasis& basis, const std::vector<double>& activity, double lambda);

}  // namespace mc
