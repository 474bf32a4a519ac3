// Resolving a `prior: {run_dir | config, overrides}` section (PriorSourceConfig) to a
// loaded FlowPrior, training the prior on demand like `motionctl sample` does.
#pragma once
#include <string>

#include "cli/sample_job.h"
#include "samplers/flow_sampler.h"

namespace mc {

// The finished run directory `src` names: run_dir as is, else run_train(config, overrides)
// (skipped when that run is already finished). `what` names the section in messages.
std::string resolve_prior_run(const PriorSourceConfig& src, const std::string& what = "prior");

// resolve_prior_run + FlowPrior::load.
FlowPrior load_prior_source(const PriorSourceConfig& src, torch::Device device, const std::string& what = "prior");

}  // namespace mc
