// A prior named by run directory or by training config, trained on demand.
#include "samplers/prior_source.h"

#include "core/error.h"
#include "data/skeleton.h"
#include "train/train_job.h"

namespace mc {

std::string resolve_prior_run(const PriorSourceConfig& src, const std::string& what) {
  if (!src.run_dir.empty()) return src.run_dir;
  if (src.config.empty()) fail("{}: set {}.run_dir (a finished run) or {}.config (trained on demand)", what, what, what);
  TrainResult r = run_train(resolve_data_path(src.config), src.overrides);
  return r.run_dir.string();
}

FlowPrior load_prior_source(const PriorSourceConfig& src, torch::Device device, const std::string& what) {
  return FlowPrior::load(resolve_prior_run(src, what), device);
}

}  // namespace mc
