// The metric R in which ProjFlow measures corrections (eq. (11)):
// R = w_kin (I_3 (x) I_T (x) L_kin) + lambda I, block-diagonal with one J x J
// block K = w_kin L + lambda I per (frame, axis). K is factorised once; nothing
// of size d x d is ever formed except by dense() for tests.
#pragma once
#include <Eigen/Dense>
#include <string>

#include "core/config.h"

namespace mc {

struct Skeleton;

// `metric:` section of a sampler config.
struct MetricConfig : Config {
  std::string type = "kinematic";  // kinematic | euclidean
  double w_kin = 10.0;             // reference-facts §3
  double lambda = 1.0;
  void visit(FieldVisitor& v) override {
    v("type", type, "kinematic (eq. (11)) or euclidean (R = I, the ablation)", one_of({"kinematic", "euclidean"}));
    v("w_kin", w_kin, "weight of the skeleton Laplacian in R", at_least(0.0));
    v("lambda", lambda, "weight of the identity in R (keeps R positive definite)", positive<double>());
  }
};

class KinematicMetric {
 public:
  // K = w_kin L + lambda I from a J x J graph Laplacian. UserError unless
  // w_kin >= 0, lambda > 0 and L is square, symmetric and finite.
  KinematicMetric(const Eigen::MatrixXd& laplacian, double w_kin = 10.0, double lambda = 1.0);
  static KinematicMetric kinematic(const Skeleton& skeleton, double w_kin = 10.0, double lambda = 1.0);
  static KinematicMetric euclidean(int joints);  // R = I
  static KinematicMetric from_config(const MetricConfig& cfg, const Skeleton& skeleton);

  int joints() const { return static_cast<int>(k_.rows()); }
  bool is_euclidean() const { return euclidean_; }
  double w_kin() const { return w_kin_; }
  double lambda() const { return lambda_; }

  const Eigen::MatrixXd& block() const { return k_; }              // K
  const Eigen::MatrixXd& block_inverse() const { return k_inv_; }  // K^-1 = V diag(1/ev) V^T
  // r_jj = (K^-1)_jj, the diagonal of R^-1 for every frame and axis (eq. (18)).
  const Eigen::VectorXd& inverse_diagonal() const { return r_diag_; }
  // ||column j of K^-1||; reference-facts §3 spreads trust with q_j = 1 / this^2.
  const Eigen::VectorXd& inverse_column_norms() const { return col_norms_; }

  // R^-1 x and R x for motions stored frame-major (index (t*J + j)*3 + c), one
  // column per sample; rows must be a multiple of 3J.
  Eigen::MatrixXd apply_inverse(const Eigen::MatrixXd& x) const;
  Eigen::MatrixXd apply(const Eigen::MatrixXd& x) const;
  // ||v||_R for one frame v (3J numbers, joint-major): sqrt(sum_c v_c^T K v_c),
  // the curvature norm of eq. (17) when v is a second temporal difference.
  double frame_norm(const double* v) const;
  // The dense d x d R for `frames` frames (tests and the dense reference solver only).
  Eigen::MatrixXd dense(int frames) const;

 private:
  KinematicMetric() = default;
  void factorise();
  Eigen::MatrixXd apply_block(const Eigen::MatrixXd& block, const Eigen::MatrixXd& x) const;

  Eigen::MatrixXd k_, k_inv_;
  Eigen::VectorXd r_diag_, col_norms_;
  double w_kin_ = 0.0, lambda_ = 1.0;
  bool euclidean_ = false;
};

}  // namespace mc
