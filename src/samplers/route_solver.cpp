// RouteSolver: soft-token refinement through the frozen VQ decoder with raw optimiser
// updates routed onto anchor-interval bases (AnchorRoute eqs. (24)-(34)).
#include "samplers/route_solver.h"

#include <algorithm>
#include <climits>
#include <cmath>
#include <random>

#include "core/error.h"
#include "control/anchor_loss.h"
#include "data/skeleton.h"
#include "samplers/task_observation.h"

namespace mc {

namespace {

// Freezes the tokenizer for the duration of a refinement: gradients flow to u only
// (§3.4: "all generator parameters remain fixed"), and the mode is eval.
class FrozenModule {
 public:
  explicit FrozenModule(torch::nn::Module& m) : m_(m), was_training_(m.is_training()) {
    for (auto& p : m_.parameters()) {
      flags_.push_back(p.requires_grad());
      p.requires_grad_(false);
    }
    m_.eval();
  }
  ~FrozenModule() {
    size_t i = 0;
    for (auto& p : m_.parameters()) p.requires_grad_(flags_[i++]);
    m_.train(was_training_);
  }

 private:
  torch::nn::Module& m_;
  bool was_training_;
  std::vector<bool> flags_;
};

uint64_t uniform_below(std::mt19937_64& rng, uint64_t n) {
  const uint64_t limit = UINT64_MAX - UINT64_MAX % n;
  uint64_t r;
  do r = rng();
  while (r >= limit);
  return r % n;
}

torch::Tensor to_tensor(const Eigen::MatrixXd& m) {
  auto t = torch::empty({m.rows(), m.cols()});
  auto a = t.accessor<float, 2>();
  for (Eigen::Index r = 0; r < m.rows(); ++r)
    for (Eigen::Index c = 0; c < m.cols(); ++c) a[r][c] = static_cast<float>(m(r, c));
  return t;
}

std::unique_ptr<torch::optim::Optimizer> make_optimizer(const RouteSolverConfig& c, torch::Tensor& u) {
  if (c.optimizer == "adamw")
    return std::make_unique<torch::optim::AdamW>(
        std::vector<torch::Tensor>{u},
        torch::optim::AdamWOptions(c.lr).betas(std::make_tuple(c.beta1, c.beta2)).weight_decay(c.weight_decay));
  if (c.optimizer == "adam")
    return std::make_unique<torch::optim::Adam>(
        std::vector<torch::Tensor>{u},
        torch::optim::AdamOptions(c.lr).betas(std::make_tuple(c.beta1, c.beta2)).weight_decay(c.weight_decay));
  return std::make_unique<torch::optim::SGD>(std::vector<torch::Tensor>{u},
                                             torch::optim::SGDOptions(c.lr).weight_decay(c.weight_decay));
}

}  // namespace

LinearObservation extra_residual_rows(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                                      const float* source_motion) {
  ConstraintSpec extra;
  extra.source = spec.source;
  for (const auto& it : spec.items)
    if ((is_inequality_type(it.type) || is_direction_type(it.type)) && !it.score_only) extra.items.push_back(it);
  return compile(extra, frames, skeleton, source_motion);
}

RouteSolver::RouteSolver(VqTokenizer tokenizer, RouteSolverConfig cfg) : tok_(std::move(tokenizer)), cfg_(std::move(cfg)) {
  if (!tok_) fail("RouteSolver needs a tokenizer");
}

torch::Tensor RouteSolver::decode_world(const torch::Tensor& u) const {  // eq. (25)
  auto x = tok_->decode_embeddings(u);  // [B, T, J*3] normalised
  return tok_->denormalize(x.view({x.size(0), x.size(1), -1, 3}));
}

RouteSolverResult RouteSolver::refine(const torch::Tensor& ids, const std::vector<AnchorSet>& anchors, uint64_t seed,
                                      const std::vector<int>& lengths,
                                      const std::vector<LinearObservation>& extra) const {
  if (ids.dim() != 2) fail("RouteSolver: tokens must be [B, L], got {} dimensions", ids.dim());
  torch::Tensor u0;
  {
    torch::NoGradGuard ng;
    u0 = tok_->quantizer->lookup(ids.to(tok_->codebook().device(), torch::kLong));  // eq. (24)
  }
  return refine_embeddings(u0, anchors, seed, lengths, extra);
}

RouteSolverResult RouteSolver::refine_embeddings(const torch::Tensor& u0_in, const std::vector<AnchorSet>& anchors,
                                                 uint64_t seed, const std::vector<int>& lengths_in,
                                                 const std::vector<LinearObservation>& extra) const {
  FrozenModule frozen(*tok_);
  const auto device = tok_->codebook().device();
  if (u0_in.dim() != 3 || u0_in.size(2) != tok_->code_dim())
    fail("RouteSolver: soft tokens must be [B, L, D = {}], got {} dimensions", tok_->code_dim(), u0_in.dim());
  const int64_t B = u0_in.size(0), L = u0_in.size(1), S = tok_->stride(), T = L * S;
  const int64_t J = tok_->num_joints();
  if (static_cast<int64_t>(anchors.size()) != B)
    fail("RouteSolver: {} anchor sets for {} samples", anchors.size(), B);
  std::vector<int> lengths = lengths_in;
  if (lengths.empty()) lengths.assign(B, static_cast<int>(T));
  if (static_cast<int64_t>(lengths.size()) != B) fail("RouteSolver: {} lengths for {} samples", lengths.size(), B);

  const BasisKind kind = parse_basis_kind(cfg_.basis, "route_solver.basis");
  std::vector<IntervalBasis> bases;
  auto chan = torch::zeros({B, 1, J, 3});  // controlled channels q_{b,t} of eq. (27)
  auto m2 = torch::zeros({B, std::max<int64_t>(T - 2, 0)}), m1 = torch::zeros({B, std::max<int64_t>(T - 1, 0)});
  auto len = torch::zeros({B});
  for (int64_t b = 0; b < B; ++b) {
    const int Tb = lengths[b];
    if (Tb < 3 || Tb > T)
      fail("RouteSolver: sample {} has length {}; it must be in [3, {}] (the tokens' frames)", b, Tb, T);
    for (const auto& a : anchors[b].anchors) {
      if (a.frame < 0 || a.frame >= Tb)
        fail("RouteSolver: sample {}: anchor at frame {} is outside its {} frames", b, a.frame, Tb);
      if (a.joint < 0 || a.joint >= J)
        fail("RouteSolver: sample {}: anchor joint {} is not one of the tokenizer's {} joints", b, a.joint, J);
      for (int c = 0; c < 3; ++c)
        if (a.axes[c]) chan[b][0][a.joint][c] = 1.f;
    }
    bases.push_back(build_interval_basis(anchors[b].times(), Tb, static_cast<int>(L), static_cast<int>(S), kind));
    m2[b].slice(0, 0, Tb - 2).fill_(1.f);
    m1[b].slice(0, 0, Tb - 1).fill_(1.f);
    len[b] = static_cast<float>(Tb);
  }
  chan = chan.to(device);
  m2 = m2.to(device);
  m1 = m1.to(device);
  len = len.to(device);
  const AnchorBatch batch = make_anchor_batch(anchors, device);

  // The non-anchor items' rows, batched: equality rows (direction items) and the
  // inequality rows as hinges (control/linear_observation.h, inequality_rows).
  if (!extra.empty() && static_cast<int64_t>(extra.size()) != B)
    fail("RouteSolver: {} extra row sets for {} samples", extra.size(), B);
  BatchedObservation extra_eq, extra_ineq;
  std::vector<std::pair<int64_t, int>> eq_rows_at, ineq_rows_at;  // (sample, frame) of each stacked row
  const double extra_weight = cfg_.extra_residuals.weight;
  bool any_eq = false, any_ineq = false;
  if (!extra.empty() && extra_weight > 0) {
    std::vector<LinearObservation> ineq;
    std::vector<const LinearObservation*> eq_ptr, ineq_ptr;
    ineq.reserve(extra.size());
    for (int64_t b = 0; b < B; ++b) {
      if (extra[b].frames > lengths[b] || extra[b].joints != J)
        fail("RouteSolver: sample {}: extra rows cover {} frames x {} joints; the sample has {} frames x {} joints", b,
             extra[b].frames, extra[b].joints, lengths[b], J);
      any_eq = any_eq || extra[b].rows() > 0;
      any_ineq = any_ineq || extra[b].inequalities() > 0;
      ineq.push_back(inequality_rows(extra[b]));
    }
    for (int64_t b = 0; b < B; ++b) eq_ptr.push_back(&extra[b]), ineq_ptr.push_back(&ineq[b]);
    if (any_eq) extra_eq = batch_observations(eq_ptr, T, J, device);
    if (any_ineq) extra_ineq = batch_observations(ineq_ptr, T, J, device);
    // Each stacked row's sample and frame (the middle of the frames it touches: a
    // tangent's stencil t - 1, t + 1 gives t), for the activities below.
    auto locate = [&](const std::vector<const LinearObservation*>& obs, std::vector<std::pair<int64_t, int>>& out) {
      for (int64_t b = 0; b < B; ++b)
        for (int r = 0; r < obs[b]->rows(); ++r) {
          int lo = INT32_MAX, hi = -1;
          for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs[b]->A, r); it; ++it) {
            const int t = static_cast<int>(it.col() / (3 * J));
            lo = std::min(lo, t), hi = std::max(hi, t);
          }
          out.push_back({b, hi < 0 ? 0 : (lo + hi) / 2});
        }
    };
    locate(eq_ptr, eq_rows_at);
    locate(ineq_ptr, ineq_rows_at);
  }

  const torch::Tensor u0 = u0_in.detach().to(device, torch::kFloat);
  torch::Tensor u = u0.clone().set_requires_grad(true);
  auto opt = make_optimizer(cfg_, u);
  std::mt19937_64 rng(seed);
  const bool route = cfg_.update == "route";

  // The extra rows' residuals |A x - y| and hinges max(0, G x - h) (world units) by
  // sample and frame: they join the anchor errors in eq. (32), so an interval whose
  // heading or floor is off is routed like one whose anchors are (the "residual
  // scaffold" AnchorRoute §5 proposes to extend), not suppressed.
  std::vector<std::vector<std::pair<int, double>>> extra_at(B);
  auto refresh_extra = [&](const torch::Tensor& world_detached) {
    for (auto& v : extra_at) v.clear();
    auto add = [&](const BatchedObservation& rows, const std::vector<std::pair<int64_t, int>>& at, bool hinge) {
      auto r = rows.residual(world_detached);
      r = (hinge ? torch::relu(r) : r.abs()).to(torch::kCPU, torch::kDouble).contiguous();
      const double* p = r.data_ptr<double>();
      for (size_t k = 0; k < at.size(); ++k) extra_at[at[k].first].push_back({at[k].second, p[k]});
    };
    if (any_eq) add(extra_eq, eq_rows_at, false);
    if (any_ineq) add(extra_ineq, ineq_rows_at, true);
  };
  // Eq. (32)'s input: the largest control error among the anchors at each frame, and
  // an extra row's residual at both ends of the interval holding its frame.
  auto activities = [&](const torch::Tensor& err_cpu, int64_t b) {
    auto e = err_cpu.accessor<float, 2>();
    std::vector<double> frame_error(lengths[b], 0.0);
    for (size_t n = 0; n < anchors[b].anchors.size(); ++n) {
      const int t = anchors[b].anchors[n].frame;
      frame_error[t] = std::max(frame_error[t], static_cast<double>(e[b][n]));
    }
    const auto& bd = bases[b].boundaries;
    for (auto [t, v] : extra_at[b]) {
      auto hi = std::upper_bound(bd.begin(), bd.end(), t);
      const size_t k1 = std::min<size_t>(std::max<ptrdiff_t>(hi - bd.begin(), 1), bd.size() - 1);
      for (size_t k : {k1 - 1, k1}) frame_error[bd[k]] = std::max(frame_error[bd[k]], v);
    }
    auto a = interval_activities(bases[b], frame_error, cfg_.rho_f);
    if (cfg_.activity == "shuffled")
      for (size_t i = a.size(); i > 1; --i) std::swap(a[i - 1], a[uniform_below(rng, i)]);
    return a;
  };
  auto routing = [&](const torch::Tensor& err_cpu) {  // [B, L, L], eqs. (33)-(34)
    std::vector<torch::Tensor> R;
    for (int64_t b = 0; b < B; ++b) {
      std::vector<double> a = cfg_.activity == "uniform"
                                  ? std::vector<double>(bases[b].intervals(), cfg_.uniform_activity)
                                  : activities(err_cpu, b);
      R.push_back(to_tensor(routing_operator(bases[b], a, cfg_.lambda)));
    }
    return torch::stack(R).to(device);
  };
  torch::Tensor R_fixed;  // uniform activity: the routing never changes
  if (route && cfg_.activity == "uniform") R_fixed = routing({});

  RouteSolverResult res;
  auto mean_error = [&](const torch::Tensor& err) {
    double n = batch.valid.sum().item<double>();
    return n > 0 ? err.sum().item<double>() / n : 0.0;
  };
  for (int step = 0;; ++step) {
    const bool last = step == cfg_.steps;
    torch::Tensor world;
    {
      std::unique_ptr<torch::NoGradGuard> ng;
      if (last) ng = std::make_unique<torch::NoGradGuard>();
      world = decode_world(u);
    }
    torch::Tensor err = anchor_errors(world.detach(), batch).to(torch::kCPU).contiguous();
    if (any_eq || any_ineq) refresh_extra(world.detach());
    if (step == 0) {
      if (!torch::isfinite(world).all().item<bool>())
        fail("RouteSolver: the decoded tokens are not finite; check the tokenizer checkpoint");
      res.initial_errors = err.clone();
      res.initial_control_error = mean_error(err);
    }
    if (cfg_.record_history) res.control_error_history.push_back(mean_error(err));
    if (last) {
      if (!torch::isfinite(world).all().item<bool>())
        fail("RouteSolver: the refined motion is not finite after {} steps; lower route_solver.lr", cfg_.steps);
      res.world = world.detach();
      res.final_errors = err;
      res.final_control_error = mean_error(err);
      break;
    }

    // Eq. (26) summed over samples (each sample's terms only touch its own u_b,
    // so the update of a sample does not depend on the rest of the batch).
    auto objective = anchor_loss(world, batch);  // eq. (3)
    if (cfg_.gamma_sm > 0 && T > 2) {            // eq. (27)
      auto q = world * chan;
      auto d2 = q.slice(1, 2) - 2 * q.slice(1, 1, T - 1) + q.slice(1, 0, T - 2);
      objective = objective + cfg_.gamma_sm * (d2.pow(2).sum({2, 3}) * m2).sum(1) / (len - 2);
    }
    if (cfg_.gamma_tr > 0) objective = objective + cfg_.gamma_tr * (u - u0).pow(2).sum({1, 2});
    if (any_eq) {  // direction rows: squared residuals, per sample
      auto r2 = extra_eq.residual(world).pow(2);
      objective = objective + extra_weight * torch::zeros({B}, r2.options()).index_add(0, extra_eq.sample, r2);
    }
    if (any_ineq) {  // inequality rows: squared hinge max(0, g x - h)^2
      auto h2 = torch::relu(extra_ineq.residual(world)).pow(2);
      objective = objective + extra_weight * torch::zeros({B}, h2.options()).index_add(0, extra_ineq.sample, h2);
    }
    if (cfg_.gamma_feas > 0) {  // eq. (28)
      auto r = world.select(2, 0);
      auto v = ((r.slice(1, 1) - r.slice(1, 0, T - 1)).pow(2).sum(-1) + 1e-12).sqrt();
      auto hinge = torch::relu(v - cfg_.v_max).pow(2);
      objective = objective + cfg_.gamma_feas * (hinge * m1).sum(1) / (len - 1);
    }
    auto total = objective.sum();
    const double total_v = total.item<double>();
    if (!std::isfinite(total_v))
      fail("RouteSolver: the objective became non-finite at step {}; lower route_solver.lr", step);
    if (cfg_.record_history) res.objective_history.push_back(total_v);

    opt->zero_grad();
    total.backward();
    torch::Tensor u_prev = u.detach().clone();
    opt->step();  // eq. (29): Delta = OptStep(u; J) - u
    if (route) {
      torch::NoGradGuard ng;
      auto R = cfg_.activity == "uniform" ? R_fixed : routing(err);
      auto delta = u.detach() - u_prev;
      u.copy_(u_prev + torch::bmm(R, delta));  // eq. (34): u+ = u + B alpha*
    }
  }
  res.u = u.detach();
  return res;
}

}  // namespace mc
