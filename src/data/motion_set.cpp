// MotionSet bookkeeping and the HDF5 motion file (docs/formats.md): an atomic,
// byte-deterministic writer and a reader that turns every defect into a UserError.
#include "data/motion_set.h"
#include "data/motion_file_extra.h"

#include <hdf5.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <set>
#include <stdexcept>
#include <unordered_map>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_handle.h"
#include "core/h5_seal.h"
#include "core/isolated.h"
#include "core/resources.h"
#include "data/text_vocab.h"

namespace mc {
namespace {

namespace fs = std::filesystem;

constexpr const char* kFormatName = "motionctl.motion";
constexpr int64_t kFormatVersion = 1;
constexpr int kJointsGzipLevel = 4;
const std::set<std::string> kSplits = {"train", "val", "test", "sample"};

std::string join_dims(const std::vector<hsize_t>& dims) {
  std::string s = "[";
  for (size_t i = 0; i < dims.size(); ++i) s += (i ? ", " : "") + std::to_string(dims[i]);
  return s + "]";
}

// The innermost HDF5 error description (e.g. "truncated file: eof = 1024, ..."),
// which is the one that tells a user what is wrong with the file.
std::string hdf5_error_text() {
  std::string text;
  H5Ewalk2(
      H5E_DEFAULT, H5E_WALK_DOWNWARD,
      [](unsigned, const H5E_error2_t* e, void* out) -> herr_t {
        if (e->desc && *e->desc) *static_cast<std::string*>(out) = e->desc;
        return 0;
      },
      &text);
  H5Eclear2(H5E_DEFAULT);
  return text.empty() ? "unknown HDF5 error" : text;
}

H5Handle utf8_string_type() {
  H5Handle t(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(t.get(), H5T_VARIABLE);
  H5Tset_cset(t.get(), H5T_CSET_UTF8);
  return t;
}

// ---------------------------------------------------------------- writing

class Writer {
 public:
  Writer(const fs::path& tmp, std::string target) : target_(std::move(target)) {
    // Modification times in object headers would make two writes of the same
    // set differ; the only time in the file is provenance.created.
    H5Handle fcpl(H5Pcreate(H5P_FILE_CREATE), H5Pclose);
    check(fcpl.valid() && H5Pset_obj_track_times(fcpl.get(), false) >= 0, "file creation properties");
    // The user block holds the checksum seal (core/h5_seal.h), written after closing.
    check(H5Pset_userblock(fcpl.get(), kH5SealBlock) >= 0, "the user block for the checksum");
    file_ = H5Handle(H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, fcpl.get(), H5P_DEFAULT), H5Fclose);
    check(file_.valid(), "creating the file");
    str_ = utf8_string_type();
  }

  hid_t root() const { return file_.get(); }

  H5Handle group(hid_t parent, const char* name) {
    H5Handle gcpl(H5Pcreate(H5P_GROUP_CREATE), H5Pclose);
    H5Pset_obj_track_times(gcpl.get(), false);
    H5Handle g(H5Gcreate2(parent, name, H5P_DEFAULT, gcpl.get(), H5P_DEFAULT), H5Gclose);
    check(g.valid(), std::string("group '") + name + "'");
    return g;
  }

  void strings(hid_t parent, const char* name, const std::vector<std::string>& values) {
    std::vector<const char*> ptrs;
    ptrs.reserve(values.size());
    for (auto& v : values) ptrs.push_back(v.c_str());
    dataset(parent, name, str_.get(), str_.get(), {values.size()}, ptrs.data());
  }

  // Numeric dataset: `file_type` is the on-disk type (little-endian, fixed width),
  // `mem_type` the native one of `data`.
  void dataset(hid_t parent, const char* name, hid_t file_type, hid_t mem_type, const std::vector<hsize_t>& dims,
               const void* data, const std::vector<hsize_t>& chunk = {}, int gzip = 0) {
    H5Handle space(H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr), H5Sclose);
    H5Handle dcpl(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
    H5Pset_obj_track_times(dcpl.get(), false);
    if (!chunk.empty()) {
      check(H5Pset_chunk(dcpl.get(), static_cast<int>(chunk.size()), chunk.data()) >= 0, std::string(name) + " chunks");
      if (gzip > 0) check(H5Pset_deflate(dcpl.get(), gzip) >= 0, std::string(name) + " gzip filter");
    }
    H5Handle d(H5Dcreate2(parent, name, file_type, space.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT), H5Dclose);
    check(d.valid(), std::string("dataset '") + name + "'");
    hsize_t count = 1;
    for (auto n : dims) count *= n;
    if (count > 0) check(H5Dwrite(d.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) >= 0,
                         std::string("dataset '") + name + "'");
  }

  void attr_string(hid_t obj, const char* name, const std::string& value) {
    const char* p = value.c_str();
    attr(obj, name, str_.get(), str_.get(), &p);
  }
  void attr_int(hid_t obj, const char* name, int64_t value) {
    attr(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, &value);
  }
  void attr_double(hid_t obj, const char* name, double value) {
    attr(obj, name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, &value);
  }

  void close() { check(file_.close(), "closing (flushing) the file"); }

 private:
  void attr(hid_t obj, const char* name, hid_t file_type, hid_t mem_type, const void* value) {
    H5Handle space(H5Screate(H5S_SCALAR), H5Sclose);
    H5Handle a(H5Acreate2(obj, name, file_type, space.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
    check(a.valid() && H5Awrite(a.get(), mem_type, value) >= 0, std::string("attribute '") + name + "'");
  }
  void check(bool ok, const std::string& what) {
    if (!ok)
      fail("cannot write motion file '{}': HDF5 failed writing {}: {} (is the disk full or the directory read-only?)",
           target_, what, hdf5_error_text());
  }

  std::string target_;
  H5Handle file_, str_;
};

// ---------------------------------------------------------------- reading

class Reader {
 public:
  Reader(hid_t file, std::string path) : file_(file), path_(std::move(path)) {
    std::error_code ec;
    file_size_ = fs::file_size(path_, ec);
  }

  // A damaged shape can claim petabytes; refuse what the file cannot hold before
  // allocating for it. gzip expands at most ~1032x, so 1100x the file size bounds
  // any dataset an intact file holds.
  void check_size(const std::string& name, const std::vector<hsize_t>& dims, size_t elem_bytes) const {
    long double bytes = elem_bytes;
    for (auto n : dims) bytes *= static_cast<long double>(n);
    if (bytes > 1100.0L * static_cast<long double>(file_size_) + (1 << 20))
      bad(fmt::format("dataset '{}' has shape {} ({:.3g} GB in memory), more than a {}-byte file can hold", name,
                      join_dims(dims), static_cast<double>(bytes / 1e9), file_size_),
          kCorrupt);
    // A shape a (compressed) file can hold may still be more than this machine has:
    // the only size `score` and `export` are given is their file's (core/resources.h).
    require_memory(bytes, fmt::format("reading '{}'", path_),
                   fmt::format("its dataset '{}' has shape {}", name, join_dims(dims)),
                   "read a smaller file (fewer clips per file), or use a machine with more memory");
  }

  // True when every component of the slash-separated `name` exists.
  bool exists(const std::string& name) const {
    size_t pos = 0;
    while (true) {
      size_t slash = name.find('/', pos);
      std::string prefix = name.substr(0, slash);
      if (H5Lexists(file_, prefix.c_str(), H5P_DEFAULT) <= 0) return false;
      if (slash == std::string::npos) return true;
      pos = slash + 1;
    }
  }

  bool has_attr(const std::string& obj, const char* name) const {
    return H5Aexists_by_name(file_, obj.c_str(), name, H5P_DEFAULT) > 0;
  }

  [[noreturn]] void bad(const std::string& what, const std::string& fix) const {
    fail("motion file '{}': {}; {}", path_, what, fix);
  }

  H5Handle open_dataset(const std::string& name) const {
    if (!exists(name))
      bad(fmt::format("dataset '{}' is missing", name),
          "the file is not a complete motionctl motion file (docs/formats.md); re-create it");
    H5Handle d(H5Dopen2(file_, name.c_str(), H5P_DEFAULT), H5Dclose);
    if (!d.valid())
      bad(fmt::format("cannot open dataset '{}': {}", name, hdf5_error_text()), "the file is corrupt; re-create it");
    return d;
  }

  std::vector<hsize_t> shape(hid_t d, const std::string& name) const {
    H5Handle space(H5Dget_space(d), H5Sclose);
    int rank = space.valid() ? H5Sget_simple_extent_ndims(space.get()) : -1;
    if (rank < 0) bad(fmt::format("cannot read the shape of dataset '{}': {}", name, hdf5_error_text()), kCorrupt);
    std::vector<hsize_t> dims(rank);
    H5Sget_simple_extent_dims(space.get(), dims.data(), nullptr);
    return dims;
  }

  // Reads a numeric dataset of class `cls` converting to `mem_type`; checks the
  // rank and every entry of `expected` that is >= 0.
  template <class T>
  std::vector<T> numeric(const std::string& name, H5T_class_t cls, hid_t mem_type,
                         const std::vector<long long>& expected, std::vector<hsize_t>* dims_out = nullptr) const {
    H5Handle d = open_dataset(name);
    expect_class(d.get(), name, cls);
    auto dims = shape(d.get(), name);
    expect_shape(name, dims, expected);
    check_size(name, dims, sizeof(T));
    size_t count = 1;
    for (auto n : dims) count *= n;
    std::vector<T> out(count);
    if (count > 0 && H5Dread(d.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, out.data()) < 0)
      bad(fmt::format("cannot read dataset '{}': {}", name, hdf5_error_text()), kCorrupt);
    if (dims_out) *dims_out = dims;
    return out;
  }

  // Reads a 1-D string dataset, variable-length (what we and h5py write) or fixed-length.
  std::vector<std::string> strings(const std::string& name, long long expected_n) const {
    H5Handle d = open_dataset(name);
    expect_class(d.get(), name, H5T_STRING);
    auto dims = shape(d.get(), name);
    expect_shape(name, dims, {expected_n});
    check_size(name, dims, sizeof(std::string) + sizeof(char*));
    H5Handle ftype(H5Dget_type(d.get()), H5Tclose);
    std::vector<std::string> out(dims[0]);
    if (dims[0] == 0) return out;
    if (H5Tis_variable_str(ftype.get()) > 0) {
      H5Handle mtype = utf8_string_type();
      std::vector<char*> ptrs(dims[0], nullptr);
      if (H5Dread(d.get(), mtype.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, ptrs.data()) < 0)
        bad(fmt::format("cannot read dataset '{}': {}", name, hdf5_error_text()), kCorrupt);
      for (size_t i = 0; i < ptrs.size(); ++i) out[i] = ptrs[i] ? ptrs[i] : "";
      H5Handle space(H5Dget_space(d.get()), H5Sclose);
      H5Dvlen_reclaim(mtype.get(), space.get(), H5P_DEFAULT, ptrs.data());
    } else {
      size_t width = H5Tget_size(ftype.get());
      check_size(name, dims, width);
      H5Handle mtype(H5Tcopy(H5T_C_S1), H5Tclose);
      H5Tset_size(mtype.get(), width);
      H5Tset_strpad(mtype.get(), H5T_STR_NULLPAD);
      std::vector<char> buf(width * dims[0]);
      if (H5Dread(d.get(), mtype.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, buf.data()) < 0)
        bad(fmt::format("cannot read dataset '{}': {}", name, hdf5_error_text()), kCorrupt);
      for (size_t i = 0; i < out.size(); ++i) {
        const char* s = buf.data() + i * width;
        out[i] = std::string(s, strnlen(s, width));
      }
    }
    return out;
  }

  std::string attr_string(const std::string& obj, const char* name) const {
    H5Handle a = open_attr(obj, name, H5T_STRING);
    H5Handle ftype(H5Aget_type(a.get()), H5Tclose);
    if (H5Tis_variable_str(ftype.get()) > 0) {
      H5Handle mtype = utf8_string_type();
      char* p = nullptr;
      if (H5Aread(a.get(), mtype.get(), &p) < 0) bad(attr_label(obj, name) + " cannot be read", kCorrupt);
      std::string s = p ? p : "";
      H5free_memory(p);
      return s;
    }
    size_t width = H5Tget_size(ftype.get());
    if (width > file_size_)
      bad(fmt::format("{} claims {} bytes, more than the file holds", attr_label(obj, name), width), kCorrupt);
    std::vector<char> buf(width + 1, '\0');
    H5Handle mtype(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(mtype.get(), width);
    if (H5Aread(a.get(), mtype.get(), buf.data()) < 0) bad(attr_label(obj, name) + " cannot be read", kCorrupt);
    return std::string(buf.data(), strnlen(buf.data(), width));
  }

  int64_t attr_int(const std::string& obj, const char* name) const {
    H5Handle a = open_attr(obj, name, H5T_INTEGER);
    int64_t v = 0;
    if (H5Aread(a.get(), H5T_NATIVE_INT64, &v) < 0) bad(attr_label(obj, name) + " cannot be read", kCorrupt);
    return v;
  }

  double attr_double(const std::string& obj, const char* name) const {
    H5Handle a = open_attr(obj, name, H5T_FLOAT);
    double v = 0;
    if (H5Aread(a.get(), H5T_NATIVE_DOUBLE, &v) < 0) bad(attr_label(obj, name) + " cannot be read", kCorrupt);
    return v;
  }

  static constexpr const char* kCorrupt = "the file is damaged or truncated; re-create it";

 private:
  static std::string attr_label(const std::string& obj, const char* name) {
    return obj == "/" ? fmt::format("attribute '{}'", name) : fmt::format("attribute '{}' of '{}'", name, obj);
  }

  H5Handle open_attr(const std::string& obj, const char* name, H5T_class_t cls) const {
    if (!has_attr(obj, name))
      bad(attr_label(obj, name) + " is missing", "the file is not a complete motionctl motion file (docs/formats.md)");
    H5Handle a(H5Aopen_by_name(file_, obj.c_str(), name, H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
    if (!a.valid()) bad(attr_label(obj, name) + " cannot be opened: " + hdf5_error_text(), kCorrupt);
    H5Handle space(H5Aget_space(a.get()), H5Sclose);
    if (H5Sget_simple_extent_npoints(space.get()) != 1) bad(attr_label(obj, name) + " must be a single value", kFix);
    H5Handle t(H5Aget_type(a.get()), H5Tclose);
    if (H5Tget_class(t.get()) != cls)
      bad(fmt::format("{} has the wrong type (expected {})", attr_label(obj, name), class_name(cls)), kFix);
    return a;
  }

  void expect_class(hid_t d, const std::string& name, H5T_class_t cls) const {
    H5Handle t(H5Dget_type(d), H5Tclose);
    if (H5Tget_class(t.get()) != cls)
      bad(fmt::format("dataset '{}' holds the wrong type (expected {})", name, class_name(cls)), kFix);
  }

  void expect_shape(const std::string& name, const std::vector<hsize_t>& dims,
                    const std::vector<long long>& expected) const {
    bool ok = dims.size() == expected.size();
    for (size_t i = 0; ok && i < dims.size(); ++i)
      ok = expected[i] < 0 || dims[i] == static_cast<hsize_t>(expected[i]);
    if (ok) return;
    std::string want = "[";
    for (size_t i = 0; i < expected.size(); ++i)
      want += (i ? ", " : "") + (expected[i] < 0 ? std::string("*") : std::to_string(expected[i]));
    bad(fmt::format("dataset '{}' has shape {} but {} was expected", name, join_dims(dims), want + "]"), kFix);
  }

  static const char* class_name(H5T_class_t cls) {
    switch (cls) {
      case H5T_INTEGER: return "integers";
      case H5T_FLOAT: return "floating point";
      case H5T_STRING: return "strings";
      default: return "another type";
    }
  }

  static constexpr const char* kFix = "see docs/formats.md for the motion file layout and re-export the file";
  hid_t file_;
  std::string path_;
  uintmax_t file_size_ = 0;
};

void write_skeleton(Writer& w, const Skeleton& s) {
  H5Handle g = w.group(w.root(), "skeleton");
  const auto J = static_cast<hsize_t>(s.num_joints());
  w.strings(g.get(), "names", s.joint_names);
  w.dataset(g.get(), "parents", H5T_STD_I32LE, H5T_NATIVE_INT, {J}, s.parents.data());
  std::vector<double> dirs(J * 3);
  for (hsize_t j = 0; j < J; ++j)
    for (int a = 0; a < 3; ++a) dirs[j * 3 + a] = s.rest_directions[j][a];
  w.dataset(g.get(), "rest_directions", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, {J, 3}, dirs.data());
  w.dataset(g.get(), "bone_lengths", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, {J}, s.bone_lengths.data());
  w.attr_string(g.get(), "name", s.name);
  w.attr_string(g.get(), "yaml", skeleton_to_yaml(s));
}

// The yaml attribute carries chains and roles, so it wins; the datasets are the
// h5py-friendly copy and must agree with it.
Skeleton read_skeleton(const Reader& r, const std::string& path) {
  const bool has_yaml = r.exists("skeleton") && r.has_attr("skeleton", "yaml");
  Skeleton s;
  if (has_yaml) {
    s = skeleton_from_yaml_text(r.attr_string("skeleton", "yaml"),
                                fmt::format("motion file '{}' attribute 'yaml' of 'skeleton'", path));
    if (r.exists("skeleton/names") && r.strings("skeleton/names", -1) != s.joint_names)
      r.bad("dataset 'skeleton/names' disagrees with attribute 'yaml' of 'skeleton'",
            "the two copies of the skeleton must match; re-export the file");
    if (r.exists("skeleton/parents") &&
        r.numeric<int>("skeleton/parents", H5T_INTEGER, H5T_NATIVE_INT, {-1}) != s.parents)
      r.bad("dataset 'skeleton/parents' disagrees with attribute 'yaml' of 'skeleton'",
            "the two copies of the skeleton must match; re-export the file");
    return s;
  }
  s.joint_names = r.strings("skeleton/names", -1);
  const auto J = static_cast<long long>(s.joint_names.size());
  s.parents = r.numeric<int>("skeleton/parents", H5T_INTEGER, H5T_NATIVE_INT, {J});
  auto dirs = r.numeric<double>("skeleton/rest_directions", H5T_FLOAT, H5T_NATIVE_DOUBLE, {J, 3});
  for (long long j = 0; j < J; ++j) s.rest_directions.emplace_back(dirs[j * 3], dirs[j * 3 + 1], dirs[j * 3 + 2]);
  s.bone_lengths = r.numeric<double>("skeleton/bone_lengths", H5T_FLOAT, H5T_NATIVE_DOUBLE, {J});
  s.name = r.has_attr("skeleton", "name") ? r.attr_string("skeleton", "name") : "unnamed";
  s.validate(fmt::format("motion file '{}' group 'skeleton'", path));
  return s;
}

bool all_finite(const std::vector<float>& v) {
  for (float x : v)
    if (!std::isfinite(x)) return false;
  return true;
}

}  // namespace

// ---------------------------------------------------------------- MotionSet

std::vector<size_t> MotionSet::indices_of_split(const std::string& split) const {
  std::vector<size_t> idx;
  for (size_t i = 0; i < splits.size(); ++i)
    if (splits[i] == split) idx.push_back(i);
  return idx;
}

MotionSet MotionSet::subset(const std::vector<size_t>& idx) const {
  MotionSet out;
  out.skeleton = skeleton;
  out.fps = fps;
  out.t_max = t_max;
  out.provenance = provenance;
  out.stats = stats;
  out.vocab = vocab;
  const size_t stride = clip_stride();
  out.joints.reserve(idx.size() * stride);
  for (size_t i : idx) {
    if (i >= size()) throw std::out_of_range(fmt::format("MotionSet::subset: index {} >= size {}", i, size()));
    out.joints.insert(out.joints.end(), clip(i), clip(i) + stride);
    out.lengths.push_back(lengths[i]);
    out.ids.push_back(ids[i]);
    out.splits.push_back(splits[i]);
    out.captions.push_back(captions[i]);
    if (!labels.empty()) out.labels.push_back(labels[i]);
  }
  return out;
}

void MotionSet::clear_padding() {
  const size_t frame = static_cast<size_t>(num_joints()) * 3;
  for (size_t i = 0; i < size(); ++i)
    if (lengths[i] >= 0 && lengths[i] < t_max)
      std::fill(clip(i) + lengths[i] * frame, clip(i) + clip_stride(), 0.0f);
}

void MotionSet::check(const std::string& source) const {
  skeleton.validate(source);
  const size_t N = size();
  const int J = num_joints();
  auto count_must_be = [&](const char* name, size_t n) {
    if (n != N) fail("{}: '{}' has {} entries but 'lengths' has {}; every per-clip array needs one entry per clip",
                     source, name, n, N);
  };
  count_must_be("ids", ids.size());
  count_must_be("split", splits.size());
  count_must_be("captions", captions.size());
  if (!labels.empty()) count_must_be("labels", labels.size());
  if (!(std::isfinite(fps) && fps > 0)) fail("{}: fps is {}; it must be a positive number of frames per second", source, fps);
  if (t_max < 0 || (N > 0 && t_max < 1)) fail("{}: t_max is {}; a non-empty set needs t_max >= 1", source, t_max);
  if (joints.size() != N * clip_stride())
    fail("{}: 'joints' holds {} floats but N x T_max x J x 3 = {} x {} x {} x 3 = {}; the joints do not match the "
         "skeleton's {} joints or the padded length",
         source, joints.size(), N, t_max, J, N * clip_stride(), J);

  std::unordered_map<std::string, size_t> seen;
  auto no_nul = [&](const char* name, size_t i, const std::string& s) {
    if (s.find('\0') != std::string::npos) fail("{}: '{}' of clip {} contains a NUL character", source, name, i);
  };
  for (size_t i = 0; i < N; ++i) {
    if (lengths[i] < 1 || lengths[i] > t_max)
      fail("{}: 'lengths' of clip {} ('{}') is {}, outside 1..T_max = {}", source, i, ids[i], lengths[i], t_max);
    if (ids[i].empty()) fail("{}: 'ids' of clip {} is empty; every clip needs an id", source, i);
    no_nul("ids", i, ids[i]);
    auto [it, fresh] = seen.emplace(ids[i], i);
    if (!fresh)
      fail("{}: 'ids' has '{}' twice (clips {} and {}); clip ids must be unique", source, ids[i], it->second, i);
    if (!kSplits.count(splits[i]))
      fail("{}: 'split' of clip {} ('{}') is '{}'; use train, val, test or sample", source, i, ids[i], splits[i]);
    if (captions[i].empty())
      fail("{}: 'captions' of clip {} ('{}') is empty; every clip needs at least one caption", source, i, ids[i]);
    for (auto& c : captions[i]) no_nul("captions", i, c);
    if (!labels.empty()) no_nul("labels", i, labels[i]);

    const float* c = clip(i);
    for (size_t k = 0; k < clip_stride(); ++k) {
      const size_t frame = k / (J * 3), joint = (k / 3) % J;
      if (!std::isfinite(c[k]))
        fail("{}: 'joints' of clip {} ('{}') frame {} joint {} ('{}') is not finite; fix the generator or the "
             "source data",
             source, i, ids[i], frame, joint, skeleton.joint_names[joint]);
      if (static_cast<int>(frame) >= lengths[i] && c[k] != 0.0f)
        fail("{}: 'joints' of clip {} ('{}') is not zero at padding frame {} (length {}); frames past the length "
             "must be zero (MotionSet::clear_padding)",
             source, i, ids[i], frame, lengths[i]);
    }
  }
  if (stats) {
    const NormStats& s = *stats;
    if (s.joint_mean.size() != 3 || s.joint_std.size() != 3)
      fail("{}: 'stats/joint_mean' and 'stats/joint_std' need 3 values (x, y, z), have {} and {}", source,
           s.joint_mean.size(), s.joint_std.size());
    if (s.feature_mean.size() != s.feature_std.size())
      fail("{}: 'stats/feature_mean' has {} values but 'stats/feature_std' {}", source, s.feature_mean.size(),
           s.feature_std.size());
    if (!all_finite(s.joint_mean) || !all_finite(s.joint_std) || !all_finite(s.feature_mean) ||
        !all_finite(s.feature_std))
      fail("{}: 'stats' holds non-finite values; recompute the statistics", source);
    for (float v : s.joint_std)
      if (!(v > 0)) fail("{}: 'stats/joint_std' must be positive; recompute the statistics", source);
    for (float v : s.feature_std)
      if (!(v > 0)) fail("{}: 'stats/feature_std' must be positive; recompute the statistics", source);
  }
  // One vocabulary format for every writer (docs/formats.md, "Vocabulary"): the
  // special tokens at ids 0-3, then the words. A file in another layout (an older
  // converter's sorted word list) is refused here, naming the file, rather than by
  // the first model that builds a TextVocab from it.
  if (!vocab.empty()) {
    const auto& specials = TextVocab::special_tokens();
    if (vocab.size() < specials.size() || !std::equal(specials.begin(), specials.end(), vocab.begin()))
      fail("{}: 'vocab' must start with <pad>, <unk>, <sos>, <eos> (ids 0-3), then the words (docs/formats.md, "
           "Vocabulary); it starts with '{}'. Re-convert the dataset with tools/humanml3d_to_h5.py (1.1 or later) "
           "or delete the 'vocab' dataset (models then build it from the train captions)",
           source, vocab.front());
  }
  std::set<std::string> words;
  for (auto& w : vocab)
    if (!words.insert(w).second) fail("{}: 'vocab' lists '{}' twice; vocabulary words must be unique", source, w);
}

// ---------------------------------------------------------------- file IO

void write_motion_file(const std::string& path, const MotionSet& m) { write_motion_file(path, m, nullptr); }

void write_motion_file(const std::string& path, const MotionSet& m, const std::function<void(int64_t)>& extra) {
  m.check(fmt::format("motion set for '{}'", path));
  AtomicOutput out(path);
  {
    QuietHdf5 quiet;
    Writer w(out.tmp_path(), path);
    const hid_t root = w.root();
    w.attr_string(root, "format", kFormatName);
    w.attr_int(root, "format_version", kFormatVersion);
    w.attr_double(root, "fps", m.fps);

    const auto N = static_cast<hsize_t>(m.size());
    const auto T = static_cast<hsize_t>(m.t_max);
    const auto J = static_cast<hsize_t>(m.num_joints());
    // One chunk per clip: a data loader reads clips one at a time.
    std::vector<hsize_t> chunk;
    if (N > 0) chunk = {1, T, J, 3};
    w.dataset(root, "joints", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, {N, T, J, 3}, m.joints.data(), chunk,
              kJointsGzipLevel);
    w.dataset(root, "lengths", H5T_STD_I32LE, H5T_NATIVE_INT, {N}, m.lengths.data());
    w.strings(root, "ids", m.ids);
    w.strings(root, "split", m.splits);
    if (!m.labels.empty()) w.strings(root, "labels", m.labels);

    std::vector<std::string> texts;
    std::vector<int64_t> offsets{0};
    for (auto& caps : m.captions) {
      texts.insert(texts.end(), caps.begin(), caps.end());
      offsets.push_back(static_cast<int64_t>(texts.size()));
    }
    {
      H5Handle g = w.group(root, "captions");
      w.strings(g.get(), "text", texts);
      w.dataset(g.get(), "offsets", H5T_STD_I64LE, H5T_NATIVE_INT64, {offsets.size()}, offsets.data());
    }
    write_skeleton(w, m.skeleton);
    {
      H5Handle g = w.group(root, "provenance");
      w.attr_string(g.get(), "generator", m.provenance.generator);
      w.attr_string(g.get(), "version", m.provenance.version);
      w.attr_int(g.get(), "seed", m.provenance.seed);
      w.attr_string(g.get(), "config", m.provenance.config);
      w.attr_string(g.get(), "created", m.provenance.created);
    }
    if (m.stats) {
      const NormStats& s = *m.stats;
      H5Handle g = w.group(root, "stats");
      w.dataset(g.get(), "joint_mean", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, {3}, s.joint_mean.data());
      w.dataset(g.get(), "joint_std", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, {3}, s.joint_std.data());
      // Feature statistics are optional: a converted dataset carries joint statistics
      // only and components compute the feature ones from its train split.
      if (!s.feature_mean.empty()) {
        const auto F = static_cast<hsize_t>(s.feature_mean.size());
        w.dataset(g.get(), "feature_mean", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, {F}, s.feature_mean.data());
        w.dataset(g.get(), "feature_std", H5T_IEEE_F32LE, H5T_NATIVE_FLOAT, {F}, s.feature_std.data());
      }
      w.attr_string(g.get(), "feature_layout", s.feature_layout);
    }
    if (!m.vocab.empty()) w.strings(root, "vocab", m.vocab);
    if (extra) extra(root);
    w.close();
  }
  seal_h5_file(out.tmp_path().string(), fmt::format("motion file '{}'", path));
  out.commit();
}

namespace {

// The read proper; read_motion_file checks the seal first and runs this under
// crash isolation when the file has none.
MotionSet read_motion_file_unchecked(const std::string& path) {
  QuietHdf5 quiet;
  if (H5Fis_hdf5(path.c_str()) <= 0) {
    H5Eclear2(H5E_DEFAULT);
    fail("motion file '{}' is not an HDF5 file (wrong file, or damaged); motion files are written by motionctl or "
         "tools/humanml3d_to_h5.py (docs/formats.md)",
         path);
  }
  H5Handle file(H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  if (!file.valid())
    fail("motion file '{}' cannot be opened: {}; the file is damaged or truncated, re-create it", path,
         hdf5_error_text());
  Reader r(file.get(), path);

  if (!r.has_attr("/", "format"))
    r.bad("attribute 'format' is missing", "this HDF5 file is not a motionctl motion file (docs/formats.md)");
  const std::string format = r.attr_string("/", "format");
  if (format != kFormatName)
    r.bad(fmt::format("attribute 'format' is '{}', not '{}'", format, kFormatName),
          "this HDF5 file is not a motionctl motion file");
  const int64_t version = r.attr_int("/", "format_version");
  if (version != kFormatVersion)
    r.bad(fmt::format("attribute 'format_version' is {}, this motionctl reads version {}", version, kFormatVersion),
          version > kFormatVersion ? "update motionctl" : "re-create the file");

  MotionSet m;
  m.fps = r.attr_double("/", "fps");
  m.skeleton = read_skeleton(r, path);
  const long long J = m.skeleton.num_joints();

  m.lengths = r.numeric<int>("lengths", H5T_INTEGER, H5T_NATIVE_INT, {-1});
  const auto N = static_cast<long long>(m.lengths.size());
  std::vector<hsize_t> jdims;
  {
    // Checked by hand first so a J mismatch names the skeleton rather than a bare shape.
    H5Handle d = r.open_dataset("joints");
    auto dims = r.shape(d.get(), "joints");
    if (dims.size() != 4 || dims[3] != 3)
      r.bad(fmt::format("dataset 'joints' has shape {}; it must be [N, T_max, J, 3]", join_dims(dims)),
            "see docs/formats.md and re-export the file");
    if (static_cast<long long>(dims[2]) != J)
      r.bad(fmt::format("dataset 'joints' has {} joints per frame but the skeleton '{}' has {}", dims[2],
                        m.skeleton.name, J),
            "the joints and the skeleton group must describe the same skeleton; re-export the file");
    if (static_cast<long long>(dims[0]) != N)
      r.bad(fmt::format("dataset 'joints' has {} clips but dataset 'lengths' has {}", dims[0], N),
            "both must have one entry per clip; re-export the file");
    // Named here, with the shape, rather than as MotionSet::check's bare "t_max is 0".
    if (N > 0 && dims[1] == 0)
      r.bad(fmt::format("dataset 'joints' has shape {}: 0 frames per clip", join_dims(dims)),
            "every clip needs at least one frame (T_max >= 1); re-export the file");
  }
  m.joints = r.numeric<float>("joints", H5T_FLOAT, H5T_NATIVE_FLOAT, {N, -1, J, 3}, &jdims);
  m.t_max = static_cast<int>(jdims[1]);
  if (!all_finite(m.joints)) {
    // Find the first bad value so the message can point at it.
    const size_t stride = static_cast<size_t>(m.t_max) * J * 3;
    for (size_t k = 0; k < m.joints.size(); ++k)
      if (!std::isfinite(m.joints[k]))
        r.bad(fmt::format("dataset 'joints' holds a non-finite value (clip {}, frame {}, joint {})", k / stride,
                          (k % stride) / (J * 3), (k / 3) % J),
              "fix the source data or the generator and re-export the file");
  }
  m.ids = r.strings("ids", N);
  m.splits = r.strings("split", N);
  if (r.exists("labels")) m.labels = r.strings("labels", N);

  auto texts = r.strings("captions/text", -1);
  auto offsets = r.numeric<int64_t>("captions/offsets", H5T_INTEGER, H5T_NATIVE_INT64, {N + 1});
  if (offsets[0] != 0 || offsets[N] != static_cast<int64_t>(texts.size()))
    r.bad(fmt::format("dataset 'captions/offsets' runs from {} to {} but must run from 0 to {} (the size of "
                      "'captions/text')",
                      offsets[0], offsets[N], texts.size()),
          "re-export the file");
  m.captions.resize(N);
  for (long long i = 0; i < N; ++i) {
    if (offsets[i + 1] <= offsets[i])
      r.bad(fmt::format("dataset 'captions/offsets' gives clip {} no captions (offsets {} -> {})", i, offsets[i],
                        offsets[i + 1]),
            "every clip needs at least one caption and offsets must increase");
    m.captions[i].assign(texts.begin() + offsets[i], texts.begin() + offsets[i + 1]);
  }

  if (r.exists("provenance")) {
    auto str_or_empty = [&](const char* name) {
      return r.has_attr("provenance", name) ? r.attr_string("provenance", name) : std::string();
    };
    m.provenance.generator = str_or_empty("generator");
    m.provenance.version = str_or_empty("version");
    m.provenance.config = str_or_empty("config");
    m.provenance.created = str_or_empty("created");
    if (r.has_attr("provenance", "seed")) m.provenance.seed = r.attr_int("provenance", "seed");
  }

  if (r.exists("stats")) {
    NormStats s;
    s.joint_mean = r.numeric<float>("stats/joint_mean", H5T_FLOAT, H5T_NATIVE_FLOAT, {3});
    s.joint_std = r.numeric<float>("stats/joint_std", H5T_FLOAT, H5T_NATIVE_FLOAT, {3});
    // Feature statistics are optional (tools/humanml3d_to_h5.py writes joint statistics
    // only; the evaluator computes feature ones from the train split, compute_norm_stats).
    const bool has_fm = r.exists("stats/feature_mean"), has_fs = r.exists("stats/feature_std");
    if (has_fm != has_fs)
      r.bad(fmt::format("group 'stats' holds only '{}'", has_fm ? "feature_mean" : "feature_std"),
            "write both feature_mean and feature_std, or neither");
    if (has_fm) {
      s.feature_mean = r.numeric<float>("stats/feature_mean", H5T_FLOAT, H5T_NATIVE_FLOAT, {-1});
      s.feature_std = r.numeric<float>("stats/feature_std", H5T_FLOAT, H5T_NATIVE_FLOAT,
                                       {static_cast<long long>(s.feature_mean.size())});
    }
    s.feature_layout = r.has_attr("stats", "feature_layout") ? r.attr_string("stats", "feature_layout") : "";
    m.stats = std::move(s);
  }
  if (r.exists("vocab")) m.vocab = r.strings("vocab", -1);

  m.check(fmt::format("motion file '{}'", path));
  return m;
}

}  // namespace

MotionSet read_motion_file(const std::string& path) {
  std::error_code ec;
  if (!fs::exists(path, ec))
    fail("motion file '{}' does not exist; check the path (datasets come from `motionctl fixture` or "
         "tools/humanml3d_to_h5.py)",
         path);
  if (fs::is_directory(path, ec)) fail("motion file '{}' is a directory; give the path of an .h5 file", path);
  if (!std::ifstream(path)) fail("motion file '{}' cannot be read (permission denied?)", path);
  // A sealed file whose checksum matches is exactly what a motionctl writer produced,
  // so libhdf5 can read it safely; an unsealed one (older, or written by other
  // tools) is read once in a child process first, so a crash inside libhdf5 on a
  // damaged file becomes an error message instead of taking this process down.
  const std::string what = fmt::format("motion file '{}'", path);
  if (check_h5_seal(path, "motion file") == H5Seal::absent)
    isolated_probe(what, [&] { read_motion_file_unchecked(path); });
  return read_motion_file_unchecked(path);
}

}  // namespace mc
