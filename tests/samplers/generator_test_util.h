// Building generators in tests the way a job builds them (declared dependencies
// trained first, train/dependencies.h), and small control tasks over random clips.
#pragma once
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "control/constraint_spec.h"
#include "control/control_task.h"
#include "core/config.h"
#include "samplers/motion_generator.h"
#include "train/dependencies.h"

namespace mc::test {

// A file with one `generator:` component.
struct GeneratorFile : Config {
  Component generator{"generator"};
  void visit(FieldVisitor& v) override { v("generator", generator, "the generator under test"); }
};

// The generator `c` describes, its dependencies resolved first (quietly).
inline std::unique_ptr<MotionGenerator> build_generator(Component& c) {
  resolve_dependencies(c, nullptr);
  return as_generator(c).make(GeneratorContext{});
}

// From a parsed file, or from YAML text holding `generator: {type: ..., ...}`.
inline std::unique_ptr<MotionGenerator> build_generator(const ConfigSource& src) {
  GeneratorFile f;
  parse_config(src, f);
  return build_generator(f.generator);
}
inline std::unique_ptr<MotionGenerator> build_generator(const std::string& yaml) {
  return build_generator(config_from_string(yaml));
}

// A [T, 22, 3] clip of uniform noise in [-amp, amp].
inline std::vector<float> random_clip(int T, unsigned seed, float amp = 1.0f) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-amp, amp);
  std::vector<float> v(static_cast<size_t>(T) * 22 * 3);
  for (auto& x : v) x = u(rng);
  return v;
}

// A task of T frames on a random source clip; `spec_yaml` '' = no constraints.
inline ControlTask make_task(const std::string& id, int T, const std::string& spec_yaml, unsigned seed,
                             const std::string& caption = "a person walks forward") {
  ControlTask t;
  t.id = id;
  t.clip_id = id;
  t.caption = caption;
  t.length = T;
  if (!spec_yaml.empty()) t.spec = parse_constraint_spec_yaml(spec_yaml, id + ".yaml");
  t.source = random_clip(T, seed);
  return t;
}

}  // namespace mc::test
