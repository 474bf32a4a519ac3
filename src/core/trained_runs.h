// Trained components a config names (a finished run directory, or the training
// config and overrides that make it), and where the job layer put each one. A config
// section declares its dependencies (DeclaresDependencies, beside the fields that
// hold them); the layer that orchestrates jobs (train/dependencies.h) trains or finds
// every one before a model or generator is built and notes its run here. Models and
// samplers only look runs up: loading never trains.
#pragma once
#include <string>
#include <vector>

#include "core/config.h"

namespace mc {

// Receives a section's dependency declarations.
class DependencyVisitor {
 public:
  virtual ~DependencyVisitor() = default;
  // One trained component, named by three fields of the section (declared as fields
  // in its visit()): a finished run directory, or its training config + overrides.
  // `what` names it in logs and errors.
  virtual void operator()(const char* what, std::string& run_dir, std::string& config,
                          std::vector<std::string>& overrides) = 0;
};

// Mixed into a config section (beside mc::Config) that names trained components.
struct DeclaresDependencies {
  virtual ~DeclaresDependencies() = default;
  virtual void dependencies(DependencyVisitor& d) = 0;
};

// Gives `d` every dependency `cfg` declares, then those of its sections and
// components (depth first, in field order).
void for_each_dependency(Config& cfg, DependencyVisitor& d);

// Records that the dependency (config, overrides), as a config spells them, is the
// finished run `run_dir`. A later note for the same pair replaces it (the latest
// resolution wins, e.g. under another runs root).
void note_trained_run(const std::string& config, const std::vector<std::string>& overrides,
                      const std::string& run_dir);

// The run directory of a dependency: `run_dir` when set, else the run noted for
// (config, overrides). std::logic_error naming `what` when nothing was noted: the
// component is being built by a caller that did not resolve its dependencies first
// (train/dependencies.h), a bug in that caller, not bad input.
std::string trained_run(const std::string& what, const std::string& run_dir, const std::string& config,
                        const std::vector<std::string>& overrides);

}  // namespace mc
