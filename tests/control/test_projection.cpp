// The kinematic metric (eq. (11)) and the structured projection solver (eq. (7)):
// property tests over random constraint sets of every item type against the dense
// reference, exactness of hard rows, the soft limit, DDNM, the metric's effect,
// idempotence, the factorisation cache, model-unit solving; a hidden benchmark.
#include <catch2/catch.hpp>

#include <chrono>
#include <iostream>

#include "control/kinematic_metric.h"
#include "control/linear_observation.h"
#include "control/projection_solver.h"
#include "control_test_util.h"
#include "data/skeleton.h"

using namespace mc;
using namespace mc::test;

namespace {

const Skeleton& skel() { return humanml3d_skeleton(); }

std::vector<KinematicMetric> both_metrics() {
  return {KinematicMetric::euclidean(22), KinematicMetric::kinematic(skel(), 10.0, 1.0)};
}

// x_hat: the source motion plus noise, as columns.
Eigen::MatrixXd noisy_columns(std::mt19937_64& rng, const std::vector<float>& src, int columns, double noise = 0.2) {
  std::normal_distribution<double> n(0.0, noise);
  Eigen::MatrixXd x(static_cast<Eigen::Index>(src.size()), columns);
  for (int s = 0; s < columns; ++s)
    for (Eigen::Index i = 0; i < x.rows(); ++i) x(i, s) = src[static_cast<size_t>(i)] + n(rng);
  return x;
}

// The random constraint sets the property tests run over: each type alone, and
// mixtures of 2-4 random types.
std::vector<std::vector<std::string>> random_type_sets(std::mt19937_64& rng, int mixtures) {
  std::vector<std::vector<std::string>> sets;
  for (auto& t : constraint_types()) sets.push_back({t});
  const auto& types = constraint_types();
  for (int k = 0; k < mixtures; ++k) {
    std::vector<std::string> s;
    int n = uniform_int(rng, 2, 4);
    for (int i = 0; i < n; ++i) s.push_back(types[uniform_int(rng, 0, static_cast<int>(types.size()) - 1)]);
    sets.push_back(s);
  }
  return sets;
}

// The item types a drawn observation really holds (conflicting draws are dropped).
std::string describe(const LinearObservation& obs) {
  std::string s;
  for (auto& label : obs.item_labels) s += (s.empty() ? "" : " + ") + label;
  return s;
}

double max_hard_residual(const LinearObservation& obs, const Eigen::MatrixXd& x) {
  Eigen::MatrixXd r = obs.A * x;
  r.colwise() -= obs.y;
  double worst = 0;
  for (int k = 0; k < obs.rows(); ++k)
    if (obs.is_hard(k)) worst = std::max(worst, r.row(k).cwiseAbs().maxCoeff());
  return worst;
}

}  // namespace

