// ProjFlow step (eqs. (5)-(10)), pseudo-observations (eqs. (13)-(18)), and the
// reconstruction-guidance baseline over the same observations.
#include "samplers/projflow.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>

#include "control/control_task.h"
#include "core/error.h"
#include "samplers/task_observation.h"

namespace mc {

// ---------------------------------------------------------------- pseudo-observations

PseudoCandidates pseudo_candidates(const LinearObservation& hard) {
  const int J = hard.joints, T = hard.frames;
  // (joint, axis) -> observed frame -> value (model units)
  std::map<std::pair<int, int>, std::map<int, double>> observed;
  for (int r = 0; r < hard.rows(); ++r) {
    if (!hard.is_hard(r)) continue;
    if (hard.A.outerIndexPtr()[r + 1] - hard.A.outerIndexPtr()[r] != 1) continue;
    Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(hard.A, r);
    if (it.value() == 0.0) continue;
    const int col = static_cast<int>(it.col());
    const int frame = col / (3 * J), joint = (col / 3) % J, axis = col % 3;
    observed[{joint, axis}][frame] = hard.y[r] / it.value();
  }
  PseudoCandidates out;
  for (auto& [ja, frames] : observed) {
    for (int n = 0; n < T; ++n) {
      if (frames.count(n)) continue;
      auto after = frames.lower_bound(n);
      const bool has_after = after != frames.end();
      const bool has_before = after != frames.begin();
      auto before = has_before ? std::prev(after) : frames.end();
      double target;
      int dist;
      if (has_before && has_after) {
        const double w = double(n - before->first) / double(after->first - before->first);
        target = (1 - w) * before->second + w * after->second;
        dist = std::min(n - before->first, after->first - n);
      } else if (has_before) {
        target = before->second;
        dist = n - before->first;
      } else {
        target = after->second;
        dist = after->first - n;
      }
      out.entries.push_back({n, ja.first, ja.second, dist, target});
    }
  }
  std::sort(out.entries.begin(), out.entries.end(), [](const auto& a, const auto& b) {
    return std::tie(a.frame, a.joint, a.axis) < std::tie(b.frame, b.joint, b.axis);
  });
  return out;
}

PseudoStep pseudo_step(const PseudoCandidates& cand, const PseudoObservationConfig& cfg,
                       const KinematicMetric& metric, const Eigen::Ref<const Eigen::MatrixXd>& x1_hat, int k,
                       int steps, double t) {
  PseudoStep out;
  if (cand.entries.empty()) return out;
  // eq. (14) on the step grid: l = l_max - (l_max - l_min) k / (N - 1)
  const double frac = steps > 1 ? double(k) / double(steps - 1) : 1.0;
  const double radius = cfg.l_max - (cfg.l_max - cfg.l_min) * frac;
  for (int e = 0; e < static_cast<int>(cand.entries.size()); ++e)
    if (cand.entries[e].distance < radius) out.active.push_back(e);
  if (out.active.empty()) return out;

  // eq. (17): curvature of the clean estimate in the R-norm, per frame.
  const int T = static_cast<int>(x1_hat.rows());
  std::vector<double> s(T, 0.0);
  if (T >= 3) {
    Eigen::VectorXd a(x1_hat.cols());
    for (int n = 1; n + 1 < T; ++n) {
      a = x1_hat.row(n + 1) - 2 * x1_hat.row(n) + x1_hat.row(n - 1);
      s[n] = metric.frame_norm(a.data());
    }
    s[0] = s[1];
    s[T - 1] = s[T - 2];
  }
  std::vector<double> sorted(s.begin(), s.end());
  std::nth_element(sorted.begin(), sorted.begin() + T / 2, sorted.end());
  const double s_med = sorted[T / 2];
  const double tau = cfg.tau_min + (1 - cfg.tau_min) * (1 - t);  // eq. (16)
  auto frame_trust = [&](int n) {
    const double ratio = s_med > 0 ? s[n] / s_med : 0.0;
    const double pi = tau * cfg.c0 / (1 + cfg.lambda_s * std::pow(ratio, cfg.p));  // eq. (15)
    return std::clamp(pi, cfg.pi_min, cfg.pi_max);
  };

  // Spread the frame trust over the frame's halo joints with q_j = 1 / ||K^-1 e_j||^2,
  // then sigma^2 = r_jj (1 - pi) / pi (eq. (18)).
  const Eigen::VectorXd& col = metric.inverse_column_norms();
  const Eigen::VectorXd& r = metric.inverse_diagonal();
  out.variance.resize(out.active.size());
  size_t i = 0;
  while (i < out.active.size()) {
    const int n = cand.entries[out.active[i]].frame;
    size_t j = i;
    double q_sum = 0;
    int last_joint = -1;
    while (j < out.active.size() && cand.entries[out.active[j]].frame == n) {
      const int joint = cand.entries[out.active[j]].joint;
      if (joint != last_joint) q_sum += 1.0 / (col[joint] * col[joint]);  // entries are sorted by joint
      last_joint = joint;
      ++j;
    }
    const double pi_n = frame_trust(n);
    for (size_t m = i; m < j; ++m) {
      const int joint = cand.entries[out.active[m]].joint;
      const double q = 1.0 / (col[joint] * col[joint]);
      const double pi = std::clamp(pi_n * q / q_sum, cfg.pi_min, cfg.pi_max);
      out.variance[m] = std::max(cfg.min_variance, r[joint] * (1 - pi) / pi);
    }
    i = j;
  }
  return out;
}

LinearObservation with_pseudo_rows(const LinearObservation& hard, const PseudoCandidates& cand,
                                   const PseudoStep& step) {
  LinearObservation o;
  o.frames = hard.frames;
  o.joints = hard.joints;
  o.source = hard.source;
  o.item_labels = hard.item_labels;
  o.G = hard.G;  // inequalities pass through unchanged (their rows keep their indices)
  o.h = hard.h;
  o.g_variance = hard.g_variance;
  o.item_of_g_row = hard.item_of_g_row;
  o.directions = hard.directions;
  o.item_labels.push_back("pseudo-observations (eq. (13))");
  const int m0 = hard.rows(), m = m0 + static_cast<int>(step.active.size());
  std::vector<Eigen::Triplet<double>> trip;
  trip.reserve(hard.A.nonZeros() + step.active.size());
  for (int r = 0; r < m0; ++r)
    for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(hard.A, r); it; ++it)
      trip.emplace_back(r, static_cast<int>(it.col()), it.value());
  o.y.resize(m);
  o.variance.resize(m);
  o.y.head(m0) = hard.y;
  o.variance.head(m0) = hard.variance;
  o.item_of_row = hard.item_of_row;
  for (size_t i = 0; i < step.active.size(); ++i) {
    const auto& e = cand.entries[step.active[i]];
    const int r = m0 + static_cast<int>(i);
    trip.emplace_back(r, LinearObservation::index(e.frame, e.joint, e.axis, hard.joints), 1.0);
    o.y[r] = e.target;
    o.variance[r] = step.variance[i];
    o.item_of_row.push_back(static_cast<int>(o.item_labels.size()) - 1);
  }
  o.A.resize(m, hard.dim());
  o.A.setFromTriplets(trip.begin(), trip.end());
  o.A.makeCompressed();
  return o;
}

