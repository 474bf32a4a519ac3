// `generator: {type: ground_truth}`: returns each task's ground-truth clip. The
// "Real motion" row of every table, and the oracle the experiment layer is tested with.
#include <chrono>

#include "core/error.h"
#include "samplers/motion_generator.h"

namespace mc {
namespace {

class GroundTruthGenerator : public MotionGenerator {
 public:
  explicit GroundTruthGenerator(int joints) : joints_(joints) {}
  GeneratedMotions generate(const std::vector<ControlTask>& tasks, uint64_t) override {
    auto t0 = std::chrono::steady_clock::now();
    GeneratedMotions g;
    int T = 0;
    for (auto& t : tasks) T = std::max(T, t.length);
    g.world = torch::zeros({static_cast<int64_t>(tasks.size()), T, joints_, 3});
    for (size_t i = 0; i < tasks.size(); ++i) {
      const auto& t = tasks[i];
      if (t.source.size() != static_cast<size_t>(t.length) * joints_ * 3)
        fail("task '{}' carries no ground-truth clip of {} frames x {} joints; the ground_truth generator needs one",
             t.id, t.length, joints_);
      auto src = torch::from_blob(const_cast<float*>(t.source.data()), {t.length, joints_, 3}, torch::kFloat);
      g.world[static_cast<int64_t>(i)].narrow(0, 0, t.length).copy_(src);
      g.lengths.push_back(t.length);
    }
    g.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return g;
  }
  std::string describe() const override { return "ground truth (the task's source clip)"; }

 private:
  int joints_;
};

struct GroundTruthConfig : GeneratorConfig {
  int joints = 22;
  void visit(FieldVisitor& v) override { v("joints", joints, "joints per frame of the tasks' clips", at_least(1)); }
  std::unique_ptr<MotionGenerator> make(const GeneratorContext&) const override {
    return std::make_unique<GroundTruthGenerator>(joints);
  }
};

MC_REGISTER_GENERATOR("ground_truth", GroundTruthConfig, "the task's ground-truth clip (Real motion rows)");

}  // namespace
}  // namespace mc
