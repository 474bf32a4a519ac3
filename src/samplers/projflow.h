// The ProjFlow sampler (projflow.txt §4.2-§4.3): at every Euler step the clean
// estimate is projected onto the linear observations under the kinematic metric
// (eqs. (5)-(8)), then recombined with partly fresh noise (eqs. (9)-(10)), with
// time-varying pseudo-observations for sparse inpainting (eqs. (13)-(18)).
// Also the two zero-shot baselines that live on the same step hook: imputation
// (DDNM/MDM-style replacement, a ProjFlow preset) and reconstruction guidance.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "control/kinematic_metric.h"
#include "control/linear_observation.h"
#include "control/projection_solver.h"
#include "core/config.h"
#include "samplers/flow_sampler.h"

namespace mc {

struct ControlTask;

// `pseudo_observations:` (eqs. (13)-(18); defaults of reference-facts §3).
struct PseudoObservationConfig : Config {
  bool enabled = true;
  double l_max = 10, l_min = 3;  // halo radius in frames, eq. (14)
  double tau_min = 0.1;          // eq. (16)
  double c0 = 3.0, lambda_s = 1.0, p = 2.0;  // eq. (15)
  double pi_min = 0.02, pi_max = 1.0;
  double min_variance = 1e-9;    // floor of eq. (18) so a pseudo row never turns into a hard one
  void visit(FieldVisitor& v) override {
    v("enabled", enabled, "pseudo-observations on (true) or plain masking (false, the ablation)");
    v("l_max", l_max, "halo radius at the first step, frames (eq. (14))", at_least(0.0));
    v("l_min", l_min, "halo radius at the last step, frames (eq. (14))", at_least(0.0));
    v("tau_min", tau_min, "floor of the time-decay trust tau(t) (eq. (16))", in_range(0.0, 1.0));
    v("c0", c0, "trust scale c0 (eq. (15))", positive<double>());
    v("lambda_s", lambda_s, "curvature penalty weight lambda_s (eq. (15))", at_least(0.0));
    v("p", p, "curvature penalty exponent p (eq. (15))", positive<double>());
    v("pi_min", pi_min, "lower clip of the trust pi", in_range(1e-6, 1.0));
    v("pi_max", pi_max, "upper clip of the trust pi", in_range(1e-6, 1.0));
    v("min_variance", min_variance, "floor of the pseudo-observation variance (model units^2)", positive<double>());
  }
  std::string validate() const override {
    if (pi_min > pi_max) return "pseudo_observations.pi_min must not exceed pi_max";
    if (l_min > l_max) return "pseudo_observations.l_min must not exceed l_max";
    return "";
  }
};

// `projflow:` section. Switches of the ablations (Table 3): metric euclidean |
// kinematic, noise off | flowdps, pseudo_observations.enabled. All three off is
// DDNM/MDM-style imputation.
struct ProjFlowConfig : Config {
  MetricConfig metric;
  std::string noise = "flowdps";  // eta_t = t_{k+1} (flowdps) or 0 (off)
  PseudoObservationConfig pseudo_observations;
  void visit(FieldVisitor& v) override {
    v("metric", metric, "metric R of the correction (eq. (11))");
    v("noise", noise, "recombination noise: flowdps (eta = t_{k+1}, eq. (9)) or off (eta = 0)",
      one_of({"flowdps", "off"}));
    v("pseudo_observations", pseudo_observations, "time-varying soft pseudo-observations (eqs. (13)-(18))");
  }
};

// Per-sample pseudo-observation candidates: for every (joint, axis) with hard
// point observations, each unobserved frame's distance to the nearest observed
// frame and its linearly interpolated target (copied when only one side exists).
struct PseudoCandidates {
  struct Entry {
    int frame, joint, axis;
    int distance;   // frames to the nearest observed frame of this (joint, axis)
    double target;  // model units
  };
  std::vector<Entry> entries;  // sorted by (frame, joint, axis)
};
// Hard rows with exactly one non-zero are point observations x_i = y / a; other
// rows (camera, relative, loop) produce no candidates.
PseudoCandidates pseudo_candidates(const LinearObservation& hard);

// One step's active pseudo-observations (eq. (14) halo, eqs. (15)-(18) variances)
// appended to the hard rows. `x1_hat` is the clean estimate of this sample,
// frames x (J*3) frame-major, row-major, model units.
struct PseudoStep {
  std::vector<int> active;     // indices into candidates.entries (halo at this step)
  Eigen::VectorXd variance;    // one per active entry, eq. (18)
};
PseudoStep pseudo_step(const PseudoCandidates& cand, const PseudoObservationConfig& cfg,
                       const KinematicMetric& metric, const Eigen::Ref<const Eigen::MatrixXd>& x1_hat, int k,
                       int steps, double t);
// hard rows + the active pseudo rows (unit selection rows, model units).
LinearObservation with_pseudo_rows(const LinearObservation& hard, const PseudoCandidates& cand,
                                   const PseudoStep& step);

// The ProjFlow step rule for a batch of samples, one model-unit observation per
// sample (indexed by the sampler's sample ids).
class ProjFlowStepper : public FlowStepper {
 public:
  ProjFlowStepper(const ProjFlowConfig& cfg, const KinematicMetric& metric,
                  std::vector<LinearObservation> model_observations);
  torch::Tensor step(const FlowStep& s) override;

