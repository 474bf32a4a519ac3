// Opening a trained component's run directory: the checks every loader shares.
#include "models/trained_run.h"

#include <fstream>

#include <fmt/ranges.h>

#include "core/error.h"

namespace mc {

namespace {

// A config holding only the `model:` component.
struct ModelSection : Config {
  Component model{"model"};
  void visit(FieldVisitor& v) override { v("model", model, "the trained model (picked by type)"); }
};

}  // namespace

Component read_model_section(const std::string& config_file) {
  ConfigSource src = compose_config(config_file);
  // Only `model:` is read: a run's run/data/optim sections say how it was trained,
  // which no user of the trained weights needs.
  std::vector<std::string> others;
  if (src.root->IsMap())
    for (const auto& kv : *src.root)
      if (kv.first.as<std::string>() != "model") others.push_back(kv.first.as<std::string>());
  for (const auto& k : others) src.root->remove(k);
  if (!src.root->IsMap() || !(*src.root)["model"])
    fail("'{}' has no model: section; it is not the config.yaml of a training run", config_file);
  ModelSection s;
  parse_config(src, s);
  return s.model;
}

TrainedRun open_trained_run(const std::string& run_dir, const TrainedRunSpec& spec) {
  namespace fs = std::filesystem;
  TrainedRun r;
  r.dir = fs::path(run_dir);
  r.name = run_dir;
  r.what = spec.what;
  const std::string types = fmt::format("{}", fmt::join(spec.types, " or "));
  if (!fs::is_directory(r.dir))
    fail("{} run directory '{}' does not exist; {}", spec.what, run_dir,
         spec.how_to_train.empty() ? fmt::format("point at a finished {} run", types) : spec.how_to_train);
  std::vector<fs::path> needed = {r.dir / "config.yaml", r.final_pt()};
  for (const auto& o : spec.outputs) needed.push_back(r.output(o));
  for (const fs::path& p : needed)
    if (!fs::exists(p))
      fail("{} run '{}' is incomplete: '{}' is missing; finish it with `motionctl train {}/config.yaml` (or point at "
           "a finished {} run)",
           spec.what, run_dir, p.string(), run_dir, types);
  r.model = read_model_section((r.dir / "config.yaml").string());
  if (std::find(spec.types.begin(), spec.types.end(), r.model.type) == spec.types.end())
    fail("'{}' is a run of model type '{}', not {} {} ({})", run_dir, r.model.type,
         std::string("aeiou").find(spec.what.front()) == std::string::npos ? "a" : "an", spec.what, types);
  return r;
}

void TrainedRun::read_meta(const std::string& file, const std::function<void(const YAML::Node&)>& read) const {
  const std::string path = output(file).string();
  try {
    read(YAML::LoadFile(path));
  } catch (const YAML::Exception& e) {
    fail("'{}' is corrupt: {}", path, e.what());
  }
}

std::string TrainedRun::dependency(const std::string& recorded) const {
  namespace fs = std::filesystem;
  fs::path r = fs::path(recorded).lexically_normal();
  if (r.filename().empty()) r = r.parent_path();  // a trailing separator
  const fs::path beside = dir.parent_path().parent_path() / r.parent_path().filename() / r.filename();
  std::error_code ec;
  if (!r.parent_path().filename().empty() && fs::is_directory(beside, ec)) return beside.string();
  return recorded;
}

std::vector<std::string> TrainedRun::vocab_words() const {
  std::vector<std::string> words;
  std::ifstream f(output("vocab.txt"));
  for (std::string w; std::getline(f, w);) words.push_back(w);
  return words;
}

void TrainedRun::load_weights(torch::nn::Module& module, const std::string& mismatch) const {
  load_weights_from(final_pt(), module, mismatch);
}

void TrainedRun::load_weights_from(const std::filesystem::path& file, torch::nn::Module& module,
                                   const std::string& mismatch) const {
  std::string detail;
  try {
    torch::serialize::InputArchive ar;
    ar.load_from(file.string());
    read_module_weights(ar, module);
    return;
  } catch (const c10::Error& e) {
    detail = e.what_without_backtrace();
  } catch (const std::exception& e) {  // torch::jit::ErrorReport on a damaged file
    detail = e.what();
  }
  fail("{} checkpoint '{}' is unreadable or does not match {} ({})", what, file.string(), mismatch,
       detail.substr(0, 200));
}

torch::ScalarType weights_dtype(const std::string& name) {
  if (name == "float32") return torch::kFloat32;
  if (name == "float16") return torch::kFloat16;
  fail("run.final_weights.dtype '{}' is not float32 or float16", name);
}

void read_module_weights(torch::serialize::InputArchive& ar, torch::nn::Module& module) {
  // Module::load's own loop (parameters, then buffers, then each serializable child's
  // archive), with one difference: a stored tensor of another floating dtype is
  // converted to the module tensor's dtype first. Module::load would set_ a float32
  // tensor onto float16 storage (a corrupt view), not convert it.
  torch::NoGradGuard ng;
  auto take = [](torch::Tensor& t, torch::Tensor stored) {
    if (stored.scalar_type() != t.scalar_type() && at::isFloatingType(stored.scalar_type()) &&
        at::isFloatingType(t.scalar_type()))
      stored = stored.to(t.scalar_type());
    if (t.device() != stored.device())
      t.set_data(stored);
    else
      t.set_(stored);
  };
  for (auto& item : module.named_parameters(/*recurse=*/false)) {
    torch::Tensor stored;
    ar.read(item.key(), stored);
    take(item.value(), stored);
  }
  for (auto& item : module.named_buffers(/*recurse=*/false)) {
    torch::Tensor stored;
    ar.read(item.key(), stored, /*is_buffer=*/true);
    take(item.value(), stored);
  }
  for (auto& child : module.named_children()) {
    if (!child.value()->is_serializable()) continue;
    torch::serialize::InputArchive child_ar;
    ar.read(child.key(), child_ar);
    read_module_weights(child_ar, *child.value());
  }
}

void round_module_weights(torch::nn::Module& module, torch::ScalarType dtype, const std::string& what) {
  if (dtype == torch::kFloat32) return;
  torch::NoGradGuard ng;
  for (const auto& item : module.named_parameters(/*recurse=*/true)) {
    torch::Tensor t = item.value();
    if (t.scalar_type() != torch::kFloat32) continue;
    torch::Tensor r = t.detach().to(dtype);
    if (!torch::isfinite(r).all().item<bool>())
      fail("{}: the weight '{}' (largest |w| {:.6g}) does not fit in {}; train with run.final_weights.dtype=float32",
           what, item.key(), t.detach().abs().max().item<double>(), c10::toString(dtype));
    t.copy_(r);
  }
}

void save_module_weights(torch::nn::Module& module, torch::ScalarType dtype, const std::filesystem::path& file) {
  torch::NoGradGuard ng;
  // Each lowered parameter with its own float32 data, put back after the save.
  std::vector<std::pair<torch::Tensor, torch::Tensor>> lowered;
  auto restore = [&] {
    for (auto& [t, data] : lowered) t.set_data(data);
  };
  if (dtype != torch::kFloat32)
    for (auto& t : module.parameters(/*recurse=*/true))
      if (t.scalar_type() == torch::kFloat32) {
        lowered.emplace_back(t, t.detach());
        t.set_data(t.detach().to(dtype));
      }
  // The archive holds the tensors themselves, not copies: it is written before
  // they get their float32 data back.
  try {
    torch::serialize::OutputArchive ar;
    module.save(ar);
    ar.save_to(file.string());
  } catch (...) {
    restore();
    throw;
  }
  restore();
}

}  // namespace mc
