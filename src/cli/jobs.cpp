// The job-kind table behind `motionctl config`.
#include "cli/jobs.h"

#include <yaml-cpp/yaml.h>

#include "cli/generate_job.h"
#include "cli/sample_job.h"
#include "core/error.h"
#include "cli/eval_job.h"
#include "eval/health.h"
#include "data/fixture/fixture.h"
#include "train/trainer.h"

namespace mc {

const std::vector<JobKind>& job_kinds() {
  static const std::vector<JobKind> kinds = {
      {"train", "model", [] { return std::make_unique<TrainJobConfig>(); }},
      {"fixture", "fixture", [] { return std::make_unique<FixtureJobConfig>(); }},
      {"sample", "sampler", [] { return std::make_unique<SampleJobConfig>(); }},
      {"generate", "generator", [] { return std::make_unique<GenerateJobConfig>(); }},
      {"eval", "protocol", [] { return std::make_unique<EvalJobConfig>(); }},
      {"health", "targets", [] { return std::make_unique<HealthOptions>(); }},
  };
  return kinds;
}

const JobKind& job_kind(const std::string& name) {
  std::vector<std::string> names;
  for (auto& k : job_kinds()) {
    if (k.name == name) return k;
    names.push_back(k.name);
  }
  std::string hint = did_you_mean(name, names);
  fail("unknown job kind '{}'{}; kinds: {}", name, hint.empty() ? "" : " (did you mean '" + hint + "'?)",
       fmt::format("{}", fmt::join(names, ", ")));
}

const JobKind& detect_job_kind(const ConfigSource& src) {
  for (auto& k : job_kinds())
    if ((*src.root)[k.marker_key]) return k;
  std::vector<std::string> markers;
  for (auto& k : job_kinds()) markers.push_back(fmt::format("'{}:' ({})", k.marker_key, k.name));
  fail("{}: cannot tell what kind of config this is: it has none of the top-level keys {}", src.main_file,
       fmt::format("{}", fmt::join(markers, ", ")));
}

}  // namespace mc
