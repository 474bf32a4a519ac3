// run_train: a training config run the way `motionctl train` runs it, for every
// command, generator and experiment that needs a trained component on demand.
#include "train/train_job.h"

#include <filesystem>

#include "core/error.h"
#include "data/fixture/fixture_build.h"

namespace mc {
namespace fs = std::filesystem;

static std::string stem_of(const std::string& file) { return fs::path(file).stem().string(); }

// Builds the training data from its fixture config when the file is missing.
static void ensure_training_data(const TrainJobConfig& job) {
  if (fs::exists(resolve_data_path(job.data.path))) return;
  if (job.data.fixture.empty())
    fail("data.path '{}' does not exist and data.fixture is empty; build it with `motionctl fixture` or point "
         "data.path at a motion file",
         job.data.path);
  build_fixture(resolve_data_path(job.data.fixture), {fmt::format("output={}", job.data.path)}, false);
}

TrainResult run_train(const std::string& file, const std::vector<std::string>& overrides, int64_t stop_after) {
  auto job = load_job<TrainJobConfig>(file, overrides);
  ensure_training_data(job);
  std::string name = fmt::format("{}-{}", stem_of(file), config_hash(job));
  return train(job, overrides, name, stop_after);
}

}  // namespace mc
