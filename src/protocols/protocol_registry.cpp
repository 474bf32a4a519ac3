// Casting a `protocol:` component to the ControlProtocol interface.
#include <stdexcept>

#include "control/control_task.h"

namespace mc {

const ControlProtocol& as_protocol(const Component& c) {
  auto* p = dynamic_cast<const ControlProtocol*>(c.cfg.get());
  if (!p) throw std::logic_error("component '" + c.family + "' of type '" + c.type + "' is not a control protocol");
  return *p;
}

}  // namespace mc
