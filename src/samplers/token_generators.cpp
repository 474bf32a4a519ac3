// Generators `tmd` and `masked`: unconstrained text-to-motion from a token prior
// (Table I rows). Constraint specs are ignored; a prior named by its training config
// is trained first by the job (train/dependencies.h).
#include <chrono>
#include <type_traits>

#include "core/error.h"
#include "core/trained_runs.h"
#include "samplers/motion_generator.h"
#include "samplers/tmd_sampler.h"
#include "models/token_prior.h"

namespace mc {

namespace {

// The prior run: given, or its training config run on demand.
struct TokenPriorSource : Config, DeclaresDependencies {
  std::string prior_run;
  std::string prior_config;
  std::vector<std::string> prior_overrides;
  explicit TokenPriorSource(std::string default_config) : prior_config(std::move(default_config)) {}
  void visit(FieldVisitor& v) override {
    v("prior_run", prior_run, "finished token prior run directory ('' = train prior_config on demand)");
    v("prior_config", prior_config, "prior training config run on demand when prior_run is ''");
    v("prior_overrides", prior_overrides, "key=value overrides for prior_config");
  }
  void dependencies(DependencyVisitor& d) override { d("prior", prior_run, prior_config, prior_overrides); }
  std::string resolve() const {
    if (!prior_run.empty()) return prior_run;
    if (prior_config.empty()) fail("generator: set prior_run (a finished token prior run) or prior_config");
    return trained_run("prior", prior_run, prior_config, prior_overrides);
  }
};

template <class SamplerConfig>
class TokenPriorGenerator : public MotionGenerator {
 public:
  TokenPriorGenerator(TokenPrior prior, SamplerConfig cfg) : prior_(std::move(prior)), cfg_(std::move(cfg)) {}

  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) override {
    std::vector<std::string> captions;
    std::vector<int> lengths;
    for (const auto& t : tasks) {
      captions.push_back(t.caption);
      lengths.push_back(t.length);
    }
    auto t0 = std::chrono::steady_clock::now();
    TokenSampleResult r;
    if constexpr (std::is_same_v<SamplerConfig, TmdSamplerConfig>)
      r = sample_tmd(prior_, captions, lengths, cfg_, seed);
    else
      r = sample_masked(prior_, captions, lengths, cfg_, seed);
    GeneratedMotions out;
    out.world = r.world;
    out.lengths = r.lengths;
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    out.notes.push_back(describe());
    return out;
  }

  std::string describe() const override {
    if constexpr (std::is_same_v<SamplerConfig, TmdSamplerConfig>)
      return fmt::format("TMD prior {} ({} steps, cfg {}, proposal {}, last step {})", prior_.run_dir(), cfg_.steps,
                         cfg_.cfg_scale, cfg_.proposal, cfg_.last_step);
    else
      return fmt::format("masked prior {} ({} steps, cfg {}, top-k keep {})", prior_.run_dir(), cfg_.steps,
                         cfg_.cfg_scale, cfg_.topk_keep);
  }

 private:
  TokenPrior prior_;
  SamplerConfig cfg_;
};

}  // namespace

struct TmdGeneratorConfig : GeneratorConfig, DeclaresDependencies {
  TokenPriorSource source{"configs/tmd/tmd_tiny.yaml"};
  TmdSamplerConfig sampler;
  void visit(FieldVisitor& v) override {
    source.visit(v);
    v("sampler", sampler, "TMD transition sampler (eqs. (21)-(23))");
  }
  void dependencies(DependencyVisitor& d) override { source.dependencies(d); }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    auto prior = TokenPrior::load(source.resolve(), ctx.device);
    if (!prior.is_tmd()) fail("generator tmd: '{}' is not a tmd_prior run (use generator type masked)", prior.run_dir());
    return std::make_unique<TokenPriorGenerator<TmdSamplerConfig>>(std::move(prior), sampler);
  }
};

struct MaskedGeneratorConfig : GeneratorConfig, DeclaresDependencies {
  TokenPriorSource source{"configs/masked/masked_tiny.yaml"};
  MaskedSamplerConfig sampler;
  void visit(FieldVisitor& v) override {
    source.visit(v);
    v("sampler", sampler, "MoMask-style confidence re-masking sampler");
  }
  void dependencies(DependencyVisitor& d) override { source.dependencies(d); }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const override {
    auto prior = TokenPrior::load(source.resolve(), ctx.device);
    if (prior.is_tmd()) fail("generator masked: '{}' is a tmd_prior run (use generator type tmd)", prior.run_dir());
    return std::make_unique<TokenPriorGenerator<MaskedSamplerConfig>>(std::move(prior), sampler);
  }
};

MC_REGISTER_GENERATOR("tmd", TmdGeneratorConfig,
                      "TMD token prior, unconstrained text-to-motion (AnchorRoute Table I); ignores constraints");
MC_REGISTER_GENERATOR("masked", MaskedGeneratorConfig,
                      "MoMask-style masked token prior, unconstrained text-to-motion (Table I baseline)");

}  // namespace mc