// ---------------------------------------------------------------- ProjFlow stepper

ProjFlowStepper::ProjFlowStepper(const ProjFlowConfig& cfg, const KinematicMetric& metric,
                                 std::vector<LinearObservation> model_observations)
    : cfg_(cfg), metric_(metric), obs_(std::move(model_observations)), state_(obs_.size()) {
  for (size_t i = 0; i < obs_.size(); ++i) {
    if (obs_[i].joints != metric_.joints())
      fail("observation {} has {} joints but the metric has {}", i, obs_[i].joints, metric_.joints());
    state_[i].solver = std::make_unique<ProjectionSolver>(metric_);
    if (cfg_.pseudo_observations.enabled) state_[i].candidates = pseudo_candidates(obs_[i]);
  }
}

void ProjFlowStepper::project_sample(int64_t id, float* x1, int frames, int k, int steps, double t) {
  auto& st = state_[id];
  const LinearObservation& hard = obs_[id];
  if (hard.rows() == 0 && hard.inequalities() == 0) return;
  if (hard.frames != frames)
    fail("observation of sample {} covers {} frames but the sample has {}", id, hard.frames, frames);
  const int J = hard.joints, d = hard.dim();
  Eigen::Map<Eigen::VectorXf> xf(x1, d);
  Eigen::MatrixXd x = xf.cast<double>();
  if (!st.candidates.entries.empty()) {
    Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> frames_view(
        x.data(), frames, 3 * J);
    PseudoStep ps = pseudo_step(st.candidates, cfg_.pseudo_observations, metric_, frames_view, k, steps, t);
    if (!st.observation_set || ps.active != st.active) {
      st.solver->set_observation(with_pseudo_rows(hard, st.candidates, ps));
      st.active = ps.active;
      st.observation_set = true;
    } else if (!ps.active.empty()) {
      Eigen::VectorXd var(hard.rows() + ps.variance.size());
      var << hard.variance, ps.variance;
      st.solver->update_variance(var);
    }
  } else if (!st.observation_set) {
    st.solver->set_observation(hard);
    st.observation_set = true;
  }
  // eqs. (7)-(8); with inequality rows the QP, warm-started from this sample's previous step.
  if (!warm_start_) st.active_rows.columns.clear();
  st.solver->project_in_place(x, &st.active_rows);
  xf = x.cast<float>();
  ++projections_;
}

int64_t ProjFlowStepper::qp_solves() const {
  int64_t n = 0;
  for (const auto& st : state_) n += st.solver->qp_solves();
  return n;
}

int64_t ProjFlowStepper::qp_iterations() const {
  int64_t n = 0;
  for (const auto& st : state_) n += st.solver->qp_iterations();
  return n;
}

