// Naming a flow prior in a config (a finished run, or its training config, trained
// first by the job: train/dependencies.h) and loading it: shared by `motionctl
// sample`, every flow generator and the ControlNet's frozen base.
#pragma once
#include <string>
#include <vector>

#include "core/config.h"
#include "core/trained_runs.h"
#include "models/flow_prior.h"

namespace mc {

struct PriorSourceConfig : Config, DeclaresDependencies {
  std::string run_dir;                 // a finished flow_prior run; wins over `config`
  std::string config;                  // else its training config, trained first when not finished
  std::vector<std::string> overrides;  // overrides for `config`
  void visit(FieldVisitor& v) override {
    v("run_dir", run_dir, "finished flow_prior run directory (takes precedence over config)");
    v("config", config, "training config of the prior (when run_dir is empty); trained like `motionctl train` "
      "unless already finished");
    v("overrides", overrides, "key=value overrides applied to `config`");
  }
  void dependencies(DependencyVisitor& d) override { d("prior", run_dir, config, overrides); }
  std::string validate() const override {
    if (run_dir.empty() && config.empty()) return "set prior.run_dir (a finished flow_prior run) or prior.config";
    return "";
  }
  // The run directory: run_dir, or the run of `config` the job resolved.
  std::string run() const;
};

// FlowPrior::load(src.run()).
FlowPrior load_flow_prior(const PriorSourceConfig& src, torch::Device device);

}  // namespace mc
