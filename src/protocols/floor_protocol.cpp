// `protocol: {type: with_floor, base: {...}}` (issue 20): any protocol's tasks with one
// more item, "these joints never below the floor" (by default the toes, y >= 0), so a
// floor application runs on every control task and its rows pair with the plain ones
// (same clips, ids, groups and seeds; only the extra item differs).
#include "control/control_task.h"
#include "core/error.h"

namespace mc {
namespace {

struct WithFloorProtocol : ControlProtocol {
  Component base{"protocol"};
  std::vector<std::string> joints;  // empty: the skeleton's toes role
  double height = 0.0;
  double variance = 0.0;
  void visit(FieldVisitor& v) override {
    v("base", base, "the protocol whose every task gets the floor item (picked by type)");
    v("joints", joints, "joints kept above the floor, by name ([] = the skeleton's 'toes' role)");
    v("height", height, "floor height: y >= height for those joints at every frame (metres)");
    v("variance", variance, "0 = a hard floor; > 0 = soft, the one-sided penalty's variance (m^2)", at_least(0.0));
  }
  std::vector<ControlTask> make_tasks(const MotionSet& data, const std::vector<size_t>& clips,
                                      uint64_t seed) const override {
    if (!base.cfg) fail("protocol.base: name the protocol whose tasks get the floor (protocol.base.type)");
    std::vector<ControlTask> tasks = as_protocol(base).make_tasks(data, clips, seed);
    ConstraintItem floor;
    floor.type = "floor";
    floor.name = fmt::format("floor (y >= {:g})", height);
    floor.height = height;
    floor.variance = variance;
    for (const auto& j : joints) floor.joints.push_back(JointRef{-1, j});
    for (auto& t : tasks) t.spec.items.push_back(floor);
    return tasks;
  }
};
MC_REGISTER_PROTOCOL("with_floor", WithFloorProtocol,
                     "another protocol's tasks plus a floor item: its joints (default the toes) never below y = height");

}  // namespace
}  // namespace mc
