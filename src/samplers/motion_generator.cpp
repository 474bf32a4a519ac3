// Casting a `generator:` component to the GeneratorConfig interface, and generated
// motions as a motion set (what every evaluation of a generator reads).
#include "samplers/motion_generator.h"

#include <sstream>
#include <stdexcept>

#include "core/error.h"

namespace mc {

const GeneratorConfig& as_generator(const Component& c) {
  auto* p = dynamic_cast<const GeneratorConfig*>(c.cfg.get());
  if (!p) throw std::logic_error("component '" + c.family + "' of type '" + c.type + "' is not a generator");
  return *p;
}

MotionSet generated_motion_set(const GeneratedMotions& g, const std::vector<ControlTask>& tasks,
                               const MotionSet& like) {
  MotionSet m;
  m.skeleton = like.skeleton;
  m.fps = like.fps;
  m.t_max = like.t_max;
  const int J = like.num_joints();
  torch::Tensor w = g.world.to(torch::kCPU, torch::kFloat).contiguous();
  if (w.dim() != 4 || w.size(0) != static_cast<int64_t>(tasks.size()) || w.size(2) != J || w.size(3) != 3)
    fail("generator returned motions of shape {} for {} tasks of a {}-joint skeleton", (std::ostringstream() << w.sizes()).str(),
         tasks.size(), J);
  if (!torch::isfinite(w).all().item<bool>()) fail("generator returned non-finite joints; nothing was written");
  const int64_t T = std::min<int64_t>(w.size(1), m.t_max);
  m.joints.assign(tasks.size() * m.clip_stride(), 0.0f);
  const float* src = w.data_ptr<float>();
  for (size_t i = 0; i < tasks.size(); ++i) {
    int len = std::min<int>(g.lengths.at(i), static_cast<int>(T));
    std::copy(src + i * w.size(1) * J * 3, src + (i * w.size(1) + len) * J * 3, m.clip(i));
    m.lengths.push_back(len);
    m.ids.push_back(tasks[i].id);
    m.splits.push_back("sample");
    m.captions.push_back({tasks[i].caption});
  }
  m.stats = like.stats;
  return m;
}

}  // namespace mc
