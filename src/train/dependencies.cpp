// Resolving declared dependencies: each training config a config tree's sections
// declare is trained (or found) and its run noted.
#include "train/dependencies.h"

#include <ATen/CPUGeneratorImpl.h>
#include <fmt/format.h>

#include <mutex>

#include "core/trained_runs.h"
#include "data/skeleton.h"
#include "train/train_job.h"

namespace mc {

std::string train_on_demand(const std::string& config, const std::vector<std::string>& overrides, bool* trained) {
  auto gen = at::detail::getDefaultCPUGenerator();
  torch::Tensor state;
  {
    std::lock_guard<std::mutex> lock(gen.mutex());
    state = gen.get_state();
  }
  const int threads = torch::get_num_threads();
  TrainResult r = run_train(resolve_data_path(config), overrides);
  {
    std::lock_guard<std::mutex> lock(gen.mutex());
    gen.set_state(state);
  }
  torch::set_num_threads(threads);
  if (trained) *trained = !r.skipped;
  return r.run_dir.string();
}

namespace {

// Trains (or finds) each dependency named by its training config and notes the run.
class DependencyResolver : public DependencyVisitor {
 public:
  explicit DependencyResolver(std::ostream* log) : log_(log) {}
  void operator()(const char* what, std::string& run_dir, std::string& config,
                  std::vector<std::string>& overrides) override {
    if (!run_dir.empty() || config.empty()) return;  // a finished run given, or no dependency
    bool trained = false;
    const std::string dir = train_on_demand(config, overrides, &trained);
    note_trained_run(config, overrides, dir);
    if (log_) *log_ << fmt::format("{}: {} ({})\n", what, dir, trained ? "trained" : "already trained");
  }

 private:
  std::ostream* log_;
};

}  // namespace

void resolve_dependencies(Config& cfg, std::ostream* log) {
  DependencyResolver r(log);
  for_each_dependency(cfg, r);
}

void resolve_dependencies(Component& c, std::ostream* log) {
  if (!c.cfg) return;
  DependencyResolver r(log);
  for_each_dependency(*c.cfg, r);
}

}  // namespace mc
