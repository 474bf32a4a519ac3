// Builds a fixture motion file from its job config: generate, compute
// normalisation statistics and vocabulary from the train split, write atomically.
#pragma once
#include <string>
#include <vector>

namespace mc {

struct FixtureBuildResult {
  std::string output;
  bool up_to_date = false;  // the file already held exactly this config
  size_t clips = 0;
  double seconds = 0;
};

FixtureBuildResult build_fixture(const std::string& config_file, const std::vector<std::string>& overrides, bool force);

}  // namespace mc
