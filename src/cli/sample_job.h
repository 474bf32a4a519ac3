// The `motionctl sample` job config (marker key `sampler:`): which prior, which
// texts and lengths, sampler settings, output file.
#pragma once
#include <string>
#include <vector>

#include "core/config.h"
#include "samplers/flow_sampler.h"
#include "models/prior_source.h"

namespace mc {

struct SampleRunConfig : Config {
  int64_t seed = 0;
  int threads = 0;
  std::string device = "cpu";
  void visit(FieldVisitor& v) override {
    v("seed", seed, "seed of the initial noise (stored in the output's provenance)");
    v("threads", threads, "torch CPU threads; 0 = all cores", at_least(0));
    v("device", device, "torch device: cpu, cuda, cuda:N");
  }
};

struct SampleTextsConfig : Config {
  std::vector<std::string> prompts;
  std::vector<int> lengths;  // one per prompt, or one for all; empty = `length`
  int length = 120;
  std::string from_split;    // e.g. test: first caption and length of each clip of that split
  std::string data;          // motion file for from_split ('' = the prior's training data)
  int num_samples = 0;       // from_split: first N clips (0 = all)
  void visit(FieldVisitor& v) override {
    v("prompts", prompts, "captions to sample, one motion each (exclusive with from_split)");
    v("lengths", lengths, "frames per prompt: one value for all or one per prompt (empty = length)",
      each(at_least(1)));
    v("length", length, "frames of every prompt when lengths is empty", at_least(1));
    v("from_split", from_split, "take the first caption and length of each clip of this split of `data`");
    v("data", data, "motion file for from_split ('' = the prior's training data)");
    v("num_samples", num_samples, "from_split: use the first N clips (0 = all)", at_least(0));
  }
  std::string validate() const override {
    if (prompts.empty() == from_split.empty()) return "set exactly one of texts.prompts and texts.from_split";
    if (!lengths.empty() && lengths.size() != 1 && lengths.size() != prompts.size())
      return fmt::format("texts.lengths has {} values for {} prompts; give one, or one per prompt", lengths.size(),
                         prompts.size());
    return "";
  }
};

struct SampleJobConfig : Config {
  SampleRunConfig run;
  PriorSourceConfig prior;
  FlowSamplerConfig sampler;
  SampleTextsConfig texts;
  std::string output = "samples/sample.h5";
  void visit(FieldVisitor& v) override {
    v("run", run, "seed, threads, device");
    v("prior", prior, "the flow prior to sample from");
    v("sampler", sampler, "ODE sampler settings");
    v("texts", texts, "prompts and lengths");
    v("output", output, "motion HDF5 file to write (atomically)");
  }
  std::string validate() const override { return output.empty() ? "output must name a file" : ""; }
};

}  // namespace mc
