// The reference output of a flow prior on a fixed input, stored beside its exported
// weights (`motionctl export --format weights --probe`, group /probe of the file) so a
// re-implementation outside motionctl (tools/flow_reference.py) can check itself:
// fixed noise-like joints x_t, a time t of the sampler's grid, two captions (their
// token ids and the text vectors), a padding mask, and the conditional,
// unconditional and guided velocities and the Euler step this C++ code computes.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "models/flow_prior.h"
#include "models/flow_weights.h"
#include "samplers/flow_sampler.h"

namespace mc {

struct FlowProbeOptions {
  std::vector<std::string> captions = {"a person walks forward and waves with the left hand",
                                       "someone jumps twice, then turns around"};
  int frames = 40;       // T of the probe batch (capped at the prior's t_max); the second clip is shorter
  uint64_t seed = 0;     // of x_t (torch's CPU generator)
  int steps = 99;        // the sampler's time grid linspace(0, 1, steps + 1) (FlowSamplerConfig's default)
  int step = 30;         // the probe's step k: t = grid[k], t_next = grid[k + 1]
  double cfg_scale = 2.5;  // FlowSamplerConfig's default
};

// The probe's inputs and outputs as the group "probe" (names in docs/formats.md).
// UserError when an option is out of range.
FlowWeightsGroup flow_probe(const FlowPrior& prior, const FlowProbeOptions& opt = {});

}  // namespace mc
