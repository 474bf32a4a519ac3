// Training what a component needs before it is built: the job layer's half of the
// dependency declarations (DeclaresDependencies, core/trained_runs.h). Models and generators never
// train; every job that builds one (train, generate, sample, eval, health,
// reproduce, bench) resolves its config here first, and the component then looks
// its runs up (core/trained_runs.h).
#pragma once
#include <iostream>
#include <string>
#include <vector>

#include "core/config.h"

namespace mc {

// run_train(config, overrides).run_dir, leaving torch's CPU generator state and
// thread count as they were (a run that trains reseeds both and sets its own thread
// count; a finished one does not): the caller's random stream and threads do not
// depend on whether the dependency was trained now or earlier. `trained` (may be
// null) says whether it was.
std::string train_on_demand(const std::string& config, const std::vector<std::string>& overrides,
                            bool* trained = nullptr);

// Every dependency `cfg` declares, in its sections and components too: one named by
// its training config is trained unless finished (train_on_demand; run_train resolves
// that run's own model dependencies the same way) and noted in core/trained_runs.h;
// one named by a run directory is used as it is. `log` (may be null) gets one line
// per dependency: "<what>: <run dir> (trained|already trained)".
void resolve_dependencies(Config& cfg, std::ostream* log = &std::cerr);
void resolve_dependencies(Component& c, std::ostream* log = &std::cerr);

}  // namespace mc
