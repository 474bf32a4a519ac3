// The source tree's path, compiled into this file only (see source_dir.h).
#include "core/source_dir.h"

namespace mc {
const std::string& source_dir() {
  static const std::string dir = MOTIONCTL_SOURCE_DIR;
  return dir;
}
}  // namespace mc