TEST_CASE("kinematic metric: blocks, inverse, diagonal, column norms, frame norm", "[control][projflow]") {
  KinematicMetric m = KinematicMetric::kinematic(skel(), 10.0, 1.0);
  const Eigen::MatrixXd L = skel().laplacian();
  CHECK((m.block() - (10.0 * L + Eigen::MatrixXd::Identity(22, 22))).norm() < 1e-14);
  CHECK((m.block() * m.block_inverse() - Eigen::MatrixXd::Identity(22, 22)).norm() < 1e-12);
  const int T = 3;
  Eigen::MatrixXd R = m.dense(T);
  Eigen::MatrixXd R_inv = R.inverse();
  for (int t = 0; t < T; ++t)
    for (int j = 0; j < 22; ++j)
      for (int c = 0; c < 3; ++c) {
        int i = (t * 22 + j) * 3 + c;
        CHECK(std::abs(R_inv(i, i) - m.inverse_diagonal()[j]) < 1e-12);
      }
  for (int j = 0; j < 22; ++j)
    CHECK(std::abs(m.inverse_column_norms()[j] - m.block_inverse().col(j).norm()) < 1e-14);

  std::mt19937_64 rng(9);
  Eigen::MatrixXd x = Eigen::MatrixXd::Random(3 * 22 * T, 4);
  CHECK((m.apply_inverse(x) - R_inv * x).norm() < 1e-11);
  CHECK((m.apply(x) - R * x).norm() < 1e-11);
  CHECK((m.apply(m.apply_inverse(x)) - x).norm() < 1e-11);
  // eq. (17): the R-norm of one frame
  Eigen::VectorXd v = x.col(0).head(66);
  CHECK(std::abs(m.frame_norm(v.data()) - std::sqrt(v.dot(m.dense(1) * v))) < 1e-12);

  KinematicMetric e = KinematicMetric::euclidean(22);
  CHECK(e.is_euclidean());
  CHECK(e.block_inverse() == Eigen::MatrixXd::Identity(22, 22));
  CHECK(e.apply_inverse(x) == x);

  MetricConfig cfg;
  CHECK(KinematicMetric::from_config(cfg, skel()).w_kin() == 10.0);
  cfg.type = "euclidean";
  CHECK(KinematicMetric::from_config(cfg, skel()).is_euclidean());
  CHECK_THROWS_AS(KinematicMetric(L, 10.0, 0.0), UserError);
  CHECK_THROWS_AS(KinematicMetric(L, -1.0, 1.0), UserError);
}

TEST_CASE("structured projection matches the dense reference for every item type", "[control][projflow]") {
  std::mt19937_64 rng(0xC0FFEE);
  int cases = 0;
  for (const auto& types : random_type_sets(rng, 24))
    for (bool soft : {false, true})
      for (const KinematicMetric& metric : both_metrics())
        for (int draw = 0; draw < 2; ++draw) {
          const int T = uniform_int(rng, 2, 8);
          auto src = random_motion(rng, T, skel());
          LinearObservation obs = random_observation(types, rng, T, skel(), src, soft);
          Eigen::MatrixXd x_hat = noisy_columns(rng, src, 3);
          ProjectionSolver solver(metric);
          solver.set_observation(obs);
          Eigen::MatrixXd x_s = solver.project(x_hat);
          Eigen::MatrixXd x_d = dense_reference_projection(metric, obs, x_hat);
          const double scale = (x_d - x_hat).norm();
          INFO(describe(obs) << (soft ? " soft" : " hard") << (metric.is_euclidean() ? " euclidean" : " kinematic")
                               << " T=" << T << " rows=" << obs.rows() << " groups=" << solver.groups());
          CHECK((x_s - x_d).norm() <= 1e-9 * scale + 1e-13);
          CHECK(solver.jittered_groups() == 0);
          ++cases;
        }
  CHECK(cases >= 4 * 31 * 2);
}

TEST_CASE("hard rows hold exactly after projection, 2D rows included", "[control][projflow]") {
  std::mt19937_64 rng(424242);
  for (const auto& types : random_type_sets(rng, 30))
    for (const KinematicMetric& metric : both_metrics()) {
      const int T = uniform_int(rng, 2, 8);
      auto src = random_motion(rng, T, skel());
      LinearObservation obs = random_observation(types, rng, T, skel(), src, false);
      Eigen::MatrixXd x_hat = noisy_columns(rng, src, 2, 1.0);  // far from the constraint set
      ProjectionSolver solver(metric);
      solver.set_observation(obs);
      INFO(describe(obs) << (metric.is_euclidean() ? " euclidean" : " kinematic"));
      CHECK(max_hard_residual(obs, solver.project(x_hat)) <= 1e-9);
    }
}

