// Job kinds: which top-level config struct a command parses. `motionctl config`
// uses the marker key of a file (e.g. `model:` -> train) to pick the schema.
#pragma once
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"

namespace mc {

struct JobKind {
  std::string name;        // "train", "fixture", ...
  std::string marker_key;  // a top-level key only this kind has
  std::function<std::unique_ptr<Config>()> make;
};

const std::vector<JobKind>& job_kinds();
const JobKind& job_kind(const std::string& name);         // UserError with did-you-mean
const JobKind& detect_job_kind(const ConfigSource& src);  // UserError if no marker matches

}  // namespace mc
