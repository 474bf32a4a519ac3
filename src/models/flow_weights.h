// A trained flow prior's weights as an HDF5 file for use outside motionctl
// (`motionctl export --format weights`, docs/formats.md "Flow prior weights"):
// every parameter and buffer of the network the sampler runs, under its torch
// module path, with the resolved architecture, vocabulary, skeleton and config a
// loader needs (tools/flow_reference.py is the numpy reference loader). Written
// atomically, byte-deterministic, sealed like a motion file (core/h5_seal.h).
#pragma once
#include <string>
#include <utility>
#include <vector>

#include <torch/torch.h>

#include "models/flow_prior.h"

namespace mc {

inline constexpr const char* kFlowWeightsFormat = "motionctl.flow_weights";
// 2: /model gains kinematic_head, kinematic_noise and out_channels (a version-1 file has
// none of them: its head writes num_joints * 3 channels).
inline constexpr int64_t kFlowWeightsVersion = 2;

// Where the weights came from (root attributes of the file).
struct FlowWeightsSource {
  std::string run_dir;      // the run directory as given
  std::string config_yaml;  // its config.yaml (the resolved training config)
  std::string config_hash;  // the run's identity hash (the suffix of its default name)
};

// A group of extra arrays and attributes written in the same atomic write, e.g.
// the /probe group of samplers/flow_probe.h. Tensors are stored in C order as
// float32 (float tensors), int64, int32 or uint8 (bool tensors).
struct FlowWeightsGroup {
  std::string name;
  std::vector<std::pair<std::string, torch::Tensor>> arrays;
  std::vector<std::pair<std::string, std::vector<std::string>>> strings;  // UTF-8 string datasets
  std::vector<std::pair<std::string, double>> numbers;                    // float64 attributes
  std::vector<std::pair<std::string, std::string>> texts;                 // string attributes
};

// The names and tensors written under /weights: the bundle's parameters then its
// buffers (torch's named_parameters / named_buffers, recursive), as float32 on
// the CPU. FlowPrior::load reads checkpoints/final.pt, which holds the EMA
// weights when the run kept an EMA, so these are the weights the sampler uses.
std::vector<std::pair<std::string, torch::Tensor>> flow_weight_tensors(const FlowPrior& prior);

// Writes `path` atomically (a temporary sibling renamed into place, sealed).
// UserError naming the tensor when a weight is not finite (a broken checkpoint is
// not exported) and naming the file when HDF5 cannot write it.
void write_flow_weights(const FlowPrior& prior, const FlowWeightsSource& source, const std::string& path,
                        const std::vector<FlowWeightsGroup>& extra = {});

}  // namespace mc
