// Writing a flow prior's weights file (models/flow_weights.h; layout in
// docs/formats.md, "Flow prior weights") with HDF5's C API: no modification times in
// object headers, so two exports of one run are the same bytes.
#include "models/flow_weights.h"

#include <hdf5.h>

#include "core/atomic_file.h"
#include "core/config.h"
#include "core/error.h"
#include "core/h5_handle.h"
#include "core/h5_seal.h"
#include "data/skeleton.h"

namespace mc {
namespace {

class Writer {
 public:
  Writer(const std::string& tmp, std::string target) : target_(std::move(target)) {
    H5Handle fcpl(H5Pcreate(H5P_FILE_CREATE), H5Pclose);
    check(fcpl.valid() && H5Pset_obj_track_times(fcpl.get(), false) >= 0, "file creation properties");
    check(H5Pset_userblock(fcpl.get(), kH5SealBlock) >= 0, "the user block for the checksum");
    file_.reset(new H5Handle(H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, fcpl.get(), H5P_DEFAULT), H5Fclose));
    check(file_->valid(), "creating the file");
    str_.reset(new H5Handle(H5Tcopy(H5T_C_S1), H5Tclose));
    H5Tset_size(str_->get(), H5T_VARIABLE);
    H5Tset_cset(str_->get(), H5T_CSET_UTF8);
  }
  hid_t root() const { return file_->get(); }

  std::unique_ptr<H5Handle> group(hid_t parent, const std::string& name) {
    H5Handle gcpl(H5Pcreate(H5P_GROUP_CREATE), H5Pclose);
    H5Pset_obj_track_times(gcpl.get(), false);
    auto g = std::make_unique<H5Handle>(H5Gcreate2(parent, name.c_str(), H5P_DEFAULT, gcpl.get(), H5P_DEFAULT), H5Gclose);
    check(g->valid(), "group '" + name + "'");
    return g;
  }

  // A tensor in C order: float -> float32, int64, int32, bool -> uint8.
  void tensor(hid_t parent, const std::string& name, const torch::Tensor& t) {
    torch::Tensor c = t.detach().to(torch::kCPU).contiguous();
    hid_t file_type, mem_type;
    switch (c.scalar_type()) {
      case torch::kFloat32:
      case torch::kFloat64:
      case torch::kFloat16:
      case torch::kBFloat16:
        c = c.to(torch::kFloat32).contiguous();
        file_type = H5T_IEEE_F32LE;
        mem_type = H5T_NATIVE_FLOAT;
        break;
      case torch::kInt64:
        file_type = H5T_STD_I64LE;
        mem_type = H5T_NATIVE_INT64;
        break;
      case torch::kInt32:
        file_type = H5T_STD_I32LE;
        mem_type = H5T_NATIVE_INT32;
        break;
      case torch::kBool:
        c = c.to(torch::kUInt8).contiguous();
        file_type = H5T_STD_U8LE;
        mem_type = H5T_NATIVE_UINT8;
        break;
      default:
        throw std::logic_error(fmt::format("flow weights: tensor '{}' has an unsupported dtype", name));
    }
    std::vector<hsize_t> dims(c.sizes().begin(), c.sizes().end());
    // A 0-d tensor (none in today's bundle) is stored as a scalar dataspace.
    H5Handle space(dims.empty() ? H5Screate(H5S_SCALAR) : H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr),
                 H5Sclose);
    dataset(parent, name, file_type, mem_type, space.get(), c.numel() > 0 ? c.data_ptr() : nullptr);
  }

  void strings(hid_t parent, const std::string& name, const std::vector<std::string>& values) {
    std::vector<const char*> ptrs;
    for (auto& v : values) ptrs.push_back(v.c_str());
    hsize_t n = values.size();
    H5Handle space(H5Screate_simple(1, &n, nullptr), H5Sclose);
    dataset(parent, name, str_->get(), str_->get(), space.get(), n > 0 ? ptrs.data() : nullptr);
  }

