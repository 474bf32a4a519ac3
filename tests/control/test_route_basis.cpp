// RouteSolver's interval basis (eqs. (30)-(31)), activities (eq. (32)) and the
// closed-form routed projection (eqs. (33)-(34)) against a direct least-squares solve.
#include <catch2/catch.hpp>

#include <random>

#include "control/route_basis.h"
#include "core/error.h"

using namespace mc;

namespace {

// Direct solve of eq. (33) as one stacked least-squares problem
// [B; sqrt(lambda W)] alpha = [Delta; 0] (minimum-norm solution).
Eigen::MatrixXd direct_solve(const IntervalBasis& b, const std::vector<double>& a, double lambda,
                             const Eigen::MatrixXd& delta) {
  const int P = static_cast<int>(b.B.cols());
  Eigen::MatrixXd M = Eigen::MatrixXd::Zero(b.tokens + P, P), rhs = Eigen::MatrixXd::Zero(b.tokens + P, delta.cols());
  M.topRows(b.tokens) = b.B;
  rhs.topRows(b.tokens) = delta;
  for (int c = 0; c < P; ++c) M(b.tokens + c, c) = std::sqrt(lambda * (1 - a[c / b.per_interval]));
  return M.completeOrthogonalDecomposition().solve(rhs);
}

}  // namespace

TEST_CASE("interval basis columns live only on their intervals", "[routesolver]") {
  for (auto kind : {BasisKind::affine, BasisKind::transport, BasisKind::slope, BasisKind::quadratic, BasisKind::cubic}) {
    const int T = 60, L = 16, S = 4;  // 64 frames of tokens, 60 valid
    auto b = build_interval_basis({9, 30, 31, 50}, T, L, S, kind);
    REQUIRE(b.boundaries == std::vector<int>{0, 9, 30, 31, 50, 59});
    REQUIRE(b.observed == std::vector<bool>{false, true, true, true, true, false});
    REQUIRE(b.B.rows() == L);
    REQUIRE(b.B.cols() == b.per_interval * 5);
    CHECK(b.per_interval == basis_functions(kind));
    for (int l = 0; l < L; ++l) {
      const int i = b.interval_of_token[l];
      const double c = l * S + 1.5;
      if (l * S >= T) {
        CHECK(i == -1);
        CHECK(b.B.row(l).isZero());
        continue;
      }
      REQUIRE(i >= 0);
      // The token's centre lies in its interval (the last one also takes centres past the end).
      CHECK(c >= b.boundaries[i]);
      if (i + 1 < b.intervals()) CHECK(c < b.boundaries[i + 1]);
      for (int col = 0; col < b.B.cols(); ++col)
        if (col / b.per_interval != i) CHECK(b.B(l, col) == 0.0);
    }
    // [30, 31] holds no token centre: its columns are empty.
    CHECK(b.B.middleCols(2 * b.per_interval, b.per_interval).isZero());
  }
  // Affine values: transport 1, slope 2 s - 1 with s the centre's position in the interval.
  auto b = build_interval_basis({}, 16, 4, 4, BasisKind::affine);  // one interval [0, 15]
  for (int l = 0; l < 4; ++l) {
    CHECK(b.B(l, 0) == 1.0);
    CHECK(b.B(l, 1) == Approx(2 * (l * 4 + 1.5) / 15 - 1));
  }
  CHECK_THROWS_AS(build_interval_basis({20}, 16, 4, 4), UserError);
  CHECK_THROWS_AS(parse_basis_kind("linear"), UserError);
}

TEST_CASE("residual activities: larger observed endpoint error over rho_f, clipped", "[routesolver]") {
  auto b = build_interval_basis({10, 20}, 40, 10, 4);  // intervals [0,10] [10,20] [20,39]
  std::vector<double> err(40, 0.0);
  err[10] = 0.02;
  err[20] = 0.5;
  err[0] = 9;  // not an anchor time: ignored
  auto a = interval_activities(b, err, 0.05);
  REQUIRE(a.size() == 3u);
  CHECK(a[0] == Approx(0.4));
  CHECK(a[1] == 1.0);
  CHECK(a[2] == 1.0);
  CHECK(interval_activities(build_interval_basis({}, 40, 10, 4), err, 0.05) == std::vector<double>{0.0});
  CHECK_THROWS_AS(interval_activities(b, err, 0.0), UserError);
}

TEST_CASE("eq. (33) closed form equals a direct least-squares solve", "[routesolver]") {
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  for (auto kind : {BasisKind::affine, BasisKind::transport, BasisKind::slope, BasisKind::quadratic, BasisKind::cubic}) {
    for (int trial = 0; trial < 4; ++trial) {
      const int T = 49 * 4, L = 49, D = 7;
      std::vector<int> times;
      for (int k = 0; k < 2 + 5 * trial; ++k) times.push_back(static_cast<int>(U(rng) * (T - 1)));
      auto b = build_interval_basis(times, T, L, 4, kind);
      std::vector<double> a(b.intervals());
      for (auto& x : a) x = U(rng) < 0.3 ? 1.0 : U(rng);  // some fully active (no ridge)
      const double lambda = trial == 0 ? 0.0 : 3.0 * trial;
      Eigen::MatrixXd delta = Eigen::MatrixXd::Random(L, D);
      Eigen::MatrixXd alpha = routed_coefficients(b, a, lambda, delta);
      Eigen::MatrixXd ref = direct_solve(b, a, lambda, delta);
      INFO("basis " << int(kind) << " trial " << trial);
      // The projection B alpha is unique even where alpha is not (empty or rank-deficient intervals).
      CHECK((b.B * alpha - b.B * ref).norm() < 1e-9 * (1 + delta.norm()));
      CHECK((alpha - ref).norm() < 1e-8 * (1 + ref.norm()));
      // The routing operator gives the same update.
      CHECK((routing_operator(b, a, lambda) * delta - b.B * alpha).norm() < 1e-9 * (1 + delta.norm()));
    }
  }
}

TEST_CASE("routing: full activity projects, zero activity suppresses, lambda = 0 ignores activity", "[routesolver]") {
  auto b = build_interval_basis({20, 40}, 64, 16, 4);
  Eigen::MatrixXd delta = Eigen::MatrixXd::Random(16, 5);
  // A delta already in the span of B is reproduced exactly under full activity.
  Eigen::MatrixXd in_span = b.B * Eigen::MatrixXd::Random(b.B.cols(), 5);
  auto R1 = routing_operator(b, {1, 1, 1}, 10.0);
  CHECK((R1 * in_span - in_span).norm() < 1e-10);
  CHECK((R1 * R1 - R1).norm() < 1e-10);  // an orthogonal projector
  // Zero activity with a large lambda shrinks the update toward 0, interval by interval.
  auto R0 = routing_operator(b, {0, 1, 0}, 1e8);
  Eigen::MatrixXd out = R0 * delta;
  for (int l = 0; l < 16; ++l) {
    if (b.interval_of_token[l] == 1) CHECK((out.row(l) - (R1 * delta).row(l)).norm() < 1e-9);
    else CHECK(out.row(l).norm() < 1e-5);
  }
  CHECK((routing_operator(b, {0, 0.3, 1}, 0.0) - R1).norm() < 1e-10);
}
