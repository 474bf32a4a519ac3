// Generator `anchorroute`: TMD sampling conditioned on each task's anchors through a
// trained anchor adapter (AnchorKV or a Table IV baseline; none = the frozen TMD prior),
// then optional RouteSolver refinement (§3.4) of the generated tokens.
#include <chrono>
#include <memory>

#include "control/anchors.h"
#include "control/projection_solver.h"
#include "core/error.h"
#include "data/skeleton.h"
#include "core/trained_runs.h"
#include "models/anchor_adapters.h"
#include "models/token_prior.h"
#include "control/anchor_loss.h"
#include "samplers/anchorroute_generator.h"
#include "samplers/motion_generator.h"
#include "samplers/route_solver.h"
#include "samplers/tmd_sampler.h"

namespace mc {

namespace {

class AnchorRouteGenerator : public MotionGenerator {
 public:
  AnchorRouteGenerator(std::shared_ptr<TokenPrior> prior, std::shared_ptr<AnchorAdapterModule> adapter,
                       AnchorAdapterConfig adapter_cfg, std::string adapter_run, TmdSamplerConfig sampler,
                       RouteSolverConfig route, int route_batch, AnchorGuidanceConfig guidance = {},
                       ExactProjectionConfig exact = {})
      : prior_(std::move(prior)),
        adapter_(std::move(adapter)),
        acfg_(std::move(adapter_cfg)),
        adapter_run_(std::move(adapter_run)),
        sampler_(std::move(sampler)),
        route_(std::move(route)),
        route_batch_(route_batch),
        guidance_(std::move(guidance)),
        exact_(std::move(exact)) {}

  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    const int64_t N = tasks.size(), s = prior_->stride();
    std::vector<std::string> captions;
    std::vector<int> lengths;
    std::vector<AnchorSet> sets;
    std::vector<LinearObservation> extras;  // non-anchor items' rows (RouteSolver's extra residuals)
    bool any_extra = false;
    int64_t max_tokens = 1;
    for (const auto& t : tasks) {
      captions.push_back(t.caption);
      lengths.push_back(t.length);
      AnchorSet a;
      try {
        a = anchors_from_spec(t.spec, t.length, prior_->skeleton(), t.source.empty() ? nullptr : t.source.data());
      } catch (const UserError& e) {
        fail("generator anchorroute: task '{}' cannot be used: {}", t.id, e.what());
      }
      if (a.size() == 0)
        fail("generator anchorroute: task '{}' has no anchors; AnchorRoute needs keyframe, trajectory or "
             "planar_root constraints (use generator tmd for unconstrained text-to-motion)",
             t.id);
      sets.push_back(std::move(a));
      try {
        extras.push_back(extra_residual_rows(t.spec, t.length, prior_->skeleton(),
                                             t.source.empty() ? nullptr : t.source.data()));
      } catch (const UserError& e) {
        fail("generator anchorroute: task '{}': {}", t.id, e.what());
      }
      any_extra = any_extra || extras.back().rows() > 0 || extras.back().inequalities() > 0;
      max_tokens = std::max<int64_t>(max_tokens, (t.length + s - 1) / s);
    }
    auto t0 = std::chrono::steady_clock::now();
    TokenHooksFn hooks;
    torch::Tensor feats;
    if (adapter_) {
      feats = torch::zeros({N, max_tokens * s, adapter_feature_width(acfg_.body_joints, acfg_.features)});
      // An audit twin trained on zeroed features (model.training.zero_features) sees zeros here too.
      for (int64_t i = 0; i < N && !acfg_.training.zero_features; ++i) {
        try {
          feats[i].narrow(0, 0, sets[i].frames).copy_(adapter_features(sets[i], acfg_.body_joints, acfg_.features));
        } catch (const UserError& e) {
          fail("generator anchorroute: task '{}': the adapter '{}' cannot read its anchors: {}", tasks[i].id,
               adapter_run_, e.what());
        }
      }
      const auto dev = prior_->device();
      hooks = [&, dev](int64_t start, const torch::Tensor& ids, const torch::Tensor& t, const TextContext& text,
                       const torch::Tensor& valid) {
        const int64_t B = ids.size(0), L = ids.size(1);
        auto f = feats.narrow(0, start, B).narrow(1, 0, L * s);
        if (acfg_.features.feedback.enabled && !acfg_.training.zero_features) {
          // Feedback (ours): the anchors against the frozen prior's estimate at the current
          // tokens, from the caption (the conditional call's text), as in training.
          f = f.clone();
          std::vector<AnchorSet> bs(sets.begin() + start, sets.begin() + start + B);
          fill_feedback_features(f, bs, frozen_soft_estimate(*prior_, ids, t, text, valid), prior_->skeleton(),
                                 acfg_.body_joints, acfg_.features);
        }
        AdapterInputs in{ids, t, text, valid, f.to(dev)};
        // The CFG null-text pass gets hooks computed on the null text when they read it.
        auto h = adapter_->guided_hooks(in, prior_->null_texts(B, text.memory.size(1)));
        h.guidance = guidance_.hooks();
        return h;
      };
    }
    auto r = sample_tmd(*prior_, captions, lengths, sampler_, seed, hooks);
    GeneratedMotions out;
    out.world = r.world;
    out.lengths = lengths;
    const double err0 = mean_control_error(r.world, make_anchor_batch(sets)).item<double>();
    out.notes.push_back(describe());
    out.notes.push_back(fmt::format("trainable parameters: {}", adapter_ ? count_parameters(*adapter_) : 0));
    out.stats["params"] = adapter_ ? static_cast<double>(count_parameters(*adapter_)) : 0.0;
    out.stats["steps"] = route_.steps;
    out.notes.push_back(fmt::format("generator control error: {:.4f} m", err0));
    if (route_.steps > 0) {
      RouteSolver solver(prior_->tokenizer().model, route_);
      for (int64_t start = 0; start < N; start += route_batch_) {
        const int64_t B = std::min<int64_t>(route_batch_, N - start);
        int64_t L = 1;
        for (int64_t i = 0; i < B; ++i) L = std::max(L, r.tokens[start + i].size(0));
        auto ids = torch::zeros({B, L}, torch::kInt64);  // padding tokens decode past each length and are cut
        std::vector<AnchorSet> bs(sets.begin() + start, sets.begin() + start + B);
        std::vector<int> bl(lengths.begin() + start, lengths.begin() + start + B);
        for (int64_t i = 0; i < B; ++i) ids[i].narrow(0, 0, r.tokens[start + i].size(0)).copy_(r.tokens[start + i]);
        std::vector<LinearObservation> be;
        if (any_extra) be.assign(extras.begin() + start, extras.begin() + start + B);
        auto res = solver.refine(ids.to(prior_->device()), bs, seed ^ (0x5eedull + start), bl, be);
        auto w = res.world.to(torch::kCPU);
        for (int64_t i = 0; i < B; ++i) {
          out.world[start + i].zero_();
          out.world[start + i].narrow(0, 0, bl[i]).copy_(w[i].narrow(0, 0, bl[i]));
        }
      }
      if (!torch::isfinite(out.world).all().item<bool>())
        fail("generator anchorroute: RouteSolver produced non-finite joints; lower route.lr");
      out.notes.push_back(fmt::format("RS{} control error: {:.4f} m", route_.steps,
                                      mean_control_error(out.world, make_anchor_batch(sets)).item<double>()));
    }
    if (exact_.enabled) project_exactly(tasks, lengths, sets, out);
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return out;
  }