torch::Tensor ProjFlowStepper::step(const FlowStep& s) {
  const int64_t B = s.x.size(0), T = s.x.size(1);
  auto x1_hat = s.x1_hat();  // eq. (5)
  auto x0_hat = s.x0_hat();
  auto x1 = x1_hat.to(torch::kCPU, torch::kFloat32).contiguous();
  auto lengths = s.mask.to(torch::kCPU).sum(1);
  auto t0 = std::chrono::steady_clock::now();
  const int64_t per_sample = x1.numel() / std::max<int64_t>(1, B);
  for (int64_t b = 0; b < B; ++b) {
    const int64_t id = s.sample_ids[b];
    if (id < 0 || id >= static_cast<int64_t>(obs_.size()))
      fail("ProjFlow was given {} observations but asked to sample id {}", obs_.size(), id);
    project_sample(id, x1.data_ptr<float>() + b * per_sample, static_cast<int>(lengths[b].item<int64_t>()), s.index,
                   s.steps, s.t);
  }
  projection_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  auto x1_star = x1.to(s.x.device());
  (void)T;
  // eqs. (9)-(10) with eta = t_{k+1} (FlowDPS); at t_{k+1} = 1 the state is x1* itself.
  const double eta = cfg_.noise == "flowdps" ? s.t_next : 0.0;
  torch::Tensor x0_tilde = x0_hat;
  if (eta > 0) {
    // A fresh draw of the prior's source noise (N(0, I) unless its kinematic noise).
    auto eps = s.fresh_noise().to(x0_hat.device());
    x0_tilde = std::sqrt(1 - eta) * x0_hat + std::sqrt(eta) * eps;
  }
  return s.t_next * x1_star + (1 - s.t_next) * x0_tilde;
}

// ---------------------------------------------------------------- guidance

GuidanceStepper::GuidanceStepper(const FlowPrior& prior, const GuidanceConfig& cfg,
                                 std::vector<LinearObservation> model_observations, torch::Tensor text)
    : prior_(prior), cfg_(cfg), obs_(std::move(model_observations)), text_(std::move(text)) {}

torch::Tensor GuidanceStepper::step(const FlowStep& s) {
  torch::Tensor x = s.x;
  const int64_t B = x.size(0);
  const int iterations = s.index >= s.steps - cfg_.final_steps ? cfg_.final_iterations : cfg_.iterations;
  if (iterations > 0 && cfg_.scale > 0 && s.t < cfg_.until) {
    std::vector<const LinearObservation*> batch_obs;
    for (int64_t id : s.sample_ids) batch_obs.push_back(&obs_.at(id));
    BatchedObservation rows = batch_observations(batch_obs, x.size(1), x.size(2), x.device());
    if (rows.rows() > 0) {
      auto idx = torch::tensor(s.sample_ids, torch::kInt64).to(text_.device());
      auto text = text_.index_select(0, idx);
      auto null = prior_.null_texts(B);
      auto tt = torch::full({B}, s.t, x.options());
      // Each row's weight 1 / (rows of its sample): the per-sample mean, summed over samples
      // (samples do not interact, so each sample's gradient is that of its own mean).
      auto weight = 1.0 / rows.row_count.to(x.dtype()).clamp_min(1.0).index_select(0, rows.sample);
      // World metres per normalised unit on each axis: the clip compares moves in metres.
      auto world_per_unit = prior_.net()->joint_std.to(x.device(), x.scalar_type()).view({1, 1, 1, 3});
      auto valid = s.mask.to(x.dtype()).view({B, -1, 1, 1});
      for (int it = 0; it < iterations; ++it) {
        torch::AutoGradMode grad_on(true);
        auto xg = x.detach().requires_grad_(true);
        auto v2 = prior_.raw_velocity(torch::cat({xg, xg}), torch::cat({tt, tt}), torch::cat({text, null}),
                                      torch::cat({s.mask, s.mask}));
        auto v = v2.narrow(0, B, B) + s.cfg_scale * (v2.narrow(0, 0, B) - v2.narrow(0, B, B));
        auto x1 = xg + (1 - s.t) * v;  // eq. (5), differentiable in x
        // Residuals are in world units: affine_to_model moved the normaliser into A.
        auto r = rows.residual(x1);
        auto loss = (r.pow(2) * weight).sum();
        auto g = torch::autograd::grad({loss}, {xg})[0].detach() * valid;
        auto step = cfg_.scale * g;
        if (cfg_.clip_to_residual) {
          auto largest_residual =
              torch::zeros({B}, x.options()).scatter_reduce(0, rows.sample, r.detach().abs(), "amax", true);
          auto largest_move = (step * world_per_unit).abs().amax({1, 2, 3});
          auto factor = (largest_residual / largest_move.clamp_min(1e-12)).clamp_max(1.0);
          step = step * factor.view({B, 1, 1, 1});
        }
        x = (x - step).detach();
      }
      auto v = prior_.velocity(x, tt, text, s.mask, s.cfg_scale);
      return x + (s.t_next - s.t) * v;
    }
  }
  return s.x + (s.t_next - s.t) * s.v;
}

}  // namespace mc
