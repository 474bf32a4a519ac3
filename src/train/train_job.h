// Running a training config the way `motionctl train` does: build missing data,
// name the run <config stem>-<hash>, train or resume or skip. Other commands use
// it to get a trained component (evaluator, prior, tokenizer) on demand.
#pragma once
#include <string>
#include <vector>

#include "train/trainer.h"

namespace mc {

TrainResult run_train(const std::string& config_file, const std::vector<std::string>& overrides,
                      int64_t stop_after = 0);

}  // namespace mc
