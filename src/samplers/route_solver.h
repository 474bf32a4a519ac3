// RouteSolver (AnchorRoute §3.4): refines generated motion tokens as continuous code
// vectors through the frozen VQ decoder, routing every raw optimiser update onto the
// anchor-defined interval basis weighted by residual activities (eqs. (24)-(34)).
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "control/anchors.h"
#include "control/linear_observation.h"
#include "control/route_basis.h"
#include "core/config.h"
#include "models/vq_tokenizer.h"

namespace mc {

// `route_solver:` section. Defaults and the choices behind them: docs/choices.md
// ("AnchorRoute: anchors and RouteSolver"). Table V/VI variants:
//   plain soft-token refinement (v0)     update: plain
//   interval basis, uniform activity      activity: uniform
//   shuffled residual activity            activity: shuffled
//   transport-only / slope-only basis     basis: transport / slope
//   quadratic / cubic basis               basis: quadratic / cubic
// `route.extra_residuals:` terms added to eq. (26) for a task's non-anchor items
// (issue 20; AnchorRoute §5's "tangent or orientation cues"): weight * (sum of the
// squared residuals of their equality rows + sum of max(0, g x - h)^2 over their
// inequality rows), in world units. Direction items (tangent, facing) give both
// kinds, inequality items (floor, box, ...) the hinge only. Left out of the dumped
// config at its default, so configs written before it keep their hashes.
struct RouteExtraConfig : Config {
  double weight = 1.0;
  void visit(FieldVisitor& v) override {
    v("weight", weight, "weight of the direction and inequality residuals beside the anchor loss (untuned)",
      at_least(0.0));
  }
  bool omitted_from_dump() const override { return weight == 1.0; }
};

struct RouteSolverConfig : Config {
  int steps = 200;  // RS100 / RS200 / RS500
  std::string update = "route";
  std::string basis = "affine";
  std::string activity = "residual";
  double uniform_activity = 1.0;
  double rho_f = 0.05;
  double lambda = 4.0;
  std::string optimizer = "adamw";
  double lr = 6e-2;
  double beta1 = 0.5;
  double beta2 = 0.9;
  double weight_decay = 0.0;
  double gamma_sm = 1.0;
  double gamma_tr = 1e-6;
  double gamma_feas = 0.0;
  double v_max = 0.25;
  bool record_history = true;
  RouteExtraConfig extra_residuals;

  void visit(FieldVisitor& v) override {
    v("steps", steps, "refinement steps (RS100 / RS200 / RS500); 0 = decode the tokens only", in_range(0, 100000));
    v("update", update, "route: project each raw update onto the interval basis (eqs. (33)-(34)); "
      "plain: apply the raw optimiser update (Table V/VI 'plain soft-token refinement')",
      one_of({"route", "plain"}));
    v("basis", basis, "local interval basis: affine {1, 2s-1} (eq. (30)), transport {1}, slope {2s-1}, "
      "quadratic or cubic (Legendre polynomials in 2s-1)",
      one_of({"affine", "transport", "slope", "quadratic", "cubic"}));
    v("activity", activity, "interval activities: residual (eq. (32), refreshed each step), uniform "
      "(every interval uniform_activity), shuffled (eq. (32) values randomly permuted among a sample's "
      "intervals each step)",
      one_of({"residual", "uniform", "shuffled"}));
    v("uniform_activity", uniform_activity, "activity of every interval when activity = uniform", in_range(0.0, 1.0));
    v("rho_f", rho_f, "residual tolerance rho_f of eq. (32), metres: an interval whose worse endpoint error "
      "reaches it gets full activity",
      positive<double>());
    v("lambda", lambda, "suppression strength lambda of eq. (33) on inactive intervals' coefficients",
      at_least(0.0));
    v("optimizer", optimizer, "raw update OptStep of eq. (29)", one_of({"adamw", "adam", "sgd"}));
    v("lr", lr, "optimiser learning rate", positive<double>());
    v("beta1", beta1, "Adam(W) beta1", in_range(0.0, 0.9999));
    v("beta2", beta2, "Adam(W) beta2", in_range(0.0, 0.99999));
    v("weight_decay", weight_decay, "AdamW decoupled weight decay on u (pulls toward 0, not u0)", at_least(0.0));
    v("gamma_sm", gamma_sm, "weight of the controlled-trajectory smoothness term eq. (27)", at_least(0.0));
    v("gamma_tr", gamma_tr, "weight of the trust region ||u - u0||_F^2 in eq. (26)", at_least(0.0));
    v("gamma_feas", gamma_feas, "weight of the root-velocity hinge eq. (28) (paper default 0: off)", at_least(0.0));
    v("v_max", v_max, "root speed limit of eq. (28), metres per frame", positive<double>());
    v("record_history", record_history, "record the control error and objective before every step");
    v("extra_residuals", extra_residuals, "residuals of direction and inequality items beside the anchors (issue 20)");
  }
};

struct RouteSolverResult {
  torch::Tensor u;               // [B, L, D] refined soft tokens
  torch::Tensor world;           // [B, L * stride, J, 3] decoded refined motion, world metres
  torch::Tensor initial_errors;  // [B, N] anchor control errors of the decoded tokens (0 on padding)
  torch::Tensor final_errors;    // [B, N] after refinement
  double initial_control_error = 0, final_control_error = 0;  // means over all valid anchors
  // With record_history: entry k is before step k, the last after the final step (steps + 1 entries).
  std::vector<double> control_error_history;
  std::vector<double> objective_history;  // eq. (26) summed over samples, steps entries
};

// The rows RouteSolver adds for a spec's non-anchor items (inequality and direction
// items; score_only items give none): compile() of those items alone, world units.
// An observation without rows when the spec has none.
LinearObservation extra_residual_rows(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                                      const float* source_motion);

// Holds a frozen tokenizer; refine() never changes its parameters or mode.
class RouteSolver {
 public:
  RouteSolver(VqTokenizer tokenizer, RouteSolverConfig cfg);

  // ids [B, L] generated tokens (eq. (24): u0 = E[z]); anchors one set per sample
  // (frames <= L * stride); lengths [B] valid frames per sample (empty = all
  // L * stride; each at least 3 and at least the set's frames). `seed` drives the
  // shuffled-activity permutations only. UserError on shape mismatches or a
  // non-finite objective / decoded motion.
  // `extra` (empty, or one per sample): world-unit rows of the sample's non-anchor
  // items (extra_residual_rows), added to the objective as RouteExtraConfig says.
  RouteSolverResult refine(const torch::Tensor& ids, const std::vector<AnchorSet>& anchors, uint64_t seed = 0,
                           const std::vector<int>& lengths = {},
                           const std::vector<LinearObservation>& extra = {}) const;
  // The same from continuous code vectors u0 [B, L, D].
  RouteSolverResult refine_embeddings(const torch::Tensor& u0, const std::vector<AnchorSet>& anchors,
                                      uint64_t seed = 0, const std::vector<int>& lengths = {},
                                      const std::vector<LinearObservation>& extra = {}) const;

  // The decoder D of eq. (25): u [B, L, D] -> world joints [B, L * stride, J, 3].
  torch::Tensor decode_world(const torch::Tensor& u) const;
  const RouteSolverConfig& config() const { return cfg_; }

 private:
  mutable VqTokenizer tok_;  // frozen: refine() only toggles requires_grad and mode, and restores them
  RouteSolverConfig cfg_;
};

}  // namespace mc
