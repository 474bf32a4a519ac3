// Up-front resource checks for a training job (issue 16): a model or batch that
// cannot fit in memory, or more threads than cores, is refused before any data is
// loaded or a run directory is claimed, with an estimate and the key to change.
#pragma once

namespace mc {

struct TrainJobConfig;

// UserError naming model.width / optim.batch_size / run.threads when the job
// cannot run on this machine. The memory estimate is a lower bound, so a job
// that fits is never refused.
void check_train_resources(TrainJobConfig& job);

}  // namespace mc