TEST_CASE("soft rows approach their targets monotonically as the variance shrinks", "[control][projflow]") {
  std::mt19937_64 rng(77);
  const std::vector<double> variances = {10.0, 1.0, 1e-1, 1e-2, 1e-3, 1e-4, 1e-6, 1e-8};
  for (const auto& type : constraint_types())
    for (const KinematicMetric& metric : both_metrics())
      for (int draw = 0; draw < 3; ++draw) {
        const int T = uniform_int(rng, 2, 8);
        auto src = random_motion(rng, T, skel());
        LinearObservation obs = random_observation({type}, rng, T, skel(), src, true);
        Eigen::MatrixXd x_hat = noisy_columns(rng, src, 1, 0.5);
        const double r0 = (obs.A * x_hat - obs.y).norm();
        ProjectionSolver solver(metric);
        double previous = r0;
        INFO(type << (metric.is_euclidean() ? " euclidean" : " kinematic") << " r0=" << r0);
        for (double v : variances) {
          obs.variance.setConstant(v);
          solver.set_observation(obs);
          double r = (obs.A * solver.project(x_hat) - obs.y).norm();
          INFO("variance " << v << " residual " << r);
          CHECK(r <= previous * (1 + 1e-12) + 1e-15);
          previous = r;
        }
        CHECK(previous <= 1e-5 * r0 + 1e-12);
        CHECK(solver.structure_builds() == 1);  // only variances changed
      }
}

TEST_CASE("with R = I and Sigma = 0 the projection is DDNM's x + A^+(y - Ax)", "[control][projflow]") {
  std::mt19937_64 rng(31337);
  for (const auto& types : random_type_sets(rng, 16)) {
    const int T = uniform_int(rng, 2, 8);
    auto src = random_motion(rng, T, skel());
    LinearObservation obs = random_observation(types, rng, T, skel(), src, false);
    Eigen::MatrixXd x_hat = noisy_columns(rng, src, 2);
    // A^+ from a complete orthogonal decomposition of the dense A, independent of eq. (7).
    Eigen::MatrixXd A = obs.A.toDense();
    Eigen::MatrixXd pinv = Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd>(A).pseudoInverse();
    Eigen::MatrixXd residual = -(A * x_hat);
    residual.colwise() += obs.y;
    Eigen::MatrixXd ddnm = x_hat + pinv * residual;
    ProjectionSolver solver(KinematicMetric::euclidean(22));
    solver.set_observation(obs);
    Eigen::MatrixXd x = solver.project(x_hat);
    INFO(describe(obs));
    CHECK((x - ddnm).norm() <= 1e-9 * (ddnm - x_hat).norm() + 1e-13);
  }
}

TEST_CASE("the metric matters: a kinematic pelvis correction carries its neighbours", "[control][projflow]") {
  std::mt19937_64 rng(2);
  const int T = 6, frame = 3;
  auto src = random_motion(rng, T, skel());
  auto spec = parse_constraint_spec_yaml(R"(
- {type: keyframe, joints: [pelvis], frames: [3], values: [[[0.4, 1.3, -0.6]]]}
)", "pelvis.yaml");
  LinearObservation obs = compile(spec, T, skel(), src.data());
  Eigen::VectorXd x_hat = to_vector(src);
  auto at = [&](const Eigen::VectorXd& x, int t, int j) { return Eigen::Vector3d(x.segment((t * 22 + j) * 3, 3)); };

  ProjectionSolver kinematic(KinematicMetric::kinematic(skel()));
  kinematic.set_observation(obs);
  Eigen::VectorXd xk = kinematic.project(x_hat);
  ProjectionSolver euclidean(KinematicMetric::euclidean(22));
  euclidean.set_observation(obs);
  Eigen::VectorXd xe = euclidean.project(x_hat);

  const Eigen::Vector3d pelvis_shift = at(xk, frame, 0) - at(x_hat, frame, 0);
  CHECK((at(xk, frame, 0) - Eigen::Vector3d(0.4, 1.3, -0.6)).norm() < 1e-12);
  CHECK((at(xe, frame, 0) - Eigen::Vector3d(0.4, 1.3, -0.6)).norm() < 1e-12);
  REQUIRE(pelvis_shift.norm() > 0.3);
  for (int j : {1, 2, 3}) {
    const Eigen::Vector3d shift = at(xk, frame, j) - at(x_hat, frame, j);
    INFO("joint " << j << " moves by " << shift.norm() / pelvis_shift.norm() << " of the pelvis correction");
    // Same direction, a substantial fraction: the correction spreads along the tree.
    CHECK(shift.dot(pelvis_shift) / pelvis_shift.squaredNorm() > 0.5);
    CHECK((shift.normalized() - pelvis_shift.normalized()).norm() < 1e-9);
    CHECK(at(xe, frame, j) == at(x_hat, frame, j));  // Euclidean: neighbours untouched
  }
  // Far joints move less than near ones, and other frames not at all.
  CHECK((at(xk, frame, 20) - at(x_hat, frame, 20)).norm() < (at(xk, frame, 3) - at(x_hat, frame, 3)).norm());
  for (int t = 0; t < T; ++t)
    if (t != frame)
      for (int j = 0; j < 22; ++j) CHECK(at(xk, t, j) == at(x_hat, t, j));
}

