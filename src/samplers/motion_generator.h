// Anything that turns control tasks into motions: ProjFlow, its baselines, the
// unconstrained prior, AnchorRoute and its variants. Picked by `generator: {type: ...}`.
#pragma once
#include <cstdint>
#include <memory>
#include <map>
#include <string>
#include <vector>

#include <torch/torch.h>

#include "control/control_task.h"
#include "core/config.h"
#include "data/motion_set.h"

namespace mc {

struct GeneratedMotions {
  torch::Tensor world;       // [N, T, J, 3] float, world metres, CPU, zero past each length
  std::vector<int> lengths;  // [N] = the tasks' lengths
  double seconds = 0;        // wall time of generation for all N (excludes loading/training)
  std::vector<std::string> notes;  // e.g. "trainable parameters: 1.2M", shown in run logs
  // Numbers about the generator that tables report beside the metrics (e.g.
  // "params": trainable conditioning parameters, "steps": refinement steps).
  std::map<std::string, double> stats;
};

struct GeneratorContext {
  torch::Device device = torch::kCPU;
};

class MotionGenerator {
 public:
  virtual ~MotionGenerator() = default;
  // One motion per task, in task order. Deterministic in (tasks, seed). UserError on
  // bad tasks (e.g. a constraint the method cannot express) or a non-finite result.
  virtual GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t seed) = 0;
  virtual std::string describe() const = 0;  // one line for logs: method and key settings
};

// Base of every `generator:` component type: the config builds the generator from
// finished runs. Trained components it names by training config are declared
// (DeclaresDependencies, core/trained_runs.h) and trained first by the job that
// builds it (train/dependencies.h); make() only loads them.
struct GeneratorConfig : Config {
  virtual std::unique_ptr<MotionGenerator> make(const GeneratorContext& ctx) const = 0;
};

#define MC_REGISTER_GENERATOR(TYPE, CONFIG, HELP) \
  static ::mc::ComponentRegistration<CONFIG> mc_generator_registration_##CONFIG("generator", TYPE, HELP)

const GeneratorConfig& as_generator(const Component& c);

// The generated motions as a motion set shaped like `like` (skeleton, fps, t_max,
// stats): clip i = task i's motion trimmed to its length, split "sample", caption =
// the task's. UserError on a wrong shape or non-finite joints.
MotionSet generated_motion_set(const GeneratedMotions& g, const std::vector<ControlTask>& tasks,
                               const MotionSet& like);

}  // namespace mc
