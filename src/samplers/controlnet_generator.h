// Control tasks -> the ControlNet's control signal, and ControlNet sampling
// (the `generator: {type: flow_controlnet}` component lives in the .cpp).
#pragma once
#include <vector>

#include "control/control_task.h"
#include "models/flow_controlnet.h"

namespace mc {

struct ControlTargets {
  torch::Tensor target;  // [N, T, J, 3] normalised (the base's normaliser), 0 where not controlled
  torch::Tensor mask;    // [N, T, J, 3] float, 1 on controlled entries
};

// Only keyframe and trajectory items (per-joint xyz selections) can be expressed;
// any other item type is a UserError naming the task and the item. Soft items
// (variance > 0) are used as exact targets: the branch has no notion of variance.
ControlTargets control_targets(const FlowPrior& base, const std::vector<ControlTask>& tasks, int64_t frames);

struct ControlNetSampleConfig : Config {
  int steps = 99;             // Euler updates over linspace(0, 1, steps + 1)
  double text_cfg = 2.5;      // s_text
  double control_cfg = 1.75;  // s_ctrl
  int batch_size = 32;
  void visit(FieldVisitor& v) override {
    v("steps", steps, "ODE updates; the time grid is linspace(0, 1, steps + 1)", in_range(1, 10000));
    v("text_cfg", text_cfg, "text guidance s_text (see FlowControlNet::velocity)", in_range(0.0, 100.0));
    v("control_cfg", control_cfg, "control guidance s_ctrl (see FlowControlNet::velocity)", in_range(0.0, 100.0));
    v("batch_size", batch_size, "motions per network call", at_least(1));
  }
};

// World motions [N, T, J, 3] (CPU, zero past each length) for the tasks; noise drawn
// up front from a generator seeded with `seed`. UserError on non-finite output.
torch::Tensor sample_controlnet(const FlowControlNet& net, const std::vector<ControlTask>& tasks,
                                const ControlNetSampleConfig& cfg, uint64_t seed);

}  // namespace mc