TEST_CASE("projecting twice equals projecting once for hard constraints", "[control][projflow]") {
  std::mt19937_64 rng(555);
  for (const auto& types : random_type_sets(rng, 10))
    for (const KinematicMetric& metric : both_metrics()) {
      const int T = uniform_int(rng, 2, 8);
      auto src = random_motion(rng, T, skel());
      LinearObservation obs = random_observation(types, rng, T, skel(), src, false);
      ProjectionSolver solver(metric);
      solver.set_observation(obs);
      Eigen::MatrixXd once = solver.project(noisy_columns(rng, src, 2, 0.5));
      Eigen::MatrixXd twice = solver.project(once);
      INFO(describe(obs));
      CHECK((twice - once).cwiseAbs().maxCoeff() <= 1e-10);
    }
}

TEST_CASE("factorisations are cached while A and Sigma are unchanged", "[control][projflow]") {
  std::mt19937_64 rng(8);
  const int T = 8;
  auto src = random_motion(rng, T, skel());
  auto spec = parse_constraint_spec_yaml(R"(
- {type: trajectory, name: pelvis, joints: [pelvis], from_source: true}
- {type: keyframe, name: hands, joints: [l_wrist, r_wrist], frames: [2, 6], from_source: true, variance: 0.01}
- {type: camera_2d, name: head 2d, joints: [head], frames: [1, 5], camera: {scale: 1, pitch_deg: 15, yaw_deg: 20}, from_source: true}
- {type: loop, name: feet, joints: [l_foot, r_foot]}
)", "cache.yaml");
  LinearObservation obs = compile(spec, T, skel(), src.data());
  const KinematicMetric metric = KinematicMetric::kinematic(skel());
  ProjectionSolver solver(metric);
  solver.set_observation(obs);
  const int64_t f0 = solver.factorizations();
  CHECK(f0 == solver.distinct_factors());
  // Groups: frames 3, 4 one per axis (pelvis only, 6 alike); frames 2, 6 one per
  // axis (pelvis + hands, 6 alike); frames 1, 5 one each (the camera couples the
  // axes, 2 alike); frames 0 and 7 joined by the loop, one per axis (3 alike).
  // 17 groups, 4 distinct factorisations.
  CHECK(solver.groups() == 17);
  CHECK(f0 == 4);
  CHECK(solver.structure_builds() == 1);
  Eigen::MatrixXd x_hat = noisy_columns(rng, src, 2);
  Eigen::MatrixXd first = solver.project(x_hat);

  solver.set_observation(obs);  // identical observation: nothing is refactorised
  CHECK(solver.factorizations() == f0);
  CHECK(solver.structure_builds() == 1);
  CHECK(solver.project(x_hat) == first);
  CHECK(solver.project(x_hat) == first);

  LinearObservation moved = obs;  // new targets only: factors reused
  moved.y.array() += 0.1;
  solver.set_observation(moved);
  CHECK(solver.factorizations() == f0);
  Eigen::MatrixXd x_moved = solver.project(x_hat);
  Eigen::MatrixXd reference = dense_reference_projection(metric, moved, x_hat);
  CHECK((x_moved - reference).norm() <= 1e-9 * (reference - x_hat).norm());
  solver.update_targets(obs.y);
  CHECK(solver.project(x_hat) == first);

  // One soft row's variance changes: only its group is refactorised.
  LinearObservation reweighted = obs;
  int soft_row = -1;
  for (int k = 0; k < obs.rows(); ++k)
    if (!obs.is_hard(k)) soft_row = k;
  REQUIRE(soft_row >= 0);
  reweighted.variance[soft_row] = 0.5;
  solver.set_observation(reweighted);
  CHECK(solver.factorizations() == f0 + 1);
  CHECK(solver.distinct_factors() == f0 + 1);  // the group no longer shares its factor
  CHECK(solver.structure_builds() == 1);
  reference = dense_reference_projection(metric, reweighted, x_hat);
  CHECK((solver.project(x_hat) - reference).norm() <= 1e-9 * (reference - x_hat).norm());

  // A new operator rebuilds the structure.
  spec.items.pop_back();
  solver.set_observation(compile(spec, T, skel(), src.data()));
  CHECK(solver.structure_builds() == 2);
}

