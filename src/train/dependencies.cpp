// Resolving declared dependencies: a walk over a config tree that trains (or finds)
// each training config its sections declare and notes the run.
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

// Walks a config tree (sections and components) and resolves the dependencies each
// section declares.
class DependencyResolver : public FieldVisitor, public DependencyVisitor {
 public:
  explicit DependencyResolver(std::ostream* log) : log_(log) {}
  void walk(Config& c) {
    if (auto* d = dynamic_cast<DeclaresDependencies*>(&c)) d->dependencies(*this);
    c.visit(*this);
  }
#define MC_IGNORE(T) \
  void field(const char*, T&, const char*, const Check<T>&) override {}
  MC_FIELD_TYPES(MC_IGNORE)
#undef MC_IGNORE
  void section(const char*, Config& c, const char*) override { walk(c); }
  void component(const char*, Component& c, const char*) override {
    if (c.cfg) walk(*c.cfg);
  }
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
  r.walk(cfg);
}

void resolve_dependencies(Component& c, std::ostream* log) {
  DependencyResolver r(log);
  if (c.cfg) r.walk(*c.cfg);
}

}  // namespace mc
