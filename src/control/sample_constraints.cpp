// Per-sample constraint specs inside motion files: making source-derived targets
// explicit, and the /control group's writer and reader.
#include "control/sample_constraints.h"

#include <hdf5.h>

#include <algorithm>
#include <filesystem>

#include "control/linear_observation.h"
#include "core/error.h"
#include "core/h5_handle.h"
#include "core/h5_seal.h"
#include "core/isolated.h"

namespace mc {
namespace {

constexpr const char* kFormat = "motionctl.sample_constraints";
constexpr int64_t kFormatVersion = 1;

// Distinct values in order of first appearance.
struct Ordered {
  std::vector<int> values;
  void add(int v) {
    if (std::find(values.begin(), values.end(), v) == values.end()) values.push_back(v);
  }
  int size() const { return static_cast<int>(values.size()); }
};

}  // namespace

ConstraintSpec with_explicit_targets(const ConstraintSpec& spec, int frames, const Skeleton& skeleton,
                                     const float* source_motion) {
  LinearObservation obs = compile(spec, frames, skeleton, source_motion);
  const int J = skeleton.num_joints();
  ConstraintSpec out = spec;
  for (size_t i = 0; i < spec.items.size(); ++i) {
    ConstraintItem& it = out.items[i];
    if (!it.from_source && it.type != "upper_body_edit") continue;
    if (is_direction_type(it.type)) {  // the unit directions compile() measured on the source
      int F = 0, A = 0;
      it.values.data.clear();
      for (const auto& p : obs.directions) {
        if (p.item != static_cast<int>(i)) continue;
        ++F;
        A = static_cast<int>(p.target.size());
        for (Eigen::Index k = 0; k < p.target.size(); ++k) it.values.data.push_back(p.target[k]);
      }
      it.values.shape = {F, A};
      it.from_source = false;
      continue;
    }
    std::vector<int> rows;
    for (int r = 0; r < obs.rows(); ++r)
      if (obs.item_of_row[r] == static_cast<int>(i)) rows.push_back(r);
    // Each row's (frame, joint, axis) from its columns: column = (t * J + j) * 3 + c.
    Ordered ts, js, cs;
    for (int r : rows)
      for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator e(obs.A, r); e; ++e) {
        const int col = static_cast<int>(e.col());
        ts.add(col / 3 / J);
        if (it.type != "relative") js.add(col / 3 % J);
        if (it.type != "camera_2d") cs.add(col % 3);
      }
    std::vector<int> shape;
    if (it.type == "keyframe" || it.type == "trajectory" || it.type == "upper_body_edit") {
      shape = {ts.size(), js.size(), cs.size()};
    } else if (it.type == "camera_2d") {
      shape = {ts.size(), js.size(), 2};
    } else if (it.type == "planar_root") {
      shape = {ts.size(), 2};
    } else if (it.type == "relative") {
      shape = {ts.size(), cs.size()};
    } else {
      continue;  // loop: targets are zero, nothing comes from the source
    }
    size_t count = 1;
    for (int s : shape) count *= static_cast<size_t>(s);
    if (count != rows.size())  // a row layout this code does not know: a bug, not bad input
      throw std::logic_error(fmt::format("with_explicit_targets: {} has {} rows, not the {} its shape implies",
                                         spec.item_label(static_cast<int>(i)), rows.size(), count));
    it.values.shape = shape;
    it.values.data.clear();
    for (int r : rows) it.values.data.push_back(obs.y[r]);
    it.from_source = false;
    if (it.type == "upper_body_edit") {  // the same rows, written as a trajectory of the role's joints
      it.type = "trajectory";
      it.role.clear();
      it.joints.clear();
      for (int j : js.values) it.joints.push_back(JointRef{j, ""});
      it.frames.kind = FrameSelection::Kind::list;
      it.frames.list = ts.values;
      it.axes = cs.values;
    }
  }
  return out;
}

bool any_constraints(const std::vector<ConstraintSpec>& specs) {
  return std::any_of(specs.begin(), specs.end(), [](const ConstraintSpec& s) { return !s.items.empty(); });
}