TEST_CASE("a batch of samples projects like each sample alone", "[control][projflow]") {
  std::mt19937_64 rng(12);
  const int T = 8;
  auto src = random_motion(rng, T, skel());
  LinearObservation obs = random_observation({"camera_2d", "trajectory", "loop"}, rng, T, skel(), src, false);
  ProjectionSolver solver(KinematicMetric::kinematic(skel()));
  solver.set_observation(obs);
  Eigen::MatrixXd batch = noisy_columns(rng, src, 5);
  Eigen::MatrixXd together = solver.project(batch);
  for (int s = 0; s < 5; ++s) {
    Eigen::VectorXd alone = solver.project(batch.col(s));
    CHECK((together.col(s) - alone).cwiseAbs().maxCoeff() < 1e-14);
  }
}

TEST_CASE("solving in model units and mapping back equals solving in world units (hard)", "[control][projflow]") {
  std::mt19937_64 rng(99);
  // HumanML3D's per-axis normaliser (reference-facts §2).
  const std::array<double, 3> mean{1.6e-4, 0.3766, 0.3102}, stdev{0.5148, 0.6101, 0.8716};
  const double uniform_std = 0.7;
  for (const auto& type : constraint_types())
    for (const KinematicMetric& metric : both_metrics())
      for (int draw = 0; draw < 3; ++draw) {
        // Axis-separable rows give the same minimiser under any per-axis scaling of
        // the metric; camera rows couple axes, so they need a uniform scale here.
        const bool couples_axes = type == "camera_2d";
        const std::array<double, 3> scale = couples_axes ? std::array<double, 3>{uniform_std, uniform_std, uniform_std} : stdev;
        const int T = uniform_int(rng, 2, 8);
        auto src = random_motion(rng, T, skel());
        LinearObservation world = random_observation({type}, rng, T, skel(), src, false);
        LinearObservation model = affine_to_model(world, scale, mean);
        Eigen::MatrixXd x_world = noisy_columns(rng, src, 2, 0.3);
        Eigen::MatrixXd x_model = x_world;
        for (Eigen::Index i = 0; i < x_model.rows(); ++i)
          x_model.row(i) = (x_world.row(i).array() - mean[i % 3]) / scale[i % 3];

        ProjectionSolver world_solver(metric), model_solver(metric);
        world_solver.set_observation(world);
        model_solver.set_observation(model);
        Eigen::MatrixXd expected = world_solver.project(x_world);
        Eigen::MatrixXd back = model_solver.project(x_model);
        for (Eigen::Index i = 0; i < back.rows(); ++i)
          back.row(i) = back.row(i).array() * scale[i % 3] + mean[i % 3];
        INFO(type << (metric.is_euclidean() ? " euclidean" : " kinematic"));
        CHECK((back - expected).norm() <= 1e-9 * (expected - x_world).norm() + 1e-12);
        CHECK(max_hard_residual(world, back) <= 1e-9);
      }

  // Camera rows with the real, non-uniform normaliser: a different (model-unit)
  // minimiser, but the hard 2D rows still hold exactly in world units.
  for (int draw = 0; draw < 5; ++draw) {
    const int T = uniform_int(rng, 2, 8);
    auto src = random_motion(rng, T, skel());
    LinearObservation world = random_observation({"camera_2d"}, rng, T, skel(), src, false);
    ProjectionSolver solver(KinematicMetric::kinematic(skel()));
    solver.set_observation(affine_to_model(world, stdev, mean));
    Eigen::MatrixXd x = noisy_columns(rng, src, 1, 0.3);
    for (Eigen::Index i = 0; i < x.rows(); ++i) x(i, 0) = (x(i, 0) - mean[i % 3]) / stdev[i % 3];
    Eigen::MatrixXd back = solver.project(x);
    for (Eigen::Index i = 0; i < back.rows(); ++i) back(i, 0) = back(i, 0) * stdev[i % 3] + mean[i % 3];
    CHECK(max_hard_residual(world, back) <= 1e-9);
  }
}

