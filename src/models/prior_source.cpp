// Finding and loading the flow prior a config names.
#include "models/prior_source.h"

#include "core/trained_runs.h"
#include "data/skeleton.h"

namespace mc {

std::string PriorSourceConfig::run() const {
  if (!run_dir.empty()) return resolve_data_path(run_dir);
  return trained_run("prior", run_dir, config, overrides);
}

FlowPrior load_flow_prior(const PriorSourceConfig& src, torch::Device device) {
  return FlowPrior::load(src.run(), device);
}

}  // namespace mc
