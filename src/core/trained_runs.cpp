// The table of resolved dependencies: (training config, overrides) -> run directory.
#include "core/trained_runs.h"

#include <map>
#include <mutex>
#include <stdexcept>

#include <fmt/format.h>
#include <fmt/ranges.h>

namespace mc {

namespace {

using Key = std::pair<std::string, std::vector<std::string>>;

std::map<Key, std::string>& table() {
  static std::map<Key, std::string> t;
  return t;
}

std::mutex& table_mutex() {
  static std::mutex m;
  return m;
}

}  // namespace

namespace {

// Walks a config tree (sections and components) and hands each section's declared
// dependencies to the visitor.
class DependencyWalk : public FieldVisitor {
 public:
  explicit DependencyWalk(DependencyVisitor& d) : d_(d) {}
  void walk(Config& c) {
    if (auto* declares = dynamic_cast<DeclaresDependencies*>(&c)) declares->dependencies(d_);
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

 private:
  DependencyVisitor& d_;
};

}  // namespace

void for_each_dependency(Config& cfg, DependencyVisitor& d) { DependencyWalk(d).walk(cfg); }

void note_trained_run(const std::string& config, const std::vector<std::string>& overrides,
                      const std::string& run_dir) {
  std::lock_guard<std::mutex> lock(table_mutex());
  table()[{config, overrides}] = run_dir;
}

std::string trained_run(const std::string& what, const std::string& run_dir, const std::string& config,
                        const std::vector<std::string>& overrides) {
  if (!run_dir.empty()) return run_dir;
  std::lock_guard<std::mutex> lock(table_mutex());
  auto it = table().find({config, overrides});
  if (it != table().end()) return it->second;
  throw std::logic_error(fmt::format(
      "{}: the run of training config '{}' (overrides [{}]) was not resolved before loading; the job that builds "
      "this component must call resolve_dependencies (train/dependencies.h) first, or name a finished run directory",
      what, config, fmt::join(overrides, ", ")));
}

}  // namespace mc
