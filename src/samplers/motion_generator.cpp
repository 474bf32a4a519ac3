// Casting a `generator:` component to the GeneratorConfig interface.
#include "samplers/motion_generator.h"

#include <stdexcept>

namespace mc {

const GeneratorConfig& as_generator(const Component& c) {
  auto* p = dynamic_cast<const GeneratorConfig*>(c.cfg.get());
  if (!p) throw std::logic_error("component '" + c.family + "' of type '" + c.type + "' is not a generator");
  return *p;
}

}  // namespace mc