void write_sample_constraints(int64_t file, const std::vector<ConstraintSpec>& specs, const std::vector<int>& frames,
                              const std::string& path) {
  if (frames.size() != specs.size())
    throw std::logic_error("write_sample_constraints: one frame count per spec is needed");
  QuietHdf5 quiet;
  // No modification times: the same samples give the same bytes.
  H5Handle gcpl{H5Pcreate(H5P_GROUP_CREATE), H5Pclose};
  H5Pset_obj_track_times(gcpl.get(), false);
  H5Handle dcpl{H5Pcreate(H5P_DATASET_CREATE), H5Pclose};
  H5Pset_obj_track_times(dcpl.get(), false);
  H5Handle g{H5Gcreate2(static_cast<hid_t>(file), "control", H5P_DEFAULT, gcpl.get(), H5P_DEFAULT), H5Gclose};
  if (g.get() < 0) fail("{}: cannot create group /control", path);
  {
    H5Handle space{H5Screate(H5S_SCALAR), H5Sclose};
    H5Handle str{H5Tcopy(H5T_C_S1), H5Tclose};
    H5Tset_size(str.get(), H5T_VARIABLE);
    H5Tset_cset(str.get(), H5T_CSET_UTF8);
    H5Handle a{H5Acreate2(g.get(), "format", str.get(), space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose};
    const char* f = kFormat;
    H5Awrite(a.get(), str.get(), &f);
    H5Handle v{H5Acreate2(g.get(), "format_version", H5T_STD_I64LE, space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose};
    H5Awrite(v.get(), H5T_NATIVE_INT64, &kFormatVersion);
    hsize_t n = frames.size();
    H5Handle s1{H5Screate_simple(1, &n, nullptr), H5Sclose};
    H5Handle ds{H5Dcreate2(g.get(), "frames", H5T_STD_I32LE, s1.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT), H5Dclose};
    if (ds.get() < 0 || (n > 0 && H5Dwrite(ds.get(), H5T_NATIVE_INT, H5S_ALL, H5S_ALL, H5P_DEFAULT, frames.data()) < 0))
      fail("{}: cannot write /control/frames", path);
  }
  for (size_t i = 0; i < specs.size(); ++i)
    write_constraint_spec_group(g.get(), fmt::format("sample_{:06d}", i), specs[i], path);
}

namespace {

SampleConstraints read_sample_constraints_unchecked(const std::string& path) {
  QuietHdf5 quiet;
  if (!std::filesystem::exists(path)) fail("{}: no such file", path);
  H5Handle file{H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose};
  if (file.get() < 0) fail("{}: not a readable HDF5 file", path);
  SampleConstraints out;
  if (H5Lexists(file.get(), "control", H5P_DEFAULT) <= 0) return out;
  H5Handle g{H5Gopen2(file.get(), "control", H5P_DEFAULT), H5Gclose};
  if (g.get() < 0) fail("{}: /control is not a group", path);
  if (H5Aexists(g.get(), "format_version") > 0) {
    H5Handle a{H5Aopen(g.get(), "format_version", H5P_DEFAULT), H5Aclose};
    int64_t version = 0;
    if (H5Aread(a.get(), H5T_NATIVE_INT64, &version) < 0 || version > kFormatVersion)
      fail("{}: /control has format_version {}, this build reads up to {}", path, version, kFormatVersion);
  }
  for (size_t i = 0;; ++i) {
    std::string name = fmt::format("sample_{:06d}", i);
    if (H5Lexists(g.get(), name.c_str(), H5P_DEFAULT) <= 0) break;
    out.specs.push_back(read_constraint_spec_group(g.get(), name, path));
    out.specs.back().source = fmt::format("{}:/control/{}", path, name);
  }
  if (H5Lexists(g.get(), "frames", H5P_DEFAULT) > 0) {
    H5Handle ds{H5Dopen2(g.get(), "frames", H5P_DEFAULT), H5Dclose};
    H5Handle space{ds.get() >= 0 ? H5Dget_space(ds.get()) : -1, H5Sclose};
    hsize_t n = 0;
    if (space.get() < 0 || H5Sget_simple_extent_ndims(space.get()) != 1 || H5Sget_simple_extent_dims(space.get(), &n, nullptr) < 0)
      fail("{}: /control/frames must be a 1-D integer dataset", path);
    out.frames.resize(n);
    if (n > 0 && H5Dread(ds.get(), H5T_NATIVE_INT, H5S_ALL, H5S_ALL, H5P_DEFAULT, out.frames.data()) < 0)
      fail("{}: /control/frames cannot be read as integers", path);
    if (out.frames.size() != out.specs.size())
      fail("{}: /control/frames has {} entries but /control holds {} sample groups (sample_000000, ...); give one "
           "frame count per sample",
           path, out.frames.size(), out.specs.size());
    for (size_t i = 0; i < n; ++i)
      if (out.frames[i] < 1) fail("{}: /control/frames[{}] is {}; frame counts must be >= 1", path, i, out.frames[i]);
  }
  return out;
}

}  // namespace

// Motion files carry a checksum seal (core/h5_seal.h); an unsealed file is read in
// a child process first so that libhdf5 crashing on damage cannot take us down.
SampleConstraints read_sample_constraints(const std::string& path) {
  if (std::filesystem::exists(path) && check_h5_seal(path, "motion file") == H5Seal::absent)
    isolated_probe(fmt::format("the constraints stored in '{}'", path), [&] { read_sample_constraints_unchecked(path); });
  return read_sample_constraints_unchecked(path);
}

}  // namespace mc
