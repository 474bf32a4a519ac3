// Inequality and direction items (issue 20): their rows, their errors, and the
// projection onto equalities ∩ half-spaces against a dense KKT reference that
// enumerates active sets; warm vs cold starts; infeasible sets; soft inequalities;
// the active-set Cholesky updates.
#include <catch2/catch.hpp>

#include <algorithm>
#include <random>

#include "control/active_set_qp.h"
#include "control/directions.h"
#include "control/kinematic_metric.h"
#include "control/linear_observation.h"
#include "control/projection_solver.h"
#include "control/sample_constraints.h"
#include "control_test_util.h"
#include "data/skeleton.h"
#include "eval/observation_errors.h"
#include "test_util.h"

using namespace mc;
using namespace mc::test;

namespace {

const Skeleton& skel() { return humanml3d_skeleton(); }

using SpRow = Eigen::SparseMatrix<double, Eigen::RowMajor>;

// Dense reference for the QP
//   min 1/2 |x - x_hat|_R^2 + 1/2 sum_soft eq (a x - y)^2 / var + 1/2 sum_soft ineq max(0, g x - h)^2 / var
//   s.t. hard A x = y, hard G x <= h,
// by enumerating the inequality rows' active sets: for each subset S the
// equality-constrained problem (hard rows of S as equalities, soft rows of S as
// quadratic penalties) is solved through its dense KKT system, and the subset whose
// solution meets every KKT condition (inactive rows feasible, hard active multipliers
// >= 0, soft active rows on their violated side) is the optimum. Primal and
// exhaustive: nothing in common with the solver's dual active-set method.
Eigen::VectorXd dense_qp_reference(const KinematicMetric& metric, const LinearObservation& obs,
                                   const Eigen::VectorXd& x_hat, bool* feasible = nullptr) {
  const int d = obs.dim(), p = obs.inequalities();
  REQUIRE(p <= 14);
  const Eigen::MatrixXd R = metric.dense(obs.frames);
  const Eigen::MatrixXd A = obs.A.toDense(), G = p > 0 ? Eigen::MatrixXd(obs.G.toDense()) : Eigen::MatrixXd(0, d);
  Eigen::MatrixXd H0 = R;
  Eigen::VectorXd q0 = R * x_hat;
  std::vector<int> hard_eq;
  for (int r = 0; r < obs.rows(); ++r) {
    if (obs.is_hard(r)) {
      hard_eq.push_back(r);
    } else {
      H0 += A.row(r).transpose() * A.row(r) / obs.variance[r];
      q0 += A.row(r).transpose() * obs.y[r] / obs.variance[r];
    }
  }
  for (uint32_t mask = 0; mask < (1u << p); ++mask) {
    Eigen::MatrixXd H = H0;
    Eigen::VectorXd q = q0;
    std::vector<int> cons_hard;  // indices into G
    for (int i = 0; i < p; ++i) {
      if (!(mask & (1u << i))) continue;
      if (obs.g_variance[i] > 0) {
        H += G.row(i).transpose() * G.row(i) / obs.g_variance[i];
        q += G.row(i).transpose() * obs.h[i] / obs.g_variance[i];
      } else {
        cons_hard.push_back(i);
      }
    }
    const int k = static_cast<int>(hard_eq.size() + cons_hard.size());
    Eigen::MatrixXd K = Eigen::MatrixXd::Zero(d + k, d + k);
    Eigen::VectorXd rhs(d + k);
    K.topLeftCorner(d, d) = H;
    rhs.head(d) = q;
    int c = 0;
    for (int r : hard_eq) {
      K.block(d + c, 0, 1, d) = A.row(r);
      K.block(0, d + c, d, 1) = A.row(r).transpose();
      rhs[d + c++] = obs.y[r];
    }
    for (int i : cons_hard) {
      K.block(d + c, 0, 1, d) = G.row(i);
      K.block(0, d + c, d, 1) = G.row(i).transpose();
      rhs[d + c++] = obs.h[i];
    }
    Eigen::FullPivLU<Eigen::MatrixXd> lu(K);
    if (!lu.isInvertible()) continue;  // dependent active rows: another subset describes the same point
    Eigen::VectorXd sol = lu.solve(rhs);
    Eigen::VectorXd x = sol.head(d);
    bool ok = true;
    for (int i = 0; i < p && ok; ++i) {
      const double v = G.row(i).dot(x) - obs.h[i];
      const bool in = mask & (1u << i);
      if (!in) ok = v <= 1e-9;
      else if (obs.g_variance[i] > 0) ok = v >= -1e-9;
    }
    // The multipliers: H x - q + C^T mu = 0 with mu = sol.tail(k); hard active rows need mu >= 0.
    for (size_t j = 0; j < cons_hard.size() && ok; ++j) ok = sol[d + static_cast<int>(hard_eq.size() + j)] >= -1e-9;
    if (ok) {
      if (feasible) *feasible = true;
      return x;
    }
  }
  if (feasible) *feasible = false;
  return x_hat;
}

// A small hand-built observation on a 3-joint chain metric (d = 9 T): random sparse
// equality rows and random inequality rows touching 1-3 coordinates of 1-2 frames,
// hard or soft. The inequalities are made feasible at a random point x0 that also
// meets the hard equalities (their bounds are g x0 + slack).
struct SmallProblem {
  KinematicMetric metric;
  LinearObservation obs;
  Eigen::VectorXd x0;
};
SmallProblem small_problem(std::mt19937_64& rng, bool kinematic) {
  const int J = 3, T = uniform_int(rng, 2, 4), d = 3 * J * T;
  Eigen::MatrixXd L(3, 3);
  L << 1, -1, 0, -1, 2, -1, 0, -1, 1;
  SmallProblem sp{kinematic ? KinematicMetric(L, uniform(rng, 0.5, 5.0), uniform(rng, 0.5, 2.0))
                            : KinematicMetric::euclidean(J),
                  LinearObservation{}, Eigen::VectorXd::Zero(d)};
  LinearObservation& o = sp.obs;
  o.frames = T;
  o.joints = J;
  o.source = "<small>";
  std::normal_distribution<double> n(0.0, 1.0);
  for (int i = 0; i < d; ++i) sp.x0[i] = n(rng);
  auto random_row = [&](int frames_touched) {
    std::vector<Eigen::Triplet<double>> t;
    const int f0 = uniform_int(rng, 0, T - 1);
    const int f1 = frames_touched > 1 ? uniform_int(rng, 0, T - 1) : f0;
    const int entries = uniform_int(rng, 1, 3);
    std::vector<int> used;
    for (int e = 0; e < entries; ++e) {
      int col = ((e % 2 ? f1 : f0) * J + uniform_int(rng, 0, J - 1)) * 3 + uniform_int(rng, 0, 2);
      if (std::find(used.begin(), used.end(), col) != used.end()) continue;
      used.push_back(col);
      t.emplace_back(0, col, n(rng));
    }
    return t;
  };
  const int m = uniform_int(rng, 0, 4), p = uniform_int(rng, 1, 8);
  std::vector<Eigen::Triplet<double>> ta, tg;
  o.y.resize(m);
  o.variance.resize(m);
  for (int r = 0; r < m; ++r) {
    for (auto& e : random_row(uniform_int(rng, 1, 2))) ta.emplace_back(r, e.col(), e.value());
    o.variance[r] = uniform_int(rng, 0, 2) == 0 ? std::pow(10.0, uniform(rng, -3, 0)) : 0.0;
    o.item_of_row.push_back(0);
  }
  o.A.resize(m, d);
  o.A.setFromTriplets(ta.begin(), ta.end());
  // Keep the hard equality rows independent (compile's rule) and make x0 meet them.
  std::vector<int> hard;
  for (int r = 0; r < m; ++r)
    if (o.variance[r] == 0) hard.push_back(r);
  Eigen::MatrixXd Ah(hard.size(), d);
  for (size_t k = 0; k < hard.size(); ++k) Ah.row(k) = Eigen::MatrixXd(o.A.toDense()).row(hard[k]);
  if (!hard.empty()) {
    Eigen::FullPivLU<Eigen::MatrixXd> lu(Ah);
    if (lu.rank() < static_cast<int>(hard.size()))
      for (int r : hard) o.variance[r] = 0.1;  // dependent: make them soft instead
  }
  Eigen::VectorXd ax0 = o.A * sp.x0;
  for (int r = 0; r < m; ++r) o.y[r] = o.variance[r] == 0 ? ax0[r] : ax0[r] + 0.3 * n(rng);
  o.G.resize(p, d);
  for (int r = 0; r < p; ++r)
    for (auto& e : random_row(uniform_int(rng, 1, 2))) tg.emplace_back(r, e.col(), e.value());
  o.G.setFromTriplets(tg.begin(), tg.end());
  o.h = o.G * sp.x0;
  o.g_variance = Eigen::VectorXd::Zero(p);
  for (int r = 0; r < p; ++r) {
    o.h[r] += uniform_int(rng, 0, 3) == 0 ? 0.0 : uniform(rng, 0.0, 0.5);  // some rows tight at x0
    if (uniform_int(rng, 0, 3) == 0) o.g_variance[r] = std::pow(10.0, uniform(rng, -3, 0));
    o.item_of_g_row.push_back(1);
  }
  o.item_labels = {"equalities", "inequalities"};
  return sp;
}

// x_hat far enough from x0 that many inequalities are violated.
Eigen::VectorXd violating_point(std::mt19937_64& rng, const SmallProblem& sp) {
  std::normal_distribution<double> n(0.0, 1.0);
  Eigen::VectorXd x = sp.x0;
  for (Eigen::Index i = 0; i < x.size(); ++i) x[i] += 1.5 * n(rng);
  return x;
}

double max_hard_violation(const LinearObservation& obs, const Eigen::VectorXd& x) {
  double worst = 0;
  if (obs.inequalities() > 0) {
    Eigen::VectorXd v = obs.G * x - obs.h;
    for (int r = 0; r < obs.inequalities(); ++r)
      if (obs.is_hard_inequality(r)) worst = std::max(worst, v[r]);
  }
  return worst;
}

double max_hard_eq_residual(const LinearObservation& obs, const Eigen::VectorXd& x) {
  double worst = 0;
  Eigen::VectorXd r = obs.A * x - obs.y;
  for (int k = 0; k < obs.rows(); ++k)
    if (obs.is_hard(k)) worst = std::max(worst, std::abs(r[k]));
  return worst;
}

ConstraintSpec parse(const std::string& yaml) { return parse_constraint_spec_yaml(yaml, "test.yaml"); }

std::string compile_error(const std::string& yaml, int T, const std::vector<float>* src = nullptr) {
  try {
    compile(parse(yaml), T, skel(), src ? src->data() : nullptr);
  } catch (const UserError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("active-set Cholesky: appending and removing rows equals refactorising", "[control][inequality]") {
  std::mt19937_64 rng(3);
  const int n = 9;
  Eigen::MatrixXd B = Eigen::MatrixXd::Random(n, n + 3);
  Eigen::MatrixXd M = B * B.transpose() + 0.1 * Eigen::MatrixXd::Identity(n, n);
  std::vector<int> act = {0, 1, 2};
  ActiveCholesky chol;
  chol.reset(Eigen::LLT<Eigen::MatrixXd>(M.topLeftCorner(3, 3)).matrixL(), n);
  auto check = [&] {
    const int k = static_cast<int>(act.size());
    Eigen::MatrixXd Mk(k, k);
    for (int a = 0; a < k; ++a)
      for (int b = 0; b < k; ++b) Mk(a, b) = M(act[a], act[b]);
    Eigen::VectorXd rhs = Eigen::VectorXd::Random(k), x = rhs;
    chol.solve_in_place(x);
    CHECK((Mk * x - rhs).norm() < 1e-10);
  };
  for (int step = 0; step < 40; ++step) {
    const bool add = act.size() < 2 || (act.size() < static_cast<size_t>(n) && uniform_int(rng, 0, 1));
    if (add) {
      int p;
      do p = uniform_int(rng, 0, n - 1);
      while (std::find(act.begin(), act.end(), p) != act.end());
      Eigen::VectorXd v(act.size());
      for (size_t k = 0; k < act.size(); ++k) v[static_cast<Eigen::Index>(k)] = M(act[k], p);
      Eigen::VectorXd w = chol.forward(v);
      chol.append(w, M(p, p) - w.squaredNorm());
      act.push_back(p);
    } else {
      const int q = uniform_int(rng, 0, static_cast<int>(act.size()) - 1);
      chol.remove(q);
      act.erase(act.begin() + q);
    }
    REQUIRE(chol.size() == static_cast<int>(act.size()));
    check();
  }
}

TEST_CASE("projection onto equalities and half-spaces matches the dense KKT reference to 1e-8", "[control][inequality]") {
  std::mt19937_64 rng(11);
  int checked = 0, with_active = 0;
  for (int trial = 0; trial < 160; ++trial) {
    SmallProblem sp = small_problem(rng, trial % 2 == 1);
    const Eigen::VectorXd x_hat = violating_point(rng, sp);
    bool feasible = false;
    Eigen::VectorXd ref = dense_qp_reference(sp.metric, sp.obs, x_hat, &feasible);
    REQUIRE(feasible);  // x0 meets every hard row
    ProjectionSolver solver(sp.metric);
    solver.set_observation(sp.obs);
    ProjectionSolver::ActiveSets active;
    Eigen::MatrixXd x = solver.project(x_hat, &active);
    INFO("trial " << trial << ": T " << sp.obs.frames << ", " << sp.obs.rows() << " equalities, "
                  << sp.obs.inequalities() << " inequalities");
    CHECK((x.col(0) - ref).cwiseAbs().maxCoeff() < 1e-8);
    CHECK(max_hard_violation(sp.obs, x.col(0)) < 1e-9);
    CHECK(max_hard_eq_residual(sp.obs, x.col(0)) < 1e-9);
    ++checked;
    with_active += !active.columns[0].empty();
  }
  CHECK(checked == 160);
  CHECK(with_active > 100);  // the draws really exercise active inequalities
}

TEST_CASE("compiled inequality specs on the skeleton match the dense reference, both metrics", "[control][inequality]") {
  std::mt19937_64 rng(5);
  const int T = 3;
  std::vector<float> src = random_motion(rng, T, skel());
  // lift so the toes are above the floor in the source (the fixture's convention)
  float lowest = INFINITY;
  for (size_t i = 1; i < src.size(); i += 3) lowest = std::min(lowest, src[i]);
  for (size_t i = 1; i < src.size(); i += 3) src[i] -= lowest;
  const std::vector<std::string> specs = {
      "- {type: floor}\n- {type: keyframe, joints: [pelvis], frames: [1], from_source: true}",
      "- {type: box, joints: [l_wrist], frames: [1], axes: xz, min: [-0.1, -0.2], max: [0.3, 0.2]}\n"
      "- {type: speed_limit, joints: [pelvis], axes: x, max: 0.02}",
      "- {type: half_space, joints: [l_wrist], frames: [0, 2], normal: [0, 1, 0], offset: 0.05, "
      "relative_to: head}\n- {type: floor, height: 0.01, variance: 0.001}",
      "- {type: tangent, joints: [pelvis], frames: [1], values: [[1, 0.5]]}\n"
      "- {type: facing, frames: [0, 2], values: [0, 1]}"};
  for (const auto& text : specs)
    for (const KinematicMetric& metric : {KinematicMetric::euclidean(22), KinematicMetric::kinematic(skel())}) {
      LinearObservation obs = compile(parse(text), T, skel(), src.data());
      REQUIRE(obs.inequalities() > 0);
      std::normal_distribution<double> n(0.0, 0.3);
      Eigen::VectorXd x_hat = to_vector(src);
      for (Eigen::Index i = 0; i < x_hat.size(); ++i) x_hat[i] += n(rng);
      Eigen::VectorXd ref = dense_qp_reference(metric, obs, x_hat);
      ProjectionSolver solver(metric);
      solver.set_observation(obs);
      Eigen::VectorXd x = solver.project(x_hat).col(0);
      INFO(text);
      CHECK((x - ref).cwiseAbs().maxCoeff() < 1e-8);
      CHECK(max_hard_violation(obs, x) < 1e-9);
      CHECK(max_hard_eq_residual(obs, x) < 1e-9);
    }
}

// The KKT conditions of the projection QP, checked densely on problems too large for
// the enumerating reference: stationarity R (x - x_hat) + soft gradients + A_h^T mu +
// G_act^T lambda = 0 (multipliers by least squares over the hard equalities and the
// hard inequalities that are tight), lambda >= 0, every hard row met. Returns the
// relative stationarity residual and writes the most negative multiplier.
double kkt_residual(const KinematicMetric& metric, const LinearObservation& obs, const Eigen::VectorXd& x_hat,
                    const Eigen::VectorXd& x, double* min_multiplier) {
  const Eigen::MatrixXd R = metric.dense(obs.frames);
  const Eigen::MatrixXd A = obs.A.toDense(), G = obs.G.toDense();
  Eigen::VectorXd grad = R * (x - x_hat);
  std::vector<Eigen::VectorXd> cols;
  int equalities = 0;
  for (int r = 0; r < obs.rows(); ++r) {
    if (obs.is_hard(r)) cols.push_back(A.row(r).transpose()), ++equalities;
    else grad += A.row(r).transpose() * (A.row(r).dot(x) - obs.y[r]) / obs.variance[r];
  }
  for (int r = 0; r < obs.inequalities(); ++r) {
    const double v = G.row(r).dot(x) - obs.h[r];
    if (!obs.is_hard_inequality(r)) grad += G.row(r).transpose() * std::max(0.0, v) / obs.g_variance[r];
    else if (v > -1e-9) cols.push_back(G.row(r).transpose());
  }
  Eigen::MatrixXd C(x.size(), static_cast<Eigen::Index>(cols.size()));
  for (size_t k = 0; k < cols.size(); ++k) C.col(static_cast<Eigen::Index>(k)) = cols[k];
  const Eigen::VectorXd nu = C.colPivHouseholderQr().solve(-grad);
  *min_multiplier = 0;
  for (Eigen::Index k = equalities; k < nu.size(); ++k) *min_multiplier = std::min(*min_multiplier, nu[k]);
  return (C * nu + grad).norm() / std::max(1e-12, (R * (x - x_hat)).norm());
}

TEST_CASE("speed-limit chains, floors and boxes on the skeleton meet the QP's KKT conditions", "[control][inequality]") {
  // Chains of hundreds of rows (too many for the enumerating reference), hard and soft
  // rows, both metrics; x_hat far outside the limits so long runs of rows are active.
  std::mt19937_64 rng(17);
  for (int trial = 0; trial < 6; ++trial) {
    const int T = 16 + 2 * trial;
    std::vector<float> src = random_motion(rng, T, skel());
    float lowest = INFINITY;
    for (size_t i = 1; i < src.size(); i += 3) lowest = std::min(lowest, src[i]);
    for (size_t i = 1; i < src.size(); i += 3) src[i] -= lowest;
    // the source's own largest per-axis step, so the source meets every limit
    double fastest = 0;
    for (int t = 0; t + 1 < T; ++t)
      for (int j : {0, 20, 21})
        for (int c : {0, 2})
          fastest = std::max(fastest, std::abs(double(src[((t + 1) * 22 + j) * 3 + c]) - src[(t * 22 + j) * 3 + c]));
    const std::string spec = fmt::format(
        "- {{type: keyframe, joints: [pelvis], frames: [0, {}], axes: xz, from_source: true}}\n"
        "- {{type: keyframe, joints: [l_wrist], frames: [5], from_source: true, variance: {}}}\n"
        "- {{type: floor}}\n"
        "- {{type: speed_limit, joints: [pelvis, l_wrist, r_wrist], axes: xz, max: {}}}\n"
        "- {{type: speed_limit, joints: [head], axes: y, max: 0.01, variance: 0.001}}\n"
        "- {{type: box, joints: [head], axes: y, max: {}, variance: 0.01}}",
        T - 1, trial % 2 ? 1e-3 : 0.0, fastest * 1.05, 1.3 - lowest);
    LinearObservation obs = compile(parse(spec), T, skel(), src.data());
    std::normal_distribution<double> n(0.0, 1.0);
    Eigen::VectorXd x_hat = to_vector(src);
    for (Eigen::Index i = 0; i < x_hat.size(); ++i) x_hat[i] += 0.1 * n(rng);
    for (int t = 1; t < T; ++t)  // drift every joint along x: the speed limits bind in long runs
      for (int j = 0; j < 22; ++j) x_hat[(t * 22 + j) * 3] += 0.08 * t * (trial % 2 ? 1 : -1);
    for (const KinematicMetric& metric : {KinematicMetric::euclidean(22), KinematicMetric::kinematic(skel())}) {
      ProjectionSolver solver(metric);
      solver.set_observation(obs);
      ProjectionSolver::ActiveSets active;
      const Eigen::VectorXd x = solver.project(x_hat, &active).col(0);
      double min_multiplier = 0;
      const double stationarity = kkt_residual(metric, obs, x_hat, x, &min_multiplier);
      INFO("trial " << trial << ", T " << T << ", " << obs.inequalities() << " inequality rows, "
                    << active.columns[0].size() << " active, largest component " << solver.largest_component());
      CHECK(solver.largest_component() >= 2 * (T - 1));  // a whole chain is one component
      CHECK(active.columns[0].size() >= static_cast<size_t>(T / 2));
      CHECK(stationarity < 1e-8);
      CHECK(min_multiplier > -1e-8);
      CHECK(max_hard_violation(obs, x) < 1e-9);
      CHECK(max_hard_eq_residual(obs, x) < 1e-9);
      // the warm start from this answer reproduces it, with nothing to add or drop
      const int64_t before = solver.qp_iterations();
      const Eigen::VectorXd again = solver.project(x_hat, &active).col(0);
      CHECK((again - x).cwiseAbs().maxCoeff() < 1e-10);
      CHECK(solver.qp_iterations() == before);
    }
  }
}

TEST_CASE("a warm start gives the cold start's answer, whatever rows it names", "[control][inequality]") {
  std::mt19937_64 rng(21);
  for (int trial = 0; trial < 60; ++trial) {
    SmallProblem sp = small_problem(rng, true);
    ProjectionSolver solver(sp.metric);
    solver.set_observation(sp.obs);
    Eigen::MatrixXd x_hat(sp.obs.dim(), 2);
    x_hat.col(0) = violating_point(rng, sp);
    x_hat.col(1) = violating_point(rng, sp);
    ProjectionSolver::ActiveSets previous;
    solver.project(x_hat, &previous);  // the active sets of a nearby problem
    Eigen::MatrixXd next = x_hat + 0.1 * Eigen::MatrixXd::Random(x_hat.rows(), 2);
    ProjectionSolver::ActiveSets warm = previous, garbage;
    garbage.columns.resize(2);
    for (int r = 0; r < sp.obs.inequalities(); ++r)
      if (uniform_int(rng, 0, 1)) garbage.columns[0].push_back(r), garbage.columns[1].push_back(r);
    Eigen::MatrixXd cold = solver.project(next);
    Eigen::MatrixXd a = solver.project(next, &warm);
    Eigen::MatrixXd b = solver.project(next, &garbage);
    CHECK((a - cold).cwiseAbs().maxCoeff() < 1e-10);
    CHECK((b - cold).cwiseAbs().maxCoeff() < 1e-10);
  }
  // A warm start saves work: projecting the same point again adds no row.
  SmallProblem sp = small_problem(rng, true);
  ProjectionSolver solver(sp.metric);
  solver.set_observation(sp.obs);
  Eigen::MatrixXd x_hat = violating_point(rng, sp);
  ProjectionSolver::ActiveSets warm;
  solver.project(x_hat, &warm);
  const int64_t before = solver.qp_iterations();
  solver.project(x_hat, &warm);
  CHECK(solver.qp_iterations() == before);
}

TEST_CASE("infeasible hard sets are UserErrors naming the items", "[control][inequality]") {
  std::mt19937_64 rng(2);
  std::vector<float> src = random_motion(rng, 20, skel());
  // a keyframe below the floor
  auto e = compile_error("- {type: floor, name: ground}\n"
                         "- {type: keyframe, name: sunk toe, joints: [l_foot], frames: [4], axes: y, values: [[[-0.1]]]}",
                         20);
  CHECK(e.find("infeasible") != std::string::npos);
  CHECK(e.find("'ground'") != std::string::npos);
  CHECK(e.find("'sunk toe'") != std::string::npos);
  CHECK(e.find("frame 4") != std::string::npos);
  // contradictory half-spaces
  e = compile_error("- {type: half_space, name: above, joints: [head], frames: [3], normal: [0, 1, 0], offset: 1.8}\n"
                    "- {type: box, name: low ceiling, joints: [head], frames: [3], axes: y, max: 1.5}",
                    20);
  CHECK(e.find("infeasible") != std::string::npos);
  CHECK(e.find("'above'") != std::string::npos);
  CHECK(e.find("'low ceiling'") != std::string::npos);
  // a speed limit that keyframes 2 m apart over 5 frames cannot meet (a chain of rows)
  e = compile_error("- {type: keyframe, name: start, joints: [pelvis], frames: [0], axes: x, values: [[[0.0]]]}\n"
                    "- {type: keyframe, name: end, joints: [pelvis], frames: [5], axes: x, values: [[[2.0]]]}\n"
                    "- {type: speed_limit, name: slow, joints: [pelvis], axes: x, max: 0.1}",
                    20);
  CHECK(e.find("infeasible") != std::string::npos);
  CHECK(e.find("'slow'") != std::string::npos);
  CHECK(e.find("'start'") != std::string::npos);
  CHECK(e.find("'end'") != std::string::npos);
  // the same limit with room to spare is fine, and soft items never conflict
  CHECK(compile_error("- {type: keyframe, joints: [pelvis], frames: [0], axes: x, values: [[[0.0]]]}\n"
                      "- {type: keyframe, joints: [pelvis], frames: [5], axes: x, values: [[[2.0]]]}\n"
                      "- {type: speed_limit, joints: [pelvis], axes: x, max: 0.5}",
                      20) == "");
  CHECK(compile_error("- {type: floor, variance: 0.01}\n"
                      "- {type: keyframe, joints: [l_foot], frames: [4], axes: y, values: [[[-0.1]]]}",
                      20) == "");
}

TEST_CASE("soft inequalities: a one-sided penalty that tightens as the variance shrinks", "[control][inequality]") {
  // One coordinate, R = I: the soft floor y >= 0 on y_hat = -0.2 with variance v gives
  // y = -0.2 v / (1 + v) (the MAP of a half-Gaussian), and leaves y_hat >= 0 alone.
  const KinematicMetric metric = KinematicMetric::euclidean(22);
  double previous = -0.2;
  for (double v : {1.0, 0.1, 0.01, 1e-4}) {
    LinearObservation obs = compile(parse(fmt::format("- {{type: floor, joints: [pelvis], frames: [0], variance: {}}}", v)),
                                    1, skel());
    ProjectionSolver solver(metric);
    solver.set_observation(obs);
    Eigen::VectorXd x = Eigen::VectorXd::Zero(obs.dim());
    x[1] = -0.2;
    Eigen::VectorXd out = solver.project(x).col(0);
    CHECK(out[1] == Approx(-0.2 * v / (1 + v)).margin(1e-12));
    CHECK(out[1] > previous);
    previous = out[1];
    x[1] = 0.3;
    CHECK(solver.project(x)(1, 0) == Approx(0.3).margin(1e-15));
  }
}

TEST_CASE("inequality items compile to G x <= h rows, errors name item and key", "[control][inequality]") {
  const int T = 10, J = 22;
  LinearObservation floor = compile(parse("- {type: floor, height: 0.02}"), T, skel());
  CHECK(floor.rows() == 0);
  REQUIRE(floor.inequalities() == 2 * T);  // the two toes at every frame
  CHECK(floor.G.coeff(0, LinearObservation::index(0, 10, 1, J)) == -1.0);
  CHECK(floor.h[0] == -0.02);
  LinearObservation hs = compile(parse("- {type: half_space, joints: [l_wrist], frames: [2], normal: [0, 2, 0], "
                                       "offset: 0.1, relative_to: head}"),
                                 T, skel());
  REQUIRE(hs.inequalities() == 1);
  CHECK(hs.G.coeff(0, LinearObservation::index(2, 20, 1, J)) == -1.0);  // the normal is normalised
  CHECK(hs.G.coeff(0, LinearObservation::index(2, 15, 1, J)) == 1.0);
  CHECK(hs.h[0] == -0.1);
  LinearObservation box = compile(parse("- {type: box, joints: [0], frames: [1], axes: xz, min: -1, max: [1, 2]}"), T,
                                  skel());
  CHECK(box.inequalities() == 4);
  LinearObservation speed = compile(parse("- {type: speed_limit, joints: [0], axes: y, max: 0.05}"), T, skel());
  CHECK(speed.inequalities() == 2 * (T - 1));
  // G and h move into model units like A and y
  LinearObservation m = affine_to_model(hs, {0.5, 2.0, 0.25}, {0.1, 0.9, -0.3});
  CHECK(m.G.coeff(0, LinearObservation::index(2, 20, 1, J)) == -2.0);
  CHECK(m.h[0] == Approx(-0.1 - (-0.9 + 0.9)));

  const std::vector<std::pair<std::string, std::vector<std::string>>> bad = {
      {"- {type: half_space, name: wall, joints: [0], normal: [0, 0, 0]}", {"'wall'", "normal", "zero"}},
      {"- {type: half_space, joints: [0]}", {"normal"}},
      {"- {type: box, name: cage, joints: [0], min: [1, 0, 0], max: [0, 1, 1]}", {"'cage'", "min", "empty"}},
      {"- {type: box, joints: [0]}", {"min", "max"}},
      {"- {type: box, joints: [0], axes: xz, min: [0, 0, 0]}", {"min", "per axis"}},
      {"- {type: speed_limit, joints: [0]}", {"max", "metres per frame"}},
      {"- {type: speed_limit, joints: [0], max: -1}", {"max", "> 0"}},
      {"- {type: speed_limit, joints: [0], frames: [9], max: 1}", {"frames", "transition"}},
      {"- {type: floor, height: 1, camera: {scale: 1}}", {"camera", "does not apply"}},
      {"- {type: floor, score_only: true}", {"score_only", "tangent and facing"}},
      {"- {type: half_space, joints: [head], normal: [0, 1, 0], relative_to: head}", {"relative_to", "reference"}},
      {"- {type: half_space, joints: [head], normal: [0, 1, 0], relative_to: haed}", {"relative_to", "did you mean"}},
      {"- {type: tangent, name: heading, joints: [0, 1], frames: [2], values: [1, 0]}", {"'heading'", "one joint"}},
      {"- {type: tangent, joints: [0], frames: [2], values: [0, 0]}", {"values", "zero"}},
      {"- {type: tangent, joints: [0], frames: [2], values: [[1, 0, 0]]}", {"values", "shape"}},
      {"- {type: tangent, joints: [0], values: [1, 0]}", {"frames"}},
      {"- {type: tangent, joints: [0], frames: [2], values: [1, 0], min_speed: -1}", {"min_speed"}},
      {"- {type: facing, joints: [1], frames: [2], values: [0, 1]}", {"two joints"}},
      {"- {type: flor}", {"did you mean 'floor'"}},
  };
  for (const auto& [text, words] : bad) {
    std::string e = compile_error(text, T);
    INFO(text << " -> " << e);
    CHECK(!e.empty());
    for (const auto& w : words) CHECK(e.find(w) != std::string::npos);
  }
  // from_source where the source does not move
  std::vector<float> still(static_cast<size_t>(T) * J * 3, 0.5f);
  std::string e = compile_error("- {type: tangent, joints: [0], frames: [3], from_source: true}", T, &still);
  CHECK(e.find("frame 3") != std::string::npos);
  CHECK(e.find("from_source") != std::string::npos);
}

TEST_CASE("direction rows: a motion along the direction meets them, angle errors read the same definition",
          "[control][inequality]") {
  std::mt19937_64 rng(8);
  const int T = 12, J = 22;
  std::vector<float> src = random_motion(rng, T, skel());
  // tangent and facing from the source: the source itself meets every row and scores 0 degrees
  LinearObservation obs = compile(parse("- {type: tangent, joints: [pelvis], frames: [0, 5, 11], axes: xyz, "
                                        "from_source: true, min_speed: 0}\n"
                                        "- {type: facing, frames: [3], from_source: true, min_width: 0}"),
                                  T, skel(), src.data());
  CHECK(obs.rows() == 3 * 2 + 1);
  CHECK(obs.inequalities() == 4);
  REQUIRE(obs.directions.size() == 4u);
  Eigen::VectorXd x = to_vector(src);
  CHECK((obs.A * x - obs.y).cwiseAbs().maxCoeff() < 1e-5);
  CHECK(max_inequality_violation(obs, src.data()) < 1e-6);
  for (double a : direction_errors(obs, src.data())) CHECK(a < 1e-2);
  // direction rows are not control entries
  CHECK(observation_entry_errors(obs, src.data()).empty());

  // Projecting a motion onto explicit directions makes it move and face along them.
  LinearObservation want = compile(parse("- {type: tangent, joints: [pelvis], frames: [4, 8], values: [1, 1], "
                                         "min_speed: 0.02}\n"
                                         "- {type: facing, frames: [6], values: [[-1, 0]]}"),
                                   T, skel());
  ProjectionSolver solver(KinematicMetric::kinematic(skel()));
  solver.set_observation(want);
  Eigen::VectorXd out = solver.project(x).col(0);
  std::vector<float> outf(out.data(), out.data() + out.size());
  for (double a : direction_errors(want, outf.data())) CHECK(a < 1e-2);  // float32 rounding of the positions
  Eigen::VectorXd v = joint_velocity(outf.data(), T, J, 0, 4, {0, 2});
  CHECK(v.dot(Eigen::Vector2d(1, 1).normalized()) >= 0.02 - 1e-6);
  Eigen::Vector2d fw = body_forward(outf.data(), J, 2, 1, 6);
  CHECK(fw.dot(Eigen::Vector2d(-1, 0)) >= 0.05 - 1e-6);
  CHECK(max_hard_violation(want, out) < 1e-9);
  CHECK(max_hard_eq_residual(want, out) < 1e-9);
  // angle errors of a motion facing the other way are 180 degrees
  Eigen::Vector2d here = body_forward(src.data(), J, 2, 1, 3);
  LinearObservation opposite = compile(parse(fmt::format("- {{type: facing, frames: [3], values: [{}, {}], score_only: true}}",
                                                         -here[0], -here[1])),
                                       T, skel());
  CHECK(opposite.rows() == 0);  // score_only: measured, not imposed
  CHECK(direction_errors(opposite, src.data())[0] == Approx(180.0).margin(1e-3));
}

TEST_CASE("new items round-trip through HDF5 and explicit targets", "[control][inequality]") {
  std::mt19937_64 rng(4);
  const int T = 9;
  std::vector<float> src = random_motion(rng, T, skel());
  ConstraintSpec spec = parse(
      "- {type: floor, name: f, joints: [l_foot, r_foot], height: 0.01, variance: 0.5}\n"
      "- {type: half_space, joints: [20], frames: {start: 2, stop: 6}, normal: [1, 0, 1], offset: -3, relative_to: 0}\n"
      "- {type: box, joints: [0], axes: [x, z], min: [-5, -5], max: 5}\n"
      "- {type: speed_limit, joints: [pelvis], frames: [1, 2], max: [0.5, 0.4, 0.5]}\n"
      "- {type: tangent, joints: [pelvis], frames: [3, 4], from_source: true, min_speed: 0.0}\n"
      "- {type: facing, frames: [2], from_source: true, score_only: true, min_width: 0.01}");
  TempDir dir("ineq_h5");
  const std::string path = (dir.path / "spec.h5").string();
  save_constraint_spec_h5(spec, path);
  ConstraintSpec back = load_constraint_spec_h5(path);
  REQUIRE(back.items.size() == spec.items.size());
  for (size_t i = 0; i < spec.items.size(); ++i) CHECK(back.items[i] == spec.items[i]);
  // explicit targets give the same rows without the source
  ConstraintSpec expl = with_explicit_targets(spec, T, skel(), src.data());
  LinearObservation a = compile(spec, T, skel(), src.data()), b = compile(expl, T, skel());
  CHECK((Eigen::MatrixXd(a.A.toDense()) - Eigen::MatrixXd(b.A.toDense())).cwiseAbs().maxCoeff() < 1e-12);
  CHECK((Eigen::MatrixXd(a.G.toDense()) - Eigen::MatrixXd(b.G.toDense())).cwiseAbs().maxCoeff() < 1e-12);
  CHECK((a.h - b.h).cwiseAbs().maxCoeff() < 1e-12);
  CHECK(a.directions.size() == b.directions.size());
}
