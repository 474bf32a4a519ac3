// A complete run directory of an untrained (random-weight) tiny flow prior, as
// training writes it: for sampler, generator and ControlNet tests that need a prior
// but not a good one. The one helper every test that writes such a run uses.
#pragma once
#include <yaml-cpp/yaml.h>

#include <string>
#include <vector>

#include "core/atomic_file.h"
#include "core/config.h"
#include "data/skeleton.h"
#include "models/flow_prior.h"
#include "train/trainer.h"

namespace mc::test {

inline const std::vector<std::string> kPriorWords = {"<pad>", "<unk>", "<sos>", "<eos>", "a",
                                                     "person", "walks", "jumps", "forward"};
// kPriorWords and the words of "a person walks number <i>" captions.
inline const std::vector<std::string> kPriorWordsWithNumbers = {
    "<pad>", "<unk>", "<sos>", "<eos>", "a", "person", "walks", "jumps", "forward", "number", "0", "1", "2", "3"};

// config.yaml, outputs/vocab.txt, outputs/prior_meta.yaml (HumanML3D skeleton, 20
// fps, `t_max`) and checkpoints/final.pt of a depth-2, width-64 prior with N(0,
// 0.1^2) weights drawn after torch::manual_seed(5) (with the kinematic head, its
// channel statistics drawn too). Another `model_type` writes a
// config.yaml of that type only (a foreign run for the loaders' errors).
// `model_extra` adds lines to the model section (e.g. "  prediction: clean\n").
inline void write_random_prior_run(const fs::path& dir, int t_max = 40, const std::string& model_type = "flow_prior",
                                   const std::vector<std::string>& words = kPriorWords,
                                   const std::string& model_extra = "") {
  TrainJobConfig job;
  parse_config(config_from_string("model:\n  type: flow_prior\n  depth: 2\n  width: 64\n  heads: 2\n"
                                  "  text_width: 32\n  text_heads: 4\n  text_ff: 64\n  text_layers: 1\n" +
                                  model_extra),
               job);
  std::string yaml = dump_config(job);
  if (model_type != "flow_prior") yaml = "model:\n  type: " + model_type + "\n";
  write_file_atomic(dir / "config.yaml", yaml);
  std::string vocab;
  for (auto& w : words) vocab += w + "\n";
  write_file_atomic(dir / "outputs" / "vocab.txt", vocab);
  YAML::Emitter e;
  e << YAML::BeginMap << YAML::Key << "fps" << YAML::Value << 20.0 << YAML::Key << "t_max" << YAML::Value << t_max
    << YAML::Key << "num_joints" << YAML::Value << 22 << YAML::Key << "data" << YAML::Value << ""
    << YAML::Key << "skeleton" << YAML::Value << YAML::Literal << skeleton_to_yaml(humanml3d_skeleton())
    << YAML::EndMap;
  write_file_atomic(dir / "outputs" / "prior_meta.yaml", std::string(e.c_str()) + "\n");
  torch::manual_seed(5);
  FlowPriorNet net(static_cast<int>(words.size()), 22, job.model.as<FlowPriorConfig>());
  {
    torch::NoGradGuard ng;
    for (auto& p : net->parameters()) p.normal_(0.0, 0.1);
    net->joint_mean.copy_(torch::tensor({0.0f, 0.9f, 0.1f}));
    net->joint_std.copy_(torch::tensor({0.5f, 0.4f, 0.8f}));
    if (net->kinematic_head) {  // statistics a unit map would hide: the decode must use both
      net->kin_mean.normal_(0.0, 0.1);
      net->kin_std.uniform_(0.05, 0.5);
    }
  }
  torch::serialize::OutputArchive ar;
  net->save(ar);
  fs::create_directories(dir / "checkpoints");
  ar.save_to((dir / "checkpoints" / "final.pt").string());
}

}  // namespace mc::test
