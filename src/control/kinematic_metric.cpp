// The kinematics-aware metric of eq. (11), applied block by block.
#include "control/kinematic_metric.h"

#include <cmath>

#include "core/error.h"
#include "data/skeleton.h"

namespace mc {

KinematicMetric::KinematicMetric(const Eigen::MatrixXd& laplacian, double w_kin, double lambda)
    : w_kin_(w_kin), lambda_(lambda) {
  if (laplacian.rows() == 0 || laplacian.rows() != laplacian.cols())
    fail("kinematic metric: the Laplacian must be square and non-empty, got {}x{}", laplacian.rows(), laplacian.cols());
  if (!laplacian.allFinite() || (laplacian - laplacian.transpose()).cwiseAbs().maxCoeff() > 1e-12)
    fail("kinematic metric: the Laplacian must be finite and symmetric");
  if (!std::isfinite(w_kin) || w_kin < 0) fail("kinematic metric: w_kin must be >= 0, got {}", w_kin);
  if (!std::isfinite(lambda) || !(lambda > 0))
    fail("kinematic metric: lambda must be > 0 (it keeps R positive definite), got {}", lambda);
  // eq. (11): one block per (frame, axis)
  k_ = w_kin * laplacian + lambda * Eigen::MatrixXd::Identity(laplacian.rows(), laplacian.cols());
  euclidean_ = (w_kin == 0.0 || laplacian.isZero(0.0)) && lambda == 1.0;
  factorise();
}

KinematicMetric KinematicMetric::kinematic(const Skeleton& skeleton, double w_kin, double lambda) {
  return KinematicMetric(skeleton.laplacian(), w_kin, lambda);
}

KinematicMetric KinematicMetric::euclidean(int joints) {
  if (joints < 1) fail("euclidean metric: need at least one joint, got {}", joints);
  KinematicMetric m;
  m.k_ = Eigen::MatrixXd::Identity(joints, joints);
  m.euclidean_ = true;
  m.factorise();
  return m;
}

KinematicMetric KinematicMetric::from_config(const MetricConfig& cfg, const Skeleton& skeleton) {
  if (cfg.type == "euclidean") return euclidean(skeleton.num_joints());
  if (cfg.type != "kinematic") fail("metric.type must be 'kinematic' or 'euclidean', got '{}'", cfg.type);
  return kinematic(skeleton, cfg.w_kin, cfg.lambda);
}

void KinematicMetric::factorise() {
  const int J = joints();
  if (euclidean_) {
    // Exact identity, so the Euclidean (DDNM) path has no rounding from an eigensolver.
    k_inv_ = Eigen::MatrixXd::Identity(J, J);
  } else {
    // K is SPD (L is PSD, lambda > 0): K^-1 = V diag(1/ev) V^T, computed once.
    Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(k_);
    const Eigen::VectorXd& ev = es.eigenvalues();
    if (!(ev.minCoeff() > 0)) fail("kinematic metric: K = w_kin L + lambda I is not positive definite");
    const Eigen::MatrixXd& v = es.eigenvectors();
    k_inv_ = v * ev.cwiseInverse().asDiagonal() * v.transpose();
    k_inv_ = 0.5 * (k_inv_ + k_inv_.transpose());
  }
  r_diag_ = k_inv_.diagonal();
  col_norms_ = k_inv_.colwise().norm().transpose();
}

// Each frame's 3J entries, viewed as a J x 3 matrix (row j = joint j), are
// multiplied by the J x J block: that applies it to every axis of the frame.
Eigen::MatrixXd KinematicMetric::apply_block(const Eigen::MatrixXd& block, const Eigen::MatrixXd& x) const {
  const int J = joints();
  if (x.rows() % (3 * J) != 0)
    throw std::invalid_argument(fmt::format("metric: {} rows is not a multiple of 3J = {}", x.rows(), 3 * J));
  if (euclidean_) return x;
  const int T = static_cast<int>(x.rows() / (3 * J));
  using FrameMap = Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>;
  using FrameOut = Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>;
  Eigen::MatrixXd out(x.rows(), x.cols());
  for (Eigen::Index s = 0; s < x.cols(); ++s)
    for (int t = 0; t < T; ++t) {
      const double* in = x.col(s).data() + static_cast<Eigen::Index>(t) * 3 * J;
      double* o = out.col(s).data() + static_cast<Eigen::Index>(t) * 3 * J;
      FrameOut(o, J, 3).noalias() = block * FrameMap(in, J, 3);
    }
  return out;
}

Eigen::MatrixXd KinematicMetric::apply_inverse(const Eigen::MatrixXd& x) const { return apply_block(k_inv_, x); }

Eigen::MatrixXd KinematicMetric::apply(const Eigen::MatrixXd& x) const { return apply_block(k_, x); }

double KinematicMetric::frame_norm(const double* v) const {
  const int J = joints();
  Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>> f(v, J, 3);
  // eq. (17): sum over axes of v_c^T K v_c
  return std::sqrt(std::max(0.0, (f.transpose() * k_ * f).trace()));
}

Eigen::MatrixXd KinematicMetric::dense(int frames) const {
  const int J = joints(), d = 3 * J * frames;
  Eigen::MatrixXd r = Eigen::MatrixXd::Zero(d, d);
  for (int t = 0; t < frames; ++t)
    for (int c = 0; c < 3; ++c)
      for (int a = 0; a < J; ++a)
        for (int b = 0; b < J; ++b) r((t * J + a) * 3 + c, (t * J + b) * 3 + c) = k_(a, b);
  return r;
}

}  // namespace mc
