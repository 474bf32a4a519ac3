// Reading and writing constraint specs: YAML (hand-written) and the HDF5 layout
// for dense targets (docs/constraints.md). Range checks that need the skeleton or
// the clip length happen in compile(); everything else is checked here.
#include "control/constraint_spec.h"
#include "control/sample_constraints.h"

#include <hdf5.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cstring>
#include <cmath>
#include <filesystem>
#include <map>
#include <regex>
#include <set>

#include "core/atomic_file.h"
#include "core/config.h"
#include "core/error.h"
#include "core/yaml_strict.h"
#include "core/h5_handle.h"
#include "core/h5_seal.h"
#include "core/isolated.h"

namespace mc {

namespace {

const char* const kAxisNames = "xyz";

// Keys every item accepts, then the keys of each type. A key valid for another
// type gets a "does not apply" message instead of "unknown key".
const std::vector<std::string> kCommonKeys = {"type", "name", "hard", "variance", "score_only"};
const std::map<std::string, std::vector<std::string>>& type_keys() {
  static const std::map<std::string, std::vector<std::string>> keys = {
      {"keyframe", {"joints", "frames", "axes", "values", "from_source"}},
      {"trajectory", {"joints", "frames", "axes", "values", "from_source"}},
      {"planar_root", {"frames", "values", "from_source"}},
      {"camera_2d", {"joints", "frames", "camera", "values", "from_source"}},
      {"relative", {"joints", "frames", "axes", "values", "from_source"}},
      {"loop", {"joints", "frames", "axes", "up_to_root_translation"}},
      {"upper_body_edit", {"role", "frames", "axes"}},
      {"floor", {"joints", "frames", "height"}},
      {"half_space", {"joints", "frames", "normal", "offset", "relative_to"}},
      {"box", {"joints", "frames", "axes", "min", "max"}},
      {"speed_limit", {"joints", "frames", "axes", "max"}},
      {"tangent", {"joints", "frames", "axes", "values", "from_source", "min_speed"}},
      {"facing", {"joints", "frames", "values", "from_source", "min_width"}},
  };
  return keys;
}

std::string join(const std::vector<std::string>& v, const char* sep = ", ") {
  std::string s;
  for (size_t i = 0; i < v.size(); ++i) s += (i ? sep : "") + v[i];
  return s;
}

std::string hint(const std::string& word, const std::vector<std::string>& candidates) {
  std::string h = did_you_mean(word, candidates);
  return h.empty() ? "" : " (did you mean '" + h + "'?)";
}

std::string shape_text(const std::vector<int>& shape) {
  std::string s = "[";
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

std::string label_of(int index, const std::string& name, const std::string& type) {
  std::string s = fmt::format("item {}", index);
  if (!name.empty()) s += " '" + name + "'";
  if (!type.empty()) s += " (" + type + ")";
  return s;
}

// Where an item is, for messages: "spec.yaml:12: item 2 'left wrist' (keyframe)".
struct ItemContext {
  std::string source;
  int line = 0;
  int index = 0;
  std::string name, type;
  std::string where() const {
    return (line > 0 ? fmt::format("{}:{}", source, line) : source) + ": " + label_of(index, name, type);
  }
  [[noreturn]] void fail_key(const std::string& key, const std::string& problem) const {
    fail("{}: key '{}': {}", where(), key, problem);
  }
};

// The final checks shared by the YAML and HDF5 readers: value rules that need
// neither the skeleton nor T.
void check_item(const ConstraintItem& it, const ItemContext& ctx) {
  if (!std::isfinite(it.variance)) ctx.fail_key("variance", fmt::format("must be finite, got {}", it.variance));
  if (it.variance < 0)
    ctx.fail_key("variance", fmt::format("must be >= 0 (0 = hard), got negative variance {}", it.variance));
  std::set<int> seen;
  for (int a : it.axes) {
    if (a < 0 || a > 2) ctx.fail_key("axes", fmt::format("axis {} is out of range (use x, y, z or 0, 1, 2)", a));
    if (!seen.insert(a).second) ctx.fail_key("axes", fmt::format("axis {} is listed twice", kAxisNames[a]));
  }
  size_t expect = 1;
  for (int s : it.values.shape) {
    if (s < 0) ctx.fail_key("values", "negative dimension");
    expect *= static_cast<size_t>(s);
  }
  if (it.values.given() && expect != it.values.data.size())
    ctx.fail_key("values", fmt::format("shape {} does not match its {} numbers", shape_text(it.values.shape),
                                       it.values.data.size()));
  for (size_t k = 0; k < it.values.data.size(); ++k)
    if (!std::isfinite(it.values.data[k])) {
      // Report the multi-index so the user can find the entry in a nested list.
      std::vector<int> idx(it.values.shape.size());
      size_t rest = k;
      for (int d = static_cast<int>(idx.size()) - 1; d >= 0; --d) {
        idx[d] = static_cast<int>(rest % it.values.shape[d]);
        rest /= it.values.shape[d];
      }
      ctx.fail_key("values", fmt::format("values{} is not finite ({})", shape_text(idx), it.values.data[k]));
    }
  if (it.values.given() && it.from_source)
    ctx.fail_key("from_source", "give either 'values' or 'from_source: true', not both");
  if (it.has_camera) {
    const CameraParams& c = it.camera;
    if (!std::isfinite(c.scale) || !(c.scale > 0))
      ctx.fail_key("camera", fmt::format("scale must be a finite number > 0, got {}", c.scale));
    for (double a : {c.pitch_deg, c.yaw_deg, c.roll_deg})
      if (!std::isfinite(a)) ctx.fail_key("camera", fmt::format("angles must be finite, got {}", a));
  }
  auto finite_key = [&](const char* key, double v) {
    if (!std::isfinite(v)) ctx.fail_key(key, fmt::format("must be a finite number, got {}", v));
  };
  finite_key("height", it.height);
  finite_key("offset", it.offset);
  if (!std::isfinite(it.min_speed) || it.min_speed < 0)
    ctx.fail_key("min_speed", fmt::format("must be a finite number >= 0 (metres per frame), got {}", it.min_speed));
  if (!std::isfinite(it.min_width) || it.min_width < 0)
    ctx.fail_key("min_width", fmt::format("must be a finite number >= 0 (metres), got {}", it.min_width));
  if (it.type == "half_space") {
    if (it.normal.size() != 3)
      ctx.fail_key("normal", it.normal.empty() ? std::string("half_space items need 'normal: [nx, ny, nz]'")
                                               : fmt::format("expected 3 numbers [nx, ny, nz], got {}", it.normal.size()));
    double n2 = 0;
    for (double v : it.normal) {
      finite_key("normal", v);
      n2 += v * v;
    }
    if (!(n2 > 1e-24)) ctx.fail_key("normal", "the normal is zero; give the direction in which the allowed side lies");
  }
  for (double v : it.lower) finite_key("min", v);
  for (double v : it.upper) finite_key("max", v);
  if (it.type == "box" && it.lower.empty() && it.upper.empty())
    ctx.fail_key("type", "box items need 'min' and/or 'max' (one number, or one per axis)");
  if (it.type == "box" && it.lower.size() == it.upper.size())
    for (size_t k = 0; k < it.lower.size(); ++k)
      if (it.lower[k] > it.upper[k])
        ctx.fail_key("min", fmt::format("min {} is above max {} (entry {}): the box is empty", it.lower[k],
                                        it.upper[k], k));
  if (it.type == "speed_limit") {
    if (it.upper.empty())
      ctx.fail_key("max", "speed_limit items need 'max' (metres per frame, one number or one per axis)");
    for (double v : it.upper)
      if (!(v > 0)) ctx.fail_key("max", fmt::format("the speed bound must be > 0 metres per frame, got {}", v));
  }
  if (it.frames.kind == FrameSelection::Kind::range && it.frames.step < 1)
    ctx.fail_key("frames", fmt::format("step must be >= 1, got {}", it.frames.step));
  if (it.frames.kind == FrameSelection::Kind::list && it.frames.list.empty())
    ctx.fail_key("frames", "the frame list is empty");
}

// `hard:` is redundant with `variance:` (0 = hard); when both are given they must agree.
void check_hard_flag(bool hard, double variance, const ItemContext& ctx) {
  if (hard && variance > 0)
    ctx.fail_key("hard", fmt::format("'hard: true' contradicts 'variance: {}' (a hard item has variance 0)", variance));
  if (!hard && variance == 0)
    ctx.fail_key("variance", "a soft item ('hard: false') needs 'variance' > 0 (observation units squared)");
}

// ---------------------------------------------------------------- YAML

class YamlItemReader {
 public:
  YamlItemReader(const YAML::Node& node, ItemContext ctx) : node_(node), ctx_(std::move(ctx)) {}

  ConstraintItem read() {
    ConstraintItem it;
    it.line = ctx_.line;
    if (!node_.IsMap()) fail("{}: an item must be a map with at least 'type'", ctx_.where());
    if (node_["name"]) it.name = ctx_.name = scalar_string("name");
    if (!node_["type"]) fail("{}: the item has no 'type' (one of {})", ctx_.where(), join(all_constraint_types()));
    it.type = scalar_string("type");
    auto& keys = type_keys();
    if (!keys.count(it.type))
      ctx_.fail_key("type", fmt::format("unknown constraint type '{}'{}; known types: {}", it.type,
                                        hint(it.type, all_constraint_types()), join(all_constraint_types())));
    ctx_.type = it.type;
    check_keys(it.type);

    // Negative and non-finite variances are reported by check_item, worded alike for YAML and HDF5.
    if (node_["variance"]) it.variance = scalar<double>("variance", "a number");
    if (node_["hard"]) check_hard_flag(scalar<bool>("hard", "true or false"), it.variance, ctx_);

    if (node_["joints"]) it.joints = joints();
    if (node_["frames"]) it.frames = frames();
    if (node_["axes"]) it.axes = axes();
    if (node_["values"]) it.values = values();
    if (node_["from_source"]) it.from_source = scalar<bool>("from_source", "true or false");
    if (node_["camera"]) it.camera = camera(), it.has_camera = true;
    if (node_["up_to_root_translation"])
      it.up_to_root_translation = scalar<bool>("up_to_root_translation", "true or false");
    if (node_["role"]) it.role = scalar_string("role");
    if (node_["score_only"]) it.score_only = scalar<bool>("score_only", "true or false");
    if (node_["height"]) it.height = scalar<double>("height", "a number (metres)");
    if (node_["offset"]) it.offset = scalar<double>("offset", "a number (metres)");
    if (node_["normal"]) it.normal = numbers("normal");
    if (node_["relative_to"]) it.relative_to = joint_ref("relative_to");
    if (node_["min"]) it.lower = numbers("min");
    if (node_["max"]) it.upper = numbers("max");
    if (node_["min_speed"]) it.min_speed = scalar<double>("min_speed", "a number (metres per frame)");
    if (node_["min_width"]) it.min_width = scalar<double>("min_width", "a number (metres)");
    check_item(it, ctx_);
    return it;
  }

 private:
  // One number or a flat list of numbers.
  std::vector<double> numbers(const char* key) {
    const YAML::Node n = node_[key];
    std::vector<double> out;
    auto add = [&](const YAML::Node& e) {
      if (!e.IsScalar()) ctx_.fail_key(key, "expected a number or a flat list of numbers");
      try {
        out.push_back(e.as<double>());
      } catch (const YAML::Exception&) {
        ctx_.fail_key(key, fmt::format("expected a number, got '{}'", e.Scalar()));
      }
    };
    if (n.IsSequence()) for (auto e : n) add(e);
    else add(n);
    if (out.empty()) ctx_.fail_key(key, "the list is empty");
    return out;
  }

  JointRef joint_ref(const char* key) {
    static const std::regex number(R"(^[-+]?[0-9]+$)");
    const YAML::Node n = node_[key];
    if (!n.IsScalar()) ctx_.fail_key(key, "expected one joint (an index or a name)");
    JointRef r;
    if (std::regex_match(n.Scalar(), number)) r.index = integer(n, key);
    else r.name = n.Scalar();
    if (!r.set()) ctx_.fail_key(key, fmt::format("joint index {} is negative", r.index));
    return r;
  }

  void check_keys(const std::string& type) {
    const auto& own = type_keys().at(type);
    std::vector<std::string> allowed = kCommonKeys;
    allowed.insert(allowed.end(), own.begin(), own.end());
    std::set<std::string> any;
    for (auto& [t, ks] : type_keys()) any.insert(ks.begin(), ks.end());
    for (auto kv : node_) {
      std::string key = kv.first.as<std::string>();
      if (std::find(allowed.begin(), allowed.end(), key) != allowed.end()) continue;
      if (any.count(key))
        ctx_.fail_key(key, fmt::format("does not apply to {} items; their keys are: {}", type, join(allowed)));
      ctx_.fail_key(key, fmt::format("unknown key{}; {} items take: {}", hint(key, allowed), type, join(allowed)));
    }
  }

  std::string scalar_string(const char* key) {
    const YAML::Node n = node_[key];
    if (!n.IsScalar()) ctx_.fail_key(key, "expected a single value");
    return n.Scalar();
  }

  template <class T>
  T scalar(const char* key, const char* what) {
    const YAML::Node n = node_[key];
    if (!n.IsScalar()) ctx_.fail_key(key, fmt::format("expected {}", what));
    try {
      return n.as<T>();
    } catch (const YAML::Exception&) {
      ctx_.fail_key(key, fmt::format("expected {}, got '{}'", what, n.Scalar()));
    }
  }

  int integer(const YAML::Node& n, const char* key) {
    if (!n.IsScalar()) ctx_.fail_key(key, "expected an integer");
    try {
      return n.as<int>();
    } catch (const YAML::Exception&) {
      ctx_.fail_key(key, fmt::format("expected an integer, got '{}'", n.Scalar()));
    }
  }

  std::vector<JointRef> joints() {
    static const std::regex number(R"(^[-+]?[0-9]+$)");
    const YAML::Node n = node_["joints"];
    std::vector<YAML::Node> list;
    if (n.IsScalar()) list.push_back(n);
    else if (n.IsSequence()) for (auto e : n) list.push_back(e);
    else ctx_.fail_key("joints", "expected a joint (index or name) or a list of them");
    std::vector<JointRef> out;
    for (auto& e : list) {
      if (!e.IsScalar()) ctx_.fail_key("joints", "each joint must be an index or a name");
      JointRef r;
      if (std::regex_match(e.Scalar(), number)) r.index = integer(e, "joints");
      else r.name = e.Scalar();
      out.push_back(r);
    }
    if (out.empty()) ctx_.fail_key("joints", "the joint list is empty");
    return out;
  }

  FrameSelection frames() {
    const YAML::Node n = node_["frames"];
    FrameSelection f;
    if (n.IsScalar() && n.Scalar() == "all") {
      f.kind = FrameSelection::Kind::all;
    } else if (n.IsScalar()) {
      f.kind = FrameSelection::Kind::list;
      f.list.push_back(integer(n, "frames"));
    } else if (n.IsSequence()) {
      f.kind = FrameSelection::Kind::list;
      for (auto e : n) f.list.push_back(integer(e, "frames"));
    } else if (n.IsMap()) {
      f.kind = FrameSelection::Kind::range;
      for (auto kv : n) {
        std::string k = kv.first.as<std::string>();
        if (k == "start") f.start = integer(kv.second, "frames");
        else if (k == "stop") f.stop = integer(kv.second, "frames");
        else if (k == "step") f.step = integer(kv.second, "frames");
        else ctx_.fail_key("frames", fmt::format("unknown range key '{}'{}; a range has start, stop, step", k,
                                                  hint(k, {"start", "stop", "step"})));
      }
    } else {
      ctx_.fail_key("frames", "expected a list of frames, 'all', or {start, stop, step}");
    }
    return f;
  }

  std::vector<int> axes() {
    const YAML::Node n = node_["axes"];
    std::vector<int> out;
    auto add_name = [&](const std::string& s) {
      for (char ch : s) {
        const char* p = ch ? std::strchr(kAxisNames, std::tolower(static_cast<unsigned char>(ch))) : nullptr;
        if (!p) ctx_.fail_key("axes", fmt::format("unknown axis '{}' in '{}' (use x, y, z)", ch, s));
        out.push_back(static_cast<int>(p - kAxisNames));
      }
    };
    auto add = [&](const YAML::Node& e) {
      if (!e.IsScalar()) ctx_.fail_key("axes", "expected axis names (x, y, z) or indices (0, 1, 2)");
      const std::string& s = e.Scalar();
      if (!s.empty() && std::all_of(s.begin(), s.end(), [](char c) { return std::isdigit((unsigned char)c) || c == '-'; }))
        out.push_back(integer(e, "axes"));
      else add_name(s);
    };
    if (n.IsSequence()) for (auto e : n) add(e);
    else add(n);
    if (out.empty()) ctx_.fail_key("axes", "no axes given");
    return out;
  }

  // A nested list of numbers -> row-major data and shape; rejects ragged lists.
  TargetArray values() {
    const YAML::Node n = node_["values"];
    if (!n.IsSequence()) ctx_.fail_key("values", "expected a (nested) list of numbers");
    TargetArray a;
    // Node assignment would overwrite the node it refers to; reset() rebinds.
    for (YAML::Node cur = n; cur.IsSequence(); cur.reset(cur[0])) {
      a.shape.push_back(static_cast<int>(cur.size()));
      if (cur.size() == 0) break;
    }
    std::vector<int> idx;
    fill(n, 0, a, idx);
    return a;
  }
  void fill(const YAML::Node& n, size_t depth, TargetArray& a, std::vector<int>& idx) {
    if (depth == a.shape.size()) {
      if (!n.IsScalar()) ctx_.fail_key("values", fmt::format("values{} is nested deeper than the first entry "
                                                              "suggests (shape {})", shape_text(idx), shape_text(a.shape)));
      try {
        a.data.push_back(n.as<double>());
      } catch (const YAML::Exception&) {
        ctx_.fail_key("values", fmt::format("values{} is not a number: '{}'", shape_text(idx), n.Scalar()));
      }
      return;
    }
    if (!n.IsSequence() || static_cast<int>(n.size()) != a.shape[depth])
      ctx_.fail_key("values", fmt::format("ragged list: values{} has {} entries where {} were expected (shape {})",
                                          shape_text(idx), n.IsSequence() ? static_cast<int>(n.size()) : 1,
                                          a.shape[depth], shape_text(a.shape)));
    for (int i = 0; i < a.shape[depth]; ++i) {
      idx.push_back(i);
      fill(n[i], depth + 1, a, idx);
      idx.pop_back();
    }
  }

  CameraParams camera() {
    const YAML::Node n = node_["camera"];
    if (!n.IsMap()) ctx_.fail_key("camera", "expected a map {scale, pitch_deg, yaw_deg, roll_deg}");
    CameraParams c;
    const std::vector<std::string> names = {"scale", "pitch_deg", "yaw_deg", "roll_deg"};
    for (auto kv : n) {
      std::string k = kv.first.as<std::string>();
      double v = 0;
      if (std::find(names.begin(), names.end(), k) == names.end()) {
        // "pitch" for "pitch_deg" is the likely slip, and too far for did_you_mean.
        bool angle = std::find(names.begin(), names.end(), k + "_deg") != names.end();
        ctx_.fail_key("camera", fmt::format("unknown camera key '{}'{}; a camera has {} (angles in degrees)", k,
                                            angle ? " (did you mean '" + k + "_deg'?)" : hint(k, names), join(names)));
      }
      if (!kv.second.IsScalar()) ctx_.fail_key("camera", fmt::format("'{}' must be a number", k));
      try {
        v = kv.second.as<double>();
      } catch (const YAML::Exception&) {
        ctx_.fail_key("camera", fmt::format("'{}' must be a number, got '{}'", k, kv.second.Scalar()));
      }
      (k == "scale" ? c.scale : k == "pitch_deg" ? c.pitch_deg : k == "yaw_deg" ? c.yaw_deg : c.roll_deg) = v;
    }
    return c;
  }

  const YAML::Node& node_;
  ItemContext ctx_;
};

// ---------------------------------------------------------------- HDF5

// Owns one hid_t.
// Group and dataset creation properties without modification times, so the same
// spec written twice gives the same bytes (as motion files do).
static hid_t untimed(hid_t cls) {
  hid_t p = H5Pcreate(cls);
  H5Pset_obj_track_times(p, false);
  return p;
}

H5Handle utf8_string_type() {
  H5Handle t(H5Tcopy(H5T_C_S1), H5Tclose);
  H5Tset_size(t.get(), H5T_VARIABLE);
  H5Tset_cset(t.get(), H5T_CSET_UTF8);
  return t;
}

class H5ItemReader {
 public:
  H5ItemReader(hid_t group, ItemContext ctx) : g_(group), ctx_(std::move(ctx)) {}

  ConstraintItem read() {
    ConstraintItem it;
    if (!has_attr("type")) fail("{}: the item group has no 'type' attribute", ctx_.where());
    it.type = attr_string("type");
    if (has_attr("name")) it.name = ctx_.name = attr_string("name");
    if (!type_keys().count(it.type))
      ctx_.fail_key("type", fmt::format("unknown constraint type '{}'{}; known types: {}", it.type,
                                        hint(it.type, all_constraint_types()), join(all_constraint_types())));
    ctx_.type = it.type;
    check_members(it.type);
    if (has_attr("variance")) it.variance = attr_double("variance");
    if (has_attr("hard")) check_hard_flag(attr_double("hard") != 0, it.variance, ctx_);
    if (has_attr("from_source")) it.from_source = attr_double("from_source") != 0;
    if (has_attr("up_to_root_translation")) it.up_to_root_translation = attr_double("up_to_root_translation") != 0;
    if (has_attr("role")) it.role = attr_string("role");
    if (has_dataset("joints")) it.joints = joints();
    if (has_dataset("frames")) {
      it.frames.kind = FrameSelection::Kind::list;
      it.frames.list = ints("frames");
    } else if (has_attr("frames")) {
      std::string s = attr_string("frames");
      if (s != "all") ctx_.fail_key("frames", fmt::format("attribute must be 'all', got '{}'", s));
      it.frames.kind = FrameSelection::Kind::all;
    } else if (has_attr("frames_start") || has_attr("frames_stop") || has_attr("frames_step")) {
      it.frames.kind = FrameSelection::Kind::range;
      if (has_attr("frames_start")) it.frames.start = static_cast<int>(attr_double("frames_start"));
      if (has_attr("frames_stop")) it.frames.stop = static_cast<int>(attr_double("frames_stop"));
      if (has_attr("frames_step")) it.frames.step = static_cast<int>(attr_double("frames_step"));
    }
    if (has_dataset("axes")) it.axes = ints("axes");
    if (has_dataset("values")) it.values = doubles("values");
    if (has_attr("score_only")) it.score_only = attr_double("score_only") != 0;
    if (has_attr("height")) it.height = attr_double("height");
    if (has_attr("offset")) it.offset = attr_double("offset");
    if (has_attr("min_speed")) it.min_speed = attr_double("min_speed");
    if (has_attr("min_width")) it.min_width = attr_double("min_width");
    if (has_dataset("normal")) it.normal = doubles("normal").data;
    if (has_dataset("min")) it.lower = doubles("min").data;
    if (has_dataset("max")) it.upper = doubles("max").data;
    if (has_dataset("relative_to")) {
      auto refs = joints_of("relative_to");
      if (refs.size() != 1) ctx_.fail_key("relative_to", fmt::format("must hold exactly one joint, holds {}", refs.size()));
      it.relative_to = refs[0];
    }
    if (has_dataset("camera")) {
      TargetArray c = doubles("camera");
      if (c.data.size() != 4)
        ctx_.fail_key("camera", fmt::format("dataset must hold 4 numbers (scale, pitch_deg, yaw_deg, roll_deg), "
                                            "has shape {}", shape_text(c.shape)));
      it.camera = {c.data[0], c.data[1], c.data[2], c.data[3]};
      it.has_camera = true;
    }
    check_item(it, ctx_);
    return it;
  }

 private:
  bool has_attr(const char* name) const { return H5Aexists(g_, name) > 0; }
  bool has_dataset(const char* name) const { return H5Lexists(g_, name, H5P_DEFAULT) > 0; }

  // Attributes and datasets of an item are exactly its YAML keys (frames may also
  // come as the attribute 'all' or as frames_start/stop/step).
  void check_members(const std::string& type) {
    std::vector<std::string> allowed = kCommonKeys;
    for (auto& k : type_keys().at(type)) allowed.push_back(k);
    for (const char* k : {"frames_start", "frames_stop", "frames_step"}) allowed.push_back(k);
    auto check = [&](const std::string& key) {
      if (std::find(allowed.begin(), allowed.end(), key) == allowed.end())
        ctx_.fail_key(key, fmt::format("unknown or inapplicable member{}; {} items take: {}", hint(key, allowed), type,
                                       join(allowed)));
    };
    H5G_info_t info;
    H5Gget_info(g_, &info);
    for (hsize_t i = 0; i < info.nlinks; ++i) {
      char name[256] = {0};
      H5Lget_name_by_idx(g_, ".", H5_INDEX_NAME, H5_ITER_INC, i, name, sizeof name, H5P_DEFAULT);
      check(name);
    }
    std::vector<std::string> attrs;
    hsize_t pos = 0;
    H5Aiterate2(
        g_, H5_INDEX_NAME, H5_ITER_INC, &pos,
        [](hid_t, const char* name, const H5A_info_t*, void* out) -> herr_t {
          static_cast<std::vector<std::string>*>(out)->push_back(name);
          return 0;
        },
        &attrs);
    for (auto& a : attrs) check(a);
  }

  std::string attr_string(const char* name) {
    H5Handle a(H5Aopen(g_, name, H5P_DEFAULT), H5Aclose);
    H5Handle t(H5Aget_type(a.get()), H5Tclose);
    if (H5Tget_class(t.get()) != H5T_STRING) ctx_.fail_key(name, "attribute must be a string");
    if (H5Tis_variable_str(t.get()) > 0) {
      H5Handle mt = utf8_string_type();
      char* s = nullptr;
      if (H5Aread(a.get(), mt.get(), &s) < 0 || !s) ctx_.fail_key(name, "unreadable string attribute");
      std::string out(s);
      H5free_memory(s);
      return out;
    }
    size_t size = H5Tget_size(t.get());
    std::string buf(size, '\0');
    H5Handle mt(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(mt.get(), size);
    if (H5Aread(a.get(), mt.get(), buf.data()) < 0) ctx_.fail_key(name, "unreadable string attribute");
    return std::string(buf.c_str());
  }

  double attr_double(const char* name) {
    H5Handle a(H5Aopen(g_, name, H5P_DEFAULT), H5Aclose);
    H5Handle s(H5Aget_space(a.get()), H5Sclose);
    H5Handle t(H5Aget_type(a.get()), H5Tclose);
    auto cls = H5Tget_class(t.get());
    if ((cls != H5T_FLOAT && cls != H5T_INTEGER) || H5Sget_simple_extent_npoints(s.get()) != 1)
      ctx_.fail_key(name, "attribute must be one number");
    double v = 0;
    if (H5Aread(a.get(), H5T_NATIVE_DOUBLE, &v) < 0) ctx_.fail_key(name, "unreadable attribute");
    return v;
  }

  std::vector<int> ints(const char* name) {
    TargetArray a = doubles(name, true);
    if (a.shape.size() != 1) ctx_.fail_key(name, fmt::format("must be one-dimensional, has shape {}", shape_text(a.shape)));
    std::vector<int> out;
    for (double v : a.data) out.push_back(static_cast<int>(v));
    return out;
  }

  std::vector<JointRef> joints() { return joints_of("joints"); }

  std::vector<JointRef> joints_of(const char* key) {
    H5Handle d(H5Dopen2(g_, key, H5P_DEFAULT), H5Dclose);
    H5Handle t(H5Dget_type(d.get()), H5Tclose);
    std::vector<JointRef> out;
    if (H5Tget_class(t.get()) == H5T_STRING) {
      H5Handle s(H5Dget_space(d.get()), H5Sclose);
      if (H5Sget_simple_extent_ndims(s.get()) != 1) ctx_.fail_key(key, "must be one-dimensional");
      hssize_t n = H5Sget_simple_extent_npoints(s.get());
      if (H5Tis_variable_str(t.get()) <= 0) ctx_.fail_key(key, "joint names must be variable-length strings");
      std::vector<char*> ptrs(static_cast<size_t>(n), nullptr);
      H5Handle mt = utf8_string_type();
      if (H5Dread(d.get(), mt.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, ptrs.data()) < 0)
        ctx_.fail_key(key, "unreadable dataset");
      for (char* p : ptrs) {
        JointRef r;
        r.name = p ? p : "";
        out.push_back(r);
      }
      H5Dvlen_reclaim(mt.get(), s.get(), H5P_DEFAULT, ptrs.data());
    } else {
      for (int j : ints(key)) out.push_back(JointRef{j, ""});
    }
    if (out.empty()) ctx_.fail_key(key, "the joint list is empty");
    return out;
  }

  TargetArray doubles(const char* name, bool integral = false) {
    H5Handle d(H5Dopen2(g_, name, H5P_DEFAULT), H5Dclose);
    if (!d.valid()) ctx_.fail_key(name, "is not a readable dataset");
    H5Handle t(H5Dget_type(d.get()), H5Tclose);
    auto cls = H5Tget_class(t.get());
    if (integral ? cls != H5T_INTEGER : (cls != H5T_FLOAT && cls != H5T_INTEGER))
      ctx_.fail_key(name, integral ? "dataset must hold integers" : "dataset must hold numbers");
    H5Handle s(H5Dget_space(d.get()), H5Sclose);
    int nd = H5Sget_simple_extent_ndims(s.get());
    std::vector<hsize_t> dims(std::max(nd, 0));
    H5Sget_simple_extent_dims(s.get(), dims.data(), nullptr);
    TargetArray a;
    size_t n = 1;
    for (hsize_t v : dims) a.shape.push_back(static_cast<int>(v)), n *= v;
    if (nd == 0) a.shape = {1};
    a.data.resize(n);
    if (n > 0 && H5Dread(d.get(), H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, a.data.data()) < 0)
      ctx_.fail_key(name, "unreadable dataset");
    return a;
  }

  hid_t g_;
  ItemContext ctx_;
};

class H5Writer {
 public:
  explicit H5Writer(hid_t parent) : p_(parent), str_(utf8_string_type()) {}

  void attr_string(const char* name, const std::string& v) {
    H5Handle sp(H5Screate(H5S_SCALAR), H5Sclose);
    H5Handle a(H5Acreate2(p_, name, str_.get(), sp.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
    const char* c = v.c_str();
    check(a.valid() && H5Awrite(a.get(), str_.get(), &c) >= 0, name);
  }
  void attr_double(const char* name, double v) { attr(name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, &v); }
  void attr_int(const char* name, int64_t v) { attr(name, H5T_STD_I64LE, H5T_NATIVE_INT64, &v); }

  void ints(const char* name, const std::vector<int>& v) {
    dataset(name, H5T_STD_I32LE, H5T_NATIVE_INT, {v.size()}, v.data());
  }
  void doubles(const char* name, const std::vector<double>& v, const std::vector<int>& shape) {
    std::vector<hsize_t> dims(shape.begin(), shape.end());
    dataset(name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, dims, v.data());
  }
  void strings(const char* name, const std::vector<std::string>& v) {
    std::vector<const char*> ptrs;
    for (auto& s : v) ptrs.push_back(s.c_str());
    dataset(name, str_.get(), str_.get(), {v.size()}, ptrs.data());
  }

 private:
  void attr(const char* name, hid_t ftype, hid_t mtype, const void* v) {
    H5Handle sp(H5Screate(H5S_SCALAR), H5Sclose);
    H5Handle a(H5Acreate2(p_, name, ftype, sp.get(), H5P_DEFAULT, H5P_DEFAULT), H5Aclose);
    check(a.valid() && H5Awrite(a.get(), mtype, v) >= 0, name);
  }
  void dataset(const char* name, hid_t ftype, hid_t mtype, const std::vector<hsize_t>& dims, const void* data) {
    H5Handle sp(H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr), H5Sclose);
    H5Handle dcpl(untimed(H5P_DATASET_CREATE), H5Pclose);
    H5Handle d(H5Dcreate2(p_, name, ftype, sp.get(), H5P_DEFAULT, dcpl.get(), H5P_DEFAULT), H5Dclose);
    check(d.valid(), name);
    size_t n = 1;
    for (auto v : dims) n *= v;
    if (n > 0) check(H5Dwrite(d.get(), mtype, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) >= 0, name);
  }
  static void check(bool ok, const char* what) {
    if (!ok) throw std::runtime_error(fmt::format("HDF5 error writing '{}' of a constraint spec", what));
  }
  hid_t p_;
  H5Handle str_;
};

constexpr const char* kH5Format = "motionctl.constraints";
constexpr int64_t kH5FormatVersion = 1;

}  // namespace

const std::vector<std::string>& constraint_types() {
  static const std::vector<std::string> types = {"keyframe", "trajectory", "planar_root", "camera_2d",
                                                 "relative", "loop",       "upper_body_edit"};
  return types;
}

const std::vector<std::string>& inequality_constraint_types() {
  static const std::vector<std::string> types = {"floor", "half_space", "box", "speed_limit"};
  return types;
}

const std::vector<std::string>& direction_constraint_types() {
  static const std::vector<std::string> types = {"tangent", "facing"};
  return types;
}

const std::vector<std::string>& all_constraint_types() {
  static const std::vector<std::string> types = [] {
    std::vector<std::string> all = constraint_types();
    for (auto* group : {&inequality_constraint_types(), &direction_constraint_types()})
      all.insert(all.end(), group->begin(), group->end());
    return all;
  }();
  return types;
}

bool is_inequality_type(const std::string& type) {
  const auto& t = inequality_constraint_types();
  return std::find(t.begin(), t.end(), type) != t.end();
}

bool is_direction_type(const std::string& type) {
  const auto& t = direction_constraint_types();
  return std::find(t.begin(), t.end(), type) != t.end();
}

bool ConstraintItem::operator==(const ConstraintItem& o) const {
  return type == o.type && name == o.name && variance == o.variance && joints == o.joints && frames == o.frames &&
         axes == o.axes && values == o.values && from_source == o.from_source && has_camera == o.has_camera &&
         (!has_camera || camera == o.camera) && up_to_root_translation == o.up_to_root_translation && role == o.role &&
         height == o.height && normal == o.normal && offset == o.offset && relative_to == o.relative_to &&
         lower == o.lower && upper == o.upper && min_speed == o.min_speed && min_width == o.min_width &&
         score_only == o.score_only;
}

std::string ConstraintSpec::item_label(int index) const {
  const ConstraintItem& it = items.at(index);
  return label_of(index, it.name, it.type);
}

ConstraintSpec parse_constraint_spec_yaml(const std::string& text, const std::string& source) {
  // Strict: duplicate keys, complex keys and extra documents name the line.
  YAML::Node root = parse_yaml_strict(text, source, "YAML in the constraint spec");
  YAML::Node list;
  if (root.IsSequence()) {
    list = root;
  } else if (root.IsMap()) {
    for (auto kv : root) {
      std::string key = kv.first.as<std::string>();
      if (key != "constraints")
        fail("{}: unknown top-level key '{}'{}; a spec is a list of items, or a map with 'constraints:'", source, key,
             hint(key, {"constraints"}));
    }
    list = root["constraints"];
    if (!list || !list.IsSequence()) fail("{}: 'constraints' must be a list of items", source);
  } else if (root.IsNull()) {
    fail("{}: the constraint spec is empty", source);
  } else {
    fail("{}: a constraint spec is a list of items, or a map with 'constraints:'", source);
  }
  ConstraintSpec spec;
  spec.source = source;
  int index = 0;
  try {
    for (auto node : list) {
      ItemContext ctx{source, node.Mark().line + 1, index, "", ""};
      spec.items.push_back(YamlItemReader(node, ctx).read());
      ++index;
    }
  } catch (const YAML::Exception& e) {
    fail("{}:{}: item {}: {}", source, e.mark.line + 1, index, e.msg);
  }
  return spec;
}

ConstraintSpec load_constraint_spec(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  if (ext == ".h5" || ext == ".hdf5") return load_constraint_spec_h5(path);
  return parse_constraint_spec_yaml(read_file(path), path);
}

namespace {
ConstraintSpec load_constraint_spec_h5_unchecked(const std::string& path, const std::string& group);
}

// Sealed files (core/h5_seal.h) are checked by checksum; unsealed ones are read in
// a child process first, so libhdf5 crashing on a damaged file cannot take us down.
ConstraintSpec load_constraint_spec_h5(const std::string& path, const std::string& group) {
  if (!std::filesystem::exists(path)) fail("{}: no such constraint file", path);
  if (std::filesystem::is_directory(path)) fail("{}: is a directory, not a constraint file", path);
  if (check_h5_seal(path, "constraint file") == H5Seal::absent)
    isolated_probe(fmt::format("constraint file '{}'", path), [&] { load_constraint_spec_h5_unchecked(path, group); });
  return load_constraint_spec_h5_unchecked(path, group);
}

namespace {
ConstraintSpec load_constraint_spec_h5_unchecked(const std::string& path, const std::string& group) {
  QuietHdf5 quiet;
  H5Handle file(H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  if (!file.valid()) fail("{}: not a readable HDF5 file", path);
  if (H5Lexists(file.get(), group.c_str(), H5P_DEFAULT) <= 0)
    fail("{}: no group '{}' (a constraint file keeps its items under /{})", path, group, group);
  return read_constraint_spec_group(file.get(), group, path);
}
}  // namespace

ConstraintSpec read_constraint_spec_group(int64_t parent, const std::string& group, const std::string& path) {
  QuietHdf5 quiet;
  H5Handle g(H5Gopen2(static_cast<hid_t>(parent), group.c_str(), H5P_DEFAULT), H5Gclose);
  if (!g.valid()) fail("{}: '{}' is not a group", path, group);
  {
    if (H5Aexists(g.get(), "format") > 0) {
      H5Handle a(H5Aopen(g.get(), "format", H5P_DEFAULT), H5Aclose);
      H5Handle mt = utf8_string_type();
      H5Handle t(H5Aget_type(a.get()), H5Tclose);
      std::string format;
      if (H5Tget_class(t.get()) == H5T_STRING && H5Tis_variable_str(t.get()) > 0) {
        char* s = nullptr;
        if (H5Aread(a.get(), mt.get(), &s) >= 0 && s) format = s, H5free_memory(s);
      }
      if (!format.empty() && format != kH5Format)
        fail("{}: /{} has format '{}', expected '{}'", path, group, format, kH5Format);
    }
    if (H5Aexists(g.get(), "format_version") > 0) {
      H5Handle a(H5Aopen(g.get(), "format_version", H5P_DEFAULT), H5Aclose);
      int64_t version = 0;
      if (H5Aread(a.get(), H5T_NATIVE_INT64, &version) < 0 || version > kH5FormatVersion)
        fail("{}: /{} has format_version {}, this build reads up to {}", path, group, version, kH5FormatVersion);
    }
  }
  // Items are read in the numeric order of their names (item_0, item_1, ..., item_10).
  std::vector<std::pair<long, std::string>> names;
  H5G_info_t info;
  H5Gget_info(g.get(), &info);
  static const std::regex item_name(R"(^item_([0-9]+)$)");
  for (hsize_t i = 0; i < info.nlinks; ++i) {
    char buf[256] = {0};
    H5Lget_name_by_idx(g.get(), ".", H5_INDEX_NAME, H5_ITER_INC, i, buf, sizeof buf, H5P_DEFAULT);
    std::smatch m;
    std::string s = buf;
    if (!std::regex_match(s, m, item_name))
      fail("{}: /{}/{}: item groups must be named item_<number>", path, group, s);
    names.emplace_back(std::stol(m[1]), s);
  }
  std::sort(names.begin(), names.end());
  ConstraintSpec spec;
  spec.source = fmt::format("{}:/{}", path, group);
  for (size_t i = 0; i < names.size(); ++i) {
    H5Handle ig(H5Gopen2(g.get(), names[i].second.c_str(), H5P_DEFAULT), H5Gclose);
    if (!ig.valid()) fail("{}: /{}/{} is not a group", path, group, names[i].second);
    ItemContext ctx{fmt::format("{}:/{}/{}", path, group, names[i].second), 0, static_cast<int>(i), "", ""};
    spec.items.push_back(H5ItemReader(ig.get(), ctx).read());
  }
  return spec;
}

void save_constraint_spec_h5(const ConstraintSpec& spec, const std::string& path, const std::string& group) {
  QuietHdf5 quiet;
  AtomicOutput out(path);
  {
    // The user block holds the checksum seal (core/h5_seal.h), written after closing.
    H5Handle fcpl(H5Pcreate(H5P_FILE_CREATE), H5Pclose);
    H5Pset_userblock(fcpl.get(), kH5SealBlock);
    H5Handle file(H5Fcreate(out.tmp_path().c_str(), H5F_ACC_TRUNC, fcpl.get(), H5P_DEFAULT), H5Fclose);
    if (!file.valid()) fail("{}: cannot create the HDF5 file", path);
    write_constraint_spec_group(file.get(), group, spec, path);
  }  // closed (flushed) here, before the seal covers its bytes
  seal_h5_file(out.tmp_path().string(), fmt::format("constraint file '{}'", path));
  out.commit();
}

void write_constraint_spec_group(int64_t parent, const std::string& group, const ConstraintSpec& spec,
                                 const std::string& path) {
  QuietHdf5 quiet;
  {
    H5Handle gcpl(untimed(H5P_GROUP_CREATE), H5Pclose);
    H5Handle g(H5Gcreate2(static_cast<hid_t>(parent), group.c_str(), H5P_DEFAULT, gcpl.get(), H5P_DEFAULT), H5Gclose);
    if (!g.valid()) fail("{}: cannot create group '{}'", path, group);
    H5Writer gw(g.get());
    gw.attr_string("format", kH5Format);
    gw.attr_int("format_version", kH5FormatVersion);
    for (size_t i = 0; i < spec.items.size(); ++i) {
      const ConstraintItem& it = spec.items[i];
      std::string name = fmt::format("item_{:03d}", i);
      H5Handle ig(H5Gcreate2(g.get(), name.c_str(), H5P_DEFAULT, gcpl.get(), H5P_DEFAULT), H5Gclose);
      H5Writer w(ig.get());
      w.attr_string("type", it.type);
      if (!it.name.empty()) w.attr_string("name", it.name);
      if (it.variance != 0) w.attr_double("variance", it.variance);
      if (it.from_source) w.attr_int("from_source", 1);
      if (it.up_to_root_translation) w.attr_int("up_to_root_translation", 1);
      if (!it.role.empty()) w.attr_string("role", it.role);
      if (it.score_only) w.attr_int("score_only", 1);
      if (it.height != 0.0) w.attr_double("height", it.height);
      if (it.offset != 0.0) w.attr_double("offset", it.offset);
      if (it.type == "tangent") w.attr_double("min_speed", it.min_speed);
      if (it.type == "facing") w.attr_double("min_width", it.min_width);
      if (!it.normal.empty()) w.doubles("normal", it.normal, {static_cast<int>(it.normal.size())});
      if (!it.lower.empty()) w.doubles("min", it.lower, {static_cast<int>(it.lower.size())});
      if (!it.upper.empty()) w.doubles("max", it.upper, {static_cast<int>(it.upper.size())});
      if (it.relative_to.set()) {
        if (!it.relative_to.name.empty()) w.strings("relative_to", {it.relative_to.name});
        else w.ints("relative_to", {it.relative_to.index});
      }
      if (!it.joints.empty()) {
        bool by_name = std::all_of(it.joints.begin(), it.joints.end(), [](auto& r) { return !r.name.empty(); });
        bool by_index = std::all_of(it.joints.begin(), it.joints.end(), [](auto& r) { return r.name.empty(); });
        if (!by_name && !by_index)
          fail("{}: {}: key 'joints': mixing names and indices cannot be stored in HDF5", spec.source,
               spec.item_label(static_cast<int>(i)));
        if (by_name) {
          std::vector<std::string> v;
          for (auto& r : it.joints) v.push_back(r.name);
          w.strings("joints", v);
        } else {
          std::vector<int> v;
          for (auto& r : it.joints) v.push_back(r.index);
          w.ints("joints", v);
        }
      }
      switch (it.frames.kind) {
        case FrameSelection::Kind::unset: break;
        case FrameSelection::Kind::all: w.attr_string("frames", "all"); break;
        case FrameSelection::Kind::list: w.ints("frames", it.frames.list); break;
        case FrameSelection::Kind::range:
          w.attr_int("frames_start", it.frames.start);
          w.attr_int("frames_stop", it.frames.stop);
          w.attr_int("frames_step", it.frames.step);
          break;
      }
      if (!it.axes.empty()) w.ints("axes", it.axes);
      if (it.values.given()) w.doubles("values", it.values.data, it.values.shape);
      if (it.has_camera)
        w.doubles("camera", {it.camera.scale, it.camera.pitch_deg, it.camera.yaw_deg, it.camera.roll_deg}, {4});
    }
  }
}

}  // namespace mc