  // ProjFlow's projection onto each task's whole spec, in world units (the decoded
  // motion is world metres): the anchors then hold to solver precision.
  void project_exactly(const std::vector<ControlTask>& tasks, const std::vector<int>& lengths,
                       const std::vector<AnchorSet>& sets, GeneratedMotions& out) {
    const Skeleton& sk = prior_->skeleton();
    ProjectionSolver solver(KinematicMetric::from_config(exact_.metric, sk));
    auto world = out.world.to(torch::kCPU, torch::kFloat).contiguous();
    double worst = 0;
    for (size_t i = 0; i < tasks.size(); ++i) {
      const auto& t = tasks[i];
      LinearObservation obs;
      try {
        obs = compile(t.spec, lengths[i], sk, t.source.empty() ? nullptr : t.source.data());
      } catch (const UserError& e) {
        fail("generator anchorroute: task '{}': {}", t.id, e.what());
      }
      if (obs.rows() == 0 && obs.inequalities() == 0) continue;
      solver.set_observation(obs);
      float* p = world[static_cast<int64_t>(i)].data_ptr<float>();
      const int d = obs.dim();
      Eigen::MatrixXd x(d, 1);
      for (int k = 0; k < d; ++k) x(k, 0) = p[k];
      solver.project_in_place(x);
      for (int k = 0; k < d; ++k) p[k] = static_cast<float>(x(k, 0));
      Eigen::VectorXd r = obs.A * x.col(0) - obs.y;
      for (int k = 0; k < obs.rows(); ++k)
        if (obs.is_hard(k)) worst = std::max(worst, std::abs(r[k]));
    }
    out.world = world.to(out.world.device());
    out.notes.push_back(fmt::format("exact projection ({} metric): max hard residual {:.1e} m, control error {:.2e} m",
                                    exact_.metric.type, worst,
                                    mean_control_error(out.world, make_anchor_batch(sets)).item<double>()));
  }