  void attr_string(hid_t obj, const std::string& name, const std::string& value) {
    const char* p = value.c_str();
    attr(obj, name, str_->get(), str_->get(), &p);
  }
  void attr_int(hid_t obj, const std::string& name, int64_t value) {
    attr(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, &value);
  }
  void attr_double(hid_t obj, const std::string& name, double value) {
    attr(obj, name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, &value);
  }

  void close() { check(file_->close(), "closing (flushing) the file"); }

 private:
  void dataset(hid_t parent, const std::string& name, hid_t file_type, hid_t mem_type, hid_t space, const void* data) {
    H5Handle dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
    H5Pset_obj_track_times(dcpl.get(), false);
    H5Handle d(H5Dcreate2(parent, name.c_str(), file_type, space, H5P_DEFAULT, dcpl.get(), H5P_DEFAULT), H5Dclose);
    check(d.valid(), "dataset '" + name + "'");
    if (data) check(H5Dwrite(d.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) >= 0, "dataset '" + name + "'");
  }
  void attr(hid_t obj, const std::string& name, hid_t file_type, hid_t mem_type, const void* value) {
    H5Handle space(H5Screate(H5S_SCALAR), H5Sclose);
    H5Handle a(H5Acreate2(obj, name.c_str(), file_type, space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
    check(a.valid() && H5Awrite(a.get(), mem_type, value) >= 0, "attribute '" + name + "'");
  }
  void check(bool ok, const std::string& what) {
    if (!ok)
      fail("cannot write weights file '{}': HDF5 failed writing {} (is the disk full or the folder read-only?)", target_,
           what);
  }

  std::string target_;
  std::unique_ptr<H5Handle> file_, str_;
};

}  // namespace

std::vector<std::pair<std::string, torch::Tensor>> flow_weight_tensors(const FlowPrior& prior) {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  auto& net = *prior.net();
  for (const auto& kv : net.named_parameters(true)) out.emplace_back(kv.key(), kv.value().detach().to(torch::kCPU, torch::kFloat32));
  for (const auto& kv : net.named_buffers(true)) out.emplace_back(kv.key(), kv.value().detach().to(torch::kCPU, torch::kFloat32));
  return out;
}

void write_flow_weights(const FlowPrior& prior, const FlowWeightsSource& source, const std::string& path,
                        const std::vector<FlowWeightsGroup>& extra) {
  const auto weights = flow_weight_tensors(prior);
  for (const auto& [name, t] : weights)
    if (!torch::isfinite(t).all().item<bool>())
      fail("flow prior '{}': weight '{}' is not finite; the checkpoint is broken or diverged — retrain it before "
           "exporting",
           source.run_dir, name);
  const FlowPriorNetImpl& net = *prior.net();
  // The skip (model.kinematic_head.skip) has no description in format version 2 and
  // tools/flow_reference.py does not compute it: refuse rather than write a file that
  // decodes to another prior.
  if (net.kinematic_skip)
    fail("flow prior '{}': model.kinematic_head.skip.enabled is not part of the weights format (version {}); "
         "export a prior without the skip, or use the run directory itself",
         source.run_dir, kFlowWeightsVersion);
  if (net.kinematic_bones)
    fail("flow prior '{}': model.kinematic_head.bones is not part of the weights format (version {}); export a "
         "prior without it, or use the run directory itself",
         source.run_dir, kFlowWeightsVersion);
  const FlowTransformerOptions& o = net.transformer->opt;
  const FlowPriorConfig& c = prior.config();
  FlowPriorConfig dumped = c;
  const std::string model_yaml = "type: flow_prior\n" + dump_config(dumped);

  AtomicOutput out(path);
  {
    QuietHdf5 quiet;
    Writer w(out.tmp_path().string(), path);
    const hid_t root = w.root();
    w.attr_string(root, "format", kFlowWeightsFormat);
    w.attr_int(root, "format_version", kFlowWeightsVersion);
    w.attr_string(root, "model_type", "flow_prior");
    w.attr_string(root, "motionctl_version", MOTIONCTL_VERSION);
    w.attr_string(root, "run_dir", source.run_dir);
    w.attr_string(root, "config_hash", source.config_hash);
    w.attr_string(root, "config", source.config_yaml);
    w.attr_string(root, "model_config", model_yaml);
    w.attr_int(root, "num_joints", prior.num_joints());
    w.attr_double(root, "fps", prior.fps());
    w.attr_int(root, "t_max", prior.t_max());
    {
      auto g = w.group(root, "weights");
      for (const auto& [name, t] : weights) w.tensor(g->get(), name, t);
    }
    {
      // The architecture as the network was built (defaults resolved, including the
      // constants the config does not expose), so a loader needs no YAML parser.
      auto g = w.group(root, "model");
      const hid_t m = g->get();
      w.attr_int(m, "num_joints", o.num_joints);
      w.attr_int(m, "depth", o.depth);
      w.attr_int(m, "width", o.width);
      w.attr_int(m, "heads", o.heads);
      w.attr_int(m, "head_dim", o.width / o.heads);
      w.attr_int(m, "mlp_hidden", o.resolved_mlp_hidden());
      w.attr_int(m, "cond_dim", o.cond_dim);
      w.attr_int(m, "freq_dim", o.freq_dim);
      w.attr_double(m, "time_scale", o.time_scale);
      w.attr_double(m, "rope_base", o.rope_base);
      w.attr_int(m, "temporal_kernel", o.temporal_kernel);
      w.attr_double(m, "rms_eps", net.transformer->final_norm->eps);
      w.attr_string(m, "prediction", c.prediction);
      w.attr_double(m, "clean_gap_floor", 1e-6);  // FlowPriorNetImpl::to_velocity's clamp of 1 - t
      w.attr_int(m, "vocab_size", prior.vocab().size());
      w.attr_int(m, "text_width", c.text_width);
      w.attr_int(m, "text_layers", c.text_layers);
      w.attr_int(m, "text_heads", c.text_heads);
      w.attr_int(m, "text_ff", c.text_ff);
      w.attr_int(m, "max_words", c.max_words);
      w.attr_string(m, "text_activation", "gelu");
      w.attr_string(m, "text_norm", "post");
      w.attr_double(m, "layer_norm_eps", 1e-5);  // torch's LayerNorm default, every LayerNorm of the bundle
      w.attr_int(m, "text_adapter", net.text_adapter ? 1 : 0);
      // Version 2: the kinematic head (models/kinematic_head.h). With it the head
      // writes out_channels kinematic channels per frame (/weights/kin_mean, kin_std
      // de-z-score them) that a fixed linear map decodes to joints; with its noise
      // the source noise is drawn in those channels (docs/formats.md).
      w.attr_int(m, "kinematic_head", net.kinematic_head ? 1 : 0);
      w.attr_int(m, "kinematic_noise", net.kinematic_noise ? 1 : 0);
      w.attr_int(m, "out_channels", o.resolved_out_channels());
    }
    w.strings(root, "vocab", prior.vocab().words());
    {
      const Skeleton& s = prior.skeleton();
      auto g = w.group(root, "skeleton");
      w.attr_string(g->get(), "yaml", skeleton_to_yaml(s));
      w.strings(g->get(), "names", s.joint_names);
      w.tensor(g->get(), "parents", torch::tensor(std::vector<int32_t>(s.parents.begin(), s.parents.end()), torch::kInt32));
    }
    for (const auto& e : extra) {
      auto g = w.group(root, e.name);
      for (const auto& [name, t] : e.arrays) w.tensor(g->get(), name, t);
      for (const auto& [name, v] : e.strings) w.strings(g->get(), name, v);
      for (const auto& [name, v] : e.numbers) w.attr_double(g->get(), name, v);
      for (const auto& [name, v] : e.texts) w.attr_string(g->get(), name, v);
    }
    w.close();
  }
  seal_h5_file(out.tmp_path().string(), fmt::format("weights file '{}'", path));
  out.commit();
}

}  // namespace mc
