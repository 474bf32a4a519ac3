// Training a job config the way `motionctl train` does (builds missing fixture
// data, names the run <config stem>-<hash>): shared by train, sweep and sample.
#pragma once
#include <string>
#include <vector>

#include "train/trainer.h"

namespace mc {

TrainResult run_train(const std::string& file, const std::vector<std::string>& overrides, int64_t stop_after = 0);

}  // namespace mc
