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

// Run directories run_train has returned since the last call (distinct, in
// first-use order), and forgets them: lets the table replay record which trained
// components each row used.
std::vector<std::string> take_trained_runs();

}  // namespace mc
