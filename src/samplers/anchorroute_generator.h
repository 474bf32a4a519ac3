// The `anchorroute` generator's config (AnchorRoute, §3.2-§3.4): TMD sampling through a
// trained anchor adapter, anchor-aware CFG, optional RouteSolver refinement. Declared
// here so `bench anchorroute` can read the components it names.
#pragma once
#include <memory>
#include <string>
#include <vector>

#include "control/kinematic_metric.h"
#include "core/config.h"
#include "core/trained_runs.h"
#include "models/token_transformer.h"
#include "samplers/motion_generator.h"
#include "samplers/route_solver.h"
#include "samplers/tmd_sampler.h"

namespace mc {

// How CFG treats the anchors (issue 15; TokenTransformerHooks::guidance). The defaults,
// the anchors in both CFG halves and no anchor term, are what the paper's setup implies
// (text CFG on the conditioned network) and are left out of the dumped config.
struct AnchorGuidanceConfig : Config {
  std::string anchors = "both";  // both | conditional
  double scale = 1.0;            // s_a
  void visit(FieldVisitor& v) override {
    v("anchors", anchors,
      "which CFG passes see the anchors: both (text guidance on the anchored network: l_uA + s (l_cA - l_uA)) or "
      "conditional (the unconditional pass is the frozen prior without anchors: l_u0 + s (l_cA - l_u0), so text "
      "guidance also amplifies the anchors)",
      one_of({"both", "conditional"}));
    v("scale", scale,
      "anchor guidance weight s_a: != 1 adds a third pass (text, no anchors) and (s_a - 1)(l_cA - l_c0), as "
      "ACMDM's ControlNet guidance weighs its control",
      in_range(0.0, 100.0));
  }
  bool omitted_from_dump() const override { return anchors == "both" && scale == 1.0; }
  HookGuidance hooks() const { return {anchors == "both", scale}; }
};

// `exact:` (issue 20, beyond both papers) ends AnchorRoute's decode with ProjFlow's
// projection (eq. (7), kinematic metric eq. (11), world units) onto the task's whole
// constraint spec: anchors, inequalities and direction rows, so anchors hold exactly.
// Left out of the dumped config while off.
struct ExactProjectionConfig : Config {
  bool enabled = false;
  MetricConfig metric;
  void visit(FieldVisitor& v) override {
    v("enabled", enabled, "project the decoded motion onto the task's constraints (anchors exact)");
    v("metric", metric, "metric R of the projection (eq. (11))");
  }
  bool omitted_from_dump() const override { return !enabled; }
};

struct AnchorRouteGeneratorConfig : GeneratorConfig, DeclaresDependencies {
  std::string adapter_run;
  std::string adapter_config;
  std::vector<std::string> adapter_overrides;
  std::string prior_run;
  std::string prior_config = "configs/tmd/tmd_tiny.yaml";
  std::vector<std::string> prior_overrides;
  TmdSamplerConfig sampler;
  RouteSolverConfig route;
  int route_batch = 16;
  AnchorGuidanceConfig guidance;
  ExactProjectionConfig exact;
  void visit(FieldVisitor& v) override;
  void dependencies(DependencyVisitor& d) override;
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override;
};

}  // namespace mc
