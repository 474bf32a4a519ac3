// Resolving and loading the flow prior a config names.
#include "models/prior_source.h"

#include <ostream>

#include "train/train_job.h"

namespace mc {

std::string resolve_prior_run(const PriorSourceConfig& src, std::ostream* log) {
  if (!src.run_dir.empty()) return resolve_data_path(src.run_dir);
  TrainResult r = run_train(resolve_data_path(src.config), src.overrides);
  if (log) *log << "prior: " << r.run_dir.string() << (r.skipped ? " (already trained)" : " (trained)") << "\n";
  return r.run_dir.string();
}

FlowPrior load_flow_prior(const PriorSourceConfig& src, torch::Device device, std::ostream* log) {
  return FlowPrior::load(resolve_prior_run(src, log), device);
}

}  // namespace mc
