// `generator:` types on the flow prior: `flow` (unconstrained text-to-motion),
// `projflow` (the paper's sampler; imputation is its preset with every switch off)
// and `flow_guidance` (reconstruction guidance). All read the tasks' constraint specs.
#include <chrono>

#include "control/control_task.h"
#include "core/error.h"
#include "samplers/motion_generator.h"
#include "models/prior_source.h"
#include "samplers/projflow.h"
#include "samplers/task_observation.h"

namespace mc {
namespace {

using Clock = std::chrono::steady_clock;

struct FlowInputs {
  std::vector<std::string> captions;
  std::vector<int> lengths;
};
FlowInputs flow_inputs(const FlowPrior& prior, const std::vector<ControlTask>& tasks) {
  FlowInputs in;
  for (const auto& t : tasks) {
    if (t.length < 1 || t.length > prior.t_max())
      fail("task '{}' asks for {} frames; the prior '{}' generates 1..{}", t.id, t.length, prior.run_dir(),
           prior.t_max());
    in.captions.push_back(t.caption);
    in.lengths.push_back(t.length);
  }
  return in;
}

GeneratedMotions to_generated(FlowSampleResult r, double seconds) {
  GeneratedMotions g;
  g.world = std::move(r.world);
  g.lengths = std::move(r.lengths);
  g.seconds = seconds;
  return g;
}

// ---------------------------------------------------------------- flow (no control)

class FlowGenerator : public MotionGenerator {
 public:
  FlowGenerator(FlowPrior prior, FlowSamplerConfig s) : prior_(std::move(prior)), s_(s) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    auto in = flow_inputs(prior_, tasks);
    auto t0 = Clock::now();
    auto r = sample_flow(prior_, in.captions, in.lengths, s_, seed);
    return to_generated(std::move(r), std::chrono::duration<double>(Clock::now() - t0).count());
  }
  std::string describe() const override {
    return fmt::format("flow prior {} (Euler, {} steps, {}; constraints ignored)", prior_.run_dir(), s_.steps,
                       s_.describe_cfg());
  }

 private:
  FlowPrior prior_;
  FlowSamplerConfig s_;
};

struct FlowGeneratorConfig : GeneratorConfig {
  PriorSourceConfig prior;
  FlowSamplerConfig sampler;
  void visit(FieldVisitor& v) override {
    v("prior", prior, "the flow prior");
    v("sampler", sampler, "ODE sampler settings");
  }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    return std::make_unique<FlowGenerator>(load_flow_prior(prior, ctx.device), sampler);
  }
};
MC_REGISTER_GENERATOR("flow", FlowGeneratorConfig, "the flow prior's text-to-motion samples (constraints ignored)");

// ---------------------------------------------------------------- projflow

class ProjFlowGenerator : public MotionGenerator {
 public:
  ProjFlowGenerator(FlowPrior prior, FlowSamplerConfig s, ProjFlowConfig p)
      : prior_(std::move(prior)), s_(s), p_(p), metric_(KinematicMetric::from_config(p.metric, prior_.skeleton())) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    auto in = flow_inputs(prior_, tasks);
    auto obs = model_observations(prior_, tasks);
    auto t0 = Clock::now();
    ProjFlowStepper stepper(p_, metric_, std::move(obs));
    auto r = sample_flow(prior_, in.captions, in.lengths, s_, seed, &stepper);
    auto g = to_generated(std::move(r), std::chrono::duration<double>(Clock::now() - t0).count());
    g.notes.push_back(fmt::format("projection time {:.3f} s over {} projections", stepper.projection_seconds(),
                                  stepper.projections()));
    return g;
  }
  std::string describe() const override {
    return fmt::format("ProjFlow on {} ({} steps, {}, metric {}, noise {}, pseudo-observations {})",
                       prior_.run_dir(), s_.steps, s_.describe_cfg(), p_.metric.type, p_.noise,
                       p_.pseudo_observations.enabled ? "on" : "off");
  }

 private:
  FlowPrior prior_;
  FlowSamplerConfig s_;
  ProjFlowConfig p_;
  KinematicMetric metric_;
};

struct ProjFlowGeneratorConfig : GeneratorConfig {
  PriorSourceConfig prior;
  FlowSamplerConfig sampler;
  ProjFlowConfig projflow;
  void visit(FieldVisitor& v) override {
    v("prior", prior, "the flow prior");
    v("sampler", sampler, "ODE sampler settings");
    v("projflow", projflow, "projection, recombination and pseudo-observation settings");
  }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    return std::make_unique<ProjFlowGenerator>(load_flow_prior(prior, ctx.device), sampler, projflow);
  }
};
MC_REGISTER_GENERATOR("projflow", ProjFlowGeneratorConfig,
                      "ProjFlow projection sampling (metric/noise/pseudo-observation switches; all off = imputation)");

// ---------------------------------------------------------------- guidance

class GuidanceGenerator : public MotionGenerator {
 public:
  GuidanceGenerator(FlowPrior prior, FlowSamplerConfig s, GuidanceConfig g)
      : prior_(std::move(prior)), s_(s), g_(g) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    auto in = flow_inputs(prior_, tasks);
    auto obs = model_observations(prior_, tasks);
    auto t0 = Clock::now();
    GuidanceStepper stepper(prior_, g_, std::move(obs), prior_.encode_texts(in.captions));
    auto r = sample_flow(prior_, in.captions, in.lengths, s_, seed, &stepper);
    return to_generated(std::move(r), std::chrono::duration<double>(Clock::now() - t0).count());
  }
  std::string describe() const override {
    return fmt::format(
        "reconstruction guidance on {} ({} steps, {}, scale {} on the mean squared residual, {} iterations/step, "
        "{} in the last {} steps, {})",
        prior_.run_dir(), s_.steps, s_.describe_cfg(), g_.scale, g_.iterations, g_.final_iterations, g_.final_steps,
        g_.clip_to_residual ? "clipped to the residual" : "unclipped");
  }

 private:
  FlowPrior prior_;
  FlowSamplerConfig s_;
  GuidanceConfig g_;
};

struct GuidanceGeneratorConfig : GeneratorConfig {
  PriorSourceConfig prior;
  FlowSamplerConfig sampler;
  GuidanceConfig guidance;
  void visit(FieldVisitor& v) override {
    v("prior", prior, "the flow prior");
    v("sampler", sampler, "ODE sampler settings");
    v("guidance", guidance, "gradient guidance settings");
  }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    return std::make_unique<GuidanceGenerator>(load_flow_prior(prior, ctx.device), sampler, guidance);
  }
};
MC_REGISTER_GENERATOR("flow_guidance", GuidanceGeneratorConfig,
                      "reconstruction guidance (GMD/OmniControl-style gradient steps inside flow sampling)");

}  // namespace
}  // namespace mc