  std::string describe() const override {
    std::string a = adapter_ ? fmt::format("{} adapter {}", acfg_.adapter, adapter_run_) : "no adapter";
    if (adapter_ && !guidance_.omitted_from_dump())
      a += fmt::format(" (anchors in {} CFG passes, anchor guidance {})", guidance_.anchors, guidance_.scale);
    return fmt::format("AnchorRoute: TMD prior {} ({} steps, cfg {}), {}, RouteSolver {}", prior_->run_dir(),
                       sampler_.steps, sampler_.cfg_scale, a,
                       route_.steps > 0 ? fmt::format("RS{} ({} update, {} basis, {} activity)", route_.steps,
                                                      route_.update, route_.basis, route_.activity)
                                        : std::string("off")) +
           (exact_.enabled ? fmt::format(", then the exact projection ({} metric)", exact_.metric.type) : "");
  }

 private:
  std::shared_ptr<TokenPrior> prior_;
  std::shared_ptr<AnchorAdapterModule> adapter_;
  AnchorAdapterConfig acfg_;
  std::string adapter_run_;
  TmdSamplerConfig sampler_;
  RouteSolverConfig route_;
  int route_batch_;
  AnchorGuidanceConfig guidance_;
  ExactProjectionConfig exact_;
};

}  // namespace

void AnchorRouteGeneratorConfig::visit(FieldVisitor& v) {
  v("adapter_run", adapter_run, "finished anchor_adapter run (its TMD prior is used); '' with adapter_config '' = "
    "the frozen TMD prior without generation-time conditioning ('TMD w/ solver')");
  v("adapter_config", adapter_config, "anchor_adapter training config run on demand when adapter_run is ''");
  v("adapter_overrides", adapter_overrides, "key=value overrides for adapter_config");
  v("prior_run", prior_run, "without an adapter: finished tmd_prior run ('' = train prior_config on demand)");
  v("prior_config", prior_config, "without an adapter: TMD training config run on demand");
  v("prior_overrides", prior_overrides, "key=value overrides for prior_config");
  v("sampler", sampler, "TMD transition sampler (eqs. (21)-(23))");
  v("route", route, "RouteSolver refinement (steps 0 = off; RS100 / RS200 / RS500 and the Table V/VI variants)");
  v("route_batch", route_batch, "motions refined together", at_least(1));
  v("guidance", guidance, "how CFG treats the anchors (defaults: anchors in both passes, no anchor term)");
  v("exact", exact, "end the decode with ProjFlow's projection onto the task's constraints (issue 20)");
}

void AnchorRouteGeneratorConfig::dependencies(DependencyVisitor& d) {
  d("adapter", adapter_run, adapter_config, adapter_overrides);
  // The TMD prior alone is used (and so trained first) only without an adapter.
  if (adapter_run.empty() && adapter_config.empty()) d("prior", prior_run, prior_config, prior_overrides);
}

std::unique_ptr<MotionGenerator> AnchorRouteGeneratorConfig::make(const GeneratorContext& ctx) const {
  std::string run = adapter_run;
  if (run.empty() && !adapter_config.empty()) run = trained_run("adapter", adapter_run, adapter_config, adapter_overrides);
  if (!run.empty()) {
    auto a = load_anchor_adapter(run, ctx.device);
    return std::make_unique<AnchorRouteGenerator>(a.prior, a.module, a.cfg, run, sampler, route, route_batch,
                                                  guidance, exact);
  }
  std::string p = prior_run;
  if (p.empty()) {
    if (prior_config.empty()) fail("generator anchorroute: set adapter_run/adapter_config or prior_run/prior_config");
    p = trained_run("prior", prior_run, prior_config, prior_overrides);
  }
  auto prior = std::make_shared<TokenPrior>(TokenPrior::load(p, ctx.device));
  if (!prior->is_tmd()) fail("generator anchorroute: '{}' is not a tmd_prior run", p);
  return std::make_unique<AnchorRouteGenerator>(prior, nullptr, AnchorAdapterConfig{}, "", sampler, route,
                                                route_batch, AnchorGuidanceConfig{}, exact);
}

MC_REGISTER_GENERATOR("anchorroute", AnchorRouteGeneratorConfig,
                      "AnchorRoute: TMD + anchor adapter (AnchorKV) conditioned on each task's anchors, then "
                      "RouteSolver refinement");

}  // namespace mc