  // Counters for benchmarks and tests.
  int64_t projections() const { return projections_; }
  double projection_seconds() const { return projection_seconds_; }
  int64_t qp_solves() const;      // inequality QPs run (group x sample x step)
  int64_t qp_iterations() const;  // rows added or dropped in them
  // Warm-start each sample's QP from its previous step's active rows (default on;
  // off only to measure what the warm start saves: the answer is the same).
  void set_warm_start(bool on) { warm_start_ = on; }

 private:
  struct SampleState {
    std::unique_ptr<ProjectionSolver> solver;
    PseudoCandidates candidates;
    std::vector<int> active;  // pseudo entries in the solver's current observation
    ProjectionSolver::ActiveSets active_rows;  // active inequality rows after the last step (QP warm start)
    bool observation_set = false;
  };
  void project_sample(int64_t id, float* x1, int frames, int k, int steps, double t);

  ProjFlowConfig cfg_;
  KinematicMetric metric_;
  std::vector<LinearObservation> obs_;
  std::vector<SampleState> state_;
  int64_t projections_ = 0;
  double projection_seconds_ = 0;
  bool warm_start_ = true;
};

// `guidance:` reconstruction guidance (GMD/OmniControl style, reference-facts §4):
// x <- x - scale * grad_x L(x1_hat(x)) before the Euler update, with L the mean of
// (A x1_hat - y)^2 over the sample's constrained rows (world units). Averaging rather
// than summing keeps one step size meaningful from one keyframe to a dense
// trajectory; the step is clipped so that no joint coordinate moves further (in
// metres) than the sample's largest residual, which stops a sparse keyframe from
// overshooting by metres when the step size is large enough for dense tracks.
// OmniControl runs many more guidance iterations in its last denoising steps
// (10 per step, 500 in the last 10 of 1000); `final_steps`/`final_iterations` do that.
// The defaults are the tuned baseline the tables use (scale 100 from the val sweep,
// tools/tune_guidance.py; OmniControl's heavier final steps), so `guidance: {}` is the
// fair baseline rather than a 100x weaker one.
struct GuidanceConfig : Config {
  double scale = 100.0;
  int iterations = 1;
  int final_steps = 2;        // the last this many sampling steps use final_iterations
  int final_iterations = 10;
  double until = 1.0;         // guide steps with t_k < until
  bool clip_to_residual = true;
  void visit(FieldVisitor& v) override {
    v("scale", scale, "step size s of the gradient update on the mean squared residual (tuned on val: docs/choices.md)",
      at_least(0.0));
    v("iterations", iterations, "gradient updates per sampling step", in_range(0, 100));
    v("final_steps", final_steps, "the last this many sampling steps run final_iterations updates (OmniControl)",
      at_least(0));
    v("final_iterations", final_iterations, "gradient updates per step in the last final_steps steps",
      in_range(0, 1000));
    v("until", until, "guide only while t_k < until", in_range(0.0, 1.0));
    v("clip_to_residual", clip_to_residual,
      "clip each update so no joint coordinate moves further (metres) than the sample's largest residual");
  }
};

class GuidanceStepper : public FlowStepper {
 public:
  // CFG inside the guided re-evaluation uses the step's own scale (FlowStep::cfg_scale).
  GuidanceStepper(const FlowPrior& prior, const GuidanceConfig& cfg, std::vector<LinearObservation> model_observations,
                  torch::Tensor text);
  torch::Tensor step(const FlowStep& s) override;

 private:
  const FlowPrior& prior_;
  GuidanceConfig cfg_;
  std::vector<LinearObservation> obs_;
  torch::Tensor text_;  // [N, width] pooled text vectors of every sample
};

}  // namespace mc
