// Where the source tree is (configs/, pretrained/, skeleton files resolved against
// it). One translation unit holds the path, so the compile flags of every other
// file are the same in every checkout and ccache/the precompiled header are
// shared across worktrees and clones.
#pragma once
#include <string>

namespace mc {
const std::string& source_dir();
}  // namespace mc
