// Controlled-generation requests (caption, length, constraint spec, the ground-truth
// clip they were drawn from) and the `protocol:` component that draws them.
// One type feeds every method (ProjFlow, its baselines, AnchorRoute) and every metric.
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "core/config.h"

namespace mc {

struct MotionSet;

struct ControlTask {
  std::string id;       // unique within a task list: "<clip id>" or "<clip id>#<k>"
  std::string clip_id;  // the ground-truth clip the task came from
  std::string caption;  // text condition (the clip's first caption unless the protocol says otherwise)
  int length = 0;       // frames to generate (= the clip's length)
  ConstraintSpec spec;  // world units; compile(spec, length, skeleton, source.data())
  std::vector<float> source;  // [length, J, 3] world metres of the ground-truth clip
  std::string group;    // protocol cell for per-group metrics, e.g. "joint=pelvis/density=5" or "K=8"
};

// Base of every `protocol:` component type. A protocol is a deterministic function
// of (data, clips, seed): the same arguments give the same tasks.
struct ControlProtocol : Config {
  // One or more tasks per clip index of `data` (indices into data, e.g. its test split).
  // UserError when the protocol cannot be applied (clip too short, joint unknown to
  // the skeleton, ...), naming the protocol key and the clip.
  virtual std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                              uint64_t seed) const = 0;
};

// Registers CONFIG (a ControlProtocol) as `protocol: {type: TYPE}`. Protocol sources
// live in src/protocols/ (linked as objects, so the registration is never dropped).
#define MC_REGISTER_PROTOCOL(TYPE, CONFIG, HELP) \
  static ::mc::ComponentRegistration<CONFIG> mc_protocol_registration_##CONFIG("protocol", TYPE, HELP)

// The protocol config of a Component{"protocol"}; logic_error if the type is not a protocol.
const ControlProtocol& as_protocol(const Component& c);

}  // namespace mc