TEST_CASE("bench: structured solve of a full hard observation, T = 196", "[.bench]") {
  std::mt19937_64 rng(1);
  const int T = 196;
  auto src = random_motion(rng, T, skel());
  using clock = std::chrono::steady_clock;
  auto ms = [](clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); };
  struct Case {
    const char* name;
    const char* yaml;
  };
  for (const Case& c : {Case{"all 22 joints x 3 axes, every frame, hard",
                             "- {type: trajectory, joints: [0,1,2,3,4,5,6,7,8,9,10,11,12,13,14,15,16,17,18,19,20,21], "
                             "from_source: true}"},
                        Case{"2D: all joints every frame (camera) + pelvis 3D path",
                             "- {type: camera_2d, camera: {scale: 1, pitch_deg: 20, yaw_deg: 30}, from_source: true}\n"
                             "- {type: trajectory, joints: [pelvis], axes: y, from_source: true}"},
                        Case{"worst case: all joints every frame, soft, a different variance per row",
                             "- {type: trajectory, joints: [0,1,2,3,4,5,6,7,8,9,10,11,12,13,14,15,16,17,18,19,20,21], "
                             "from_source: true}"},
                        Case{"OmniControl: 6 joints at 49 frames",
                             "- {type: trajectory, joints: [0, 10, 11, 15, 20, 21], frames: {start: 0, step: 4}, "
                             "from_source: true}"}}) {
    auto spec = parse_constraint_spec_yaml(c.yaml, "bench");
    LinearObservation obs = compile(spec, T, skel(), src.data());
    if (std::string(c.name).rfind("worst", 0) == 0)  // a different variance per row: nothing is shared
      for (int k = 0; k < obs.rows(); ++k) obs.variance[k] = uniform(rng, 1e-3, 1e-1);
    ProjectionSolver solver(KinematicMetric::kinematic(skel()));
    const int reps = 20;
    auto t0 = clock::now();
    for (int r = 0; r < reps; ++r) {
      ProjectionSolver fresh(KinematicMetric::kinematic(skel()));
      fresh.set_observation(obs);
    }
    double setup = ms(clock::now() - t0) / reps;
    solver.set_observation(obs);
    for (int S : {1, 64}) {
      Eigen::MatrixXd out = noisy_columns(rng, src, S);
      t0 = clock::now();
      for (int r = 0; r < reps; ++r) solver.project_in_place(out);  // same work every time
      double project = ms(clock::now() - t0) / reps;
      std::cout << fmt::format("[bench] {}: rows {}, groups {} (largest {}, {} distinct), set_observation {:.2f} ms, "
                               "project S={} {:.2f} ms, max hard residual {:.1e}\n",
                               c.name, obs.rows(), solver.groups(), solver.largest_group(),
                               solver.distinct_factors(), setup, S, project,
                               max_hard_residual(obs, out));
    }
  }
}
