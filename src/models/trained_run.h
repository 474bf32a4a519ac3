// One loader for the run directory of every trained component (flow prior, token
// priors, tokenizer, text encoder, ControlNet, anchor adapter, evaluator): the
// directory and the files a user needs exist, config.yaml's `model:` section has an
// accepted type, outputs/ files parse, final.pt loads into the module. Each
// component's own load() adds only what is particular to it. Loading never trains:
// a run named by its training config is found by the job layer first
// (core/trained_runs.h).
#pragma once
#include <algorithm>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include <torch/torch.h>
#include <yaml-cpp/yaml.h>

#include "core/config.h"

namespace mc {

// What a loader expects of a run directory.
struct TrainedRunSpec {
  std::string what;                  // e.g. "flow prior", in every message
  std::vector<std::string> types;    // accepted model.type values
  std::vector<std::string> outputs;  // files under outputs/ a user of the run needs
  // How to get such a run when the directory does not exist, e.g. "train one with
  // `motionctl train configs/prior/flow_tiny.yaml`".
  std::string how_to_train;
};

// A finished run directory, checked against its spec.
struct TrainedRun {
  std::filesystem::path dir;
  std::string name;                // the directory as the caller gave it (messages, *_run fields)
  std::string what;                // spec.what
  Component model{"model"};        // config.yaml's model section, parsed by type
  std::filesystem::path final_pt() const { return dir / "checkpoints" / "final.pt"; }
  std::filesystem::path output(const std::string& file) const { return dir / "outputs" / file; }
  // outputs/<file> as YAML; `read` pulls the values out, and a missing key or a
  // wrong type there is a UserError saying the file is corrupt.
  void read_meta(const std::string& file, const std::function<void(const YAML::Node&)>& read) const;
  // A dependency's run directory as this run recorded it in its outputs (where the
  // dependency was when this run trained, e.g. "runs/tokenizer/vq_tiny"). A run tree
  // moved or installed under another runs root (run.root) carries its dependencies
  // beside it: <this run's root>/<experiment>/<name> is used when it exists, the
  // recorded path otherwise (so the loader's error names what was recorded).
  std::string dependency(const std::string& recorded) const;
  // outputs/vocab.txt, one word a line.
  std::vector<std::string> vocab_words() const;
  // Reads final.pt (or `file`) into `module`; UserError naming the file when it is
  // unreadable or its tensors do not fit the module (`mismatch` says against what,
  // default "its config.yaml").
  void load_weights(torch::nn::Module& module, const std::string& mismatch = "its config.yaml") const;
  void load_weights_from(const std::filesystem::path& file, torch::nn::Module& module,
                         const std::string& mismatch = "its config.yaml") const;
};

// Module weights in a checkpoint stored at a lower precision (run.final_weights.dtype
// float16). Only parameters are lowered: buffers (normaliser statistics, a TMD's
// distance table checked against its tokenizer, counters) are data the run derived,
// not weights it learned, and stay as they are. `read_module_weights` loads an
// archive into `module` as Module::load does, converting a stored tensor of another
// floating dtype to the module tensor's (libtorch's Module::load would set_ a float32
// tensor onto float16 storage), so a half-precision final.pt loads as float32 holding
// the rounded values exactly. `round_module_weights` rounds the module's float32
// parameters in place to values `dtype` represents; UserError when one does not fit
// (|w| beyond float16's range). `save_module_weights` writes the module with its
// float32 parameters stored as `dtype` (the module is unchanged).
void read_module_weights(torch::serialize::InputArchive& ar, torch::nn::Module& module);
void round_module_weights(torch::nn::Module& module, torch::ScalarType dtype, const std::string& what);
void save_module_weights(torch::nn::Module& module, torch::ScalarType dtype, const std::filesystem::path& file);
// "float32" -> kFloat, "float16" -> kHalf (run.final_weights.dtype).
torch::ScalarType weights_dtype(const std::string& name);

// UserError naming the directory, the missing file or the foreign model type.
TrainedRun open_trained_run(const std::string& run_dir, const TrainedRunSpec& spec);

// The `model:` section of a run's (or any training) config file, parsed by type; the
// file's other sections (run, data, optim) are not read.
Component read_model_section(const std::string& config_file);

}  // namespace mc
