// Naming a flow prior in a config (a finished run, or its training config trained
// on demand) and loading it: shared by `motionctl sample` and every flow generator.
#pragma once
#include <string>
#include <vector>

#include "core/config.h"
#include "samplers/flow_sampler.h"

namespace mc {

struct PriorSourceConfig : Config {
  std::string run_dir;                 // a finished flow_prior run; wins over `config`
  std::string config;                  // else its training config, trained first when not finished
  std::vector<std::string> overrides;  // overrides for `config`
  void visit(FieldVisitor& v) override {
    v("run_dir", run_dir, "finished flow_prior run directory (takes precedence over config)");
    v("config", config, "training config of the prior (when run_dir is empty); trained like `motionctl train` "
      "unless already finished");
    v("overrides", overrides, "key=value overrides applied to `config`");
  }
  std::string validate() const override {
    if (run_dir.empty() && config.empty()) return "set prior.run_dir (a finished flow_prior run) or prior.config";
    return "";
  }
};

// The run directory `src` names, training it first when only a config is given
// and its run is not finished. `log` (may be null) gets one line saying which.
std::string resolve_prior_run(const PriorSourceConfig& src, std::ostream* log = nullptr);

// resolve_prior_run + FlowPrior::load.
FlowPrior load_flow_prior(const PriorSourceConfig& src, torch::Device device, std::ostream* log = nullptr);

}  // namespace mc
