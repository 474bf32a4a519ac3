// Runs one table row: tasks from the protocol, `repeats` fresh generations,
// evaluator and control metrics per replicate, cached in a run directory keyed
// by the resolved generator, protocol and profile and the SHA-1 of the data file
// and evaluator checkpoint (content, not paths), and reused only while the trained
// components it used still have the weights it recorded (experiments/row_record.h).
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <iostream>
#include <optional>
#include <set>
#include <sstream>

#include "control/camera.h"
#include "control/linear_observation.h"
#include "control/sample_constraints.h"
#include <H5Cpp.h>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "data/fixture/fixture_build.h"
#include "data/motion_file_extra.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "eval/observation_errors.h"
#include "experiments/experiment.h"
#include "experiments/row_evaluator.h"
#include "experiments/row_record.h"
#include "models/anchor_adapters.h"
#include "samplers/motion_generator.h"
#include "train/pretrained.h"
#include "train/train_job.h"
#include "train/trainer.h"

namespace mc {
namespace fs = std::filesystem;

ProfileFile load_profile(const std::string& name_or_file) {
  std::string file = name_or_file;
  if (file.find('/') == std::string::npos && file.find(".yaml") == std::string::npos)
    file = resolve_data_path("configs/profile/" + file + ".yaml");
  if (!fs::exists(file))
    fail("profile '{}' not found ({} does not exist); known profiles are the files in configs/profile/", name_or_file,
         file);
  return load_job<ProfileFile>(file, {});
}

// One table_num_samples entry: "table_id=N" with N >= 1 (std::nullopt when malformed).
static std::optional<std::pair<std::string, int>> parse_table_tasks(const std::string& entry) {
  const auto eq = entry.rfind('=');
  if (eq == std::string::npos || eq == 0 || eq + 1 == entry.size()) return std::nullopt;
  const std::string n = entry.substr(eq + 1);
  if (n.size() > 9 || !std::all_of(n.begin(), n.end(), [](char c) { return c >= '0' && c <= '9'; }))
    return std::nullopt;
  const int v = std::stoi(n);
  if (v < 1) return std::nullopt;
  return std::make_pair(entry.substr(0, eq), v);
}

std::string ProfileConfig::validate() const {
  std::set<std::string> seen;
  for (const auto& e : table_num_samples) {
    auto p = parse_table_tasks(e);
    if (!p)
      return fmt::format("profile.table_num_samples: '{}' is not table_id=N with N >= 1 (e.g. anchorroute/table4=256)",
                         e);
    if (!seen.insert(p->first).second)
      return fmt::format("profile.table_num_samples: table '{}' is listed twice; keep one entry", p->first);
  }
  return "";
}

int table_tasks(const ProfileConfig& profile, const TableConfig& table) {
  for (const auto& e : profile.table_num_samples)
    if (auto p = parse_table_tasks(e); p && p->first == table.id) return p->second;
  return table.num_samples > 0 ? table.num_samples : profile.num_samples;
}

std::string TableConfig::validate() const {
  if (id.empty()) return "table.id is empty";
  if (columns.empty()) return "table.columns is empty: name at least one metric";
  for (const auto& d : derived) {
    const auto eq = d.find('='), slash = d.find('/', eq == std::string::npos ? 0 : eq);
    if (eq == std::string::npos || eq == 0 || slash == std::string::npos || slash == eq + 1 || slash + 1 == d.size())
      return fmt::format("table.derived: '{}' is not column=metric/row (e.g. relative_cost=time_per_sample/rs0)", d);
    if (std::find(columns.begin(), columns.end(), d.substr(0, eq)) == columns.end())
      return fmt::format("table.derived: '{}' derives column '{}', which table.columns does not list", d,
                         d.substr(0, eq));
  }
  return "";
}

DerivedColumn parse_derived_column(const std::string& entry, const std::string& what) {
  const auto eq = entry.find('=');
  const auto slash = entry.find('/', eq == std::string::npos ? 0 : eq);
  if (eq == std::string::npos || slash == std::string::npos)
    fail("{}: table.derived entry '{}' is not column=metric/row", what, entry);
  return {entry.substr(0, eq), entry.substr(eq + 1, slash - eq - 1), entry.substr(slash + 1)};
}

TableSpec load_table_spec(const std::string& file) {
  TableSpec spec;
  spec.file = file;
  YAML::Node root;
  try {
    root = YAML::LoadFile(file);
  } catch (const YAML::Exception& e) {
    fail("{}: cannot read the experiment spec: {}", file, e.what());
  }
  if (!root.IsMap() || !root["table"] || !root["rows"])
    fail("{}: an experiment spec needs a `table:` section and a `rows:` list", file);
  for (auto kv : root) {
    std::string k = kv.first.as<std::string>();
    if (k != "table" && k != "rows")
      fail("{}: unknown top-level key '{}'{}; an experiment spec has `table:` and `rows:`", file, k,
           did_you_mean(k, {"table", "rows"}).empty() ? "" : " (did you mean '" + did_you_mean(k, {"table", "rows"}) + "'?)");
  }
  {
    YAML::Node t;
    t["table"] = root["table"];
    // Parsed as a section of a one-key document so messages say `table.<key>`.
    struct Wrapper : Config {
      TableConfig* t;
      void visit(FieldVisitor& v) override { v("table", *t, "table"); }
    } w;
    w.t = &spec.table;
    parse_config(config_from_string(YAML::Dump(t), file), w);
  }
  if (!root["rows"].IsSequence() || root["rows"].size() == 0) fail("{}: `rows:` must be a non-empty list", file);
  std::set<std::string> ids;
  for (size_t i = 0; i < root["rows"].size(); ++i) {
    RowConfig row;
    parse_config(config_from_string(YAML::Dump(root["rows"][i]), fmt::format("{} rows[{}]", file, i)), row);
    if (!ids.insert(row.id).second) fail("{}: rows[{}] repeats the row id '{}'; ids must be unique", file, i, row.id);
    spec.rows.push_back(row);
  }
  for (const auto& d : spec.table.derived) {
    const DerivedColumn dc = parse_derived_column(d, file);
    if (!ids.count(dc.base_row))
      fail("{}: table.derived '{}' divides by row '{}', which is not a row of the table (rows: {})", file, d,
           dc.base_row, fmt::join(ids, ", "));
  }
  return spec;
}

// The component under `key` of `file` with the profile substitutions whose path
// exists in it, then `overrides` (parse_component_file).
static std::string resolve_component(const std::string& file, const std::string& key,
                                     const std::vector<std::string>& substitutions,
                                     const std::vector<std::string>& overrides, Component& out) {
  std::string path = resolve_data_path(file);
  if (!fs::exists(path)) fail("{} file '{}' does not exist", key, file);
  return parse_component_file(path, key, substitutions, overrides, out);
}

ResolvedRow resolve_row(const ProfileConfig& profile, const TableSpec& table, const RowConfig& row) {
  ResolvedRow r;
  r.generator_yaml = resolve_component(row.generator, "generator", profile.substitutions, row.overrides, r.generator);
  std::string proto_file = row.protocol.empty() ? table.table.protocol : row.protocol;
  if (proto_file.empty()) fail("{}: row '{}' has no protocol and the table names none", table.file, row.id);
  std::vector<std::string> po = table.table.protocol_overrides;
  po.insert(po.end(), row.protocol_overrides.begin(), row.protocol_overrides.end());
  r.protocol_yaml = resolve_component(proto_file, "protocol", profile.substitutions, po, r.protocol);
  return r;
}

// Changes to what a generator computes from the same config and weights, keyed only for
// the rows they touch (left out of the dump when off, so other rows keep their caches).
struct RowRevisions : Config {
  // 2026-11-25: under CFG the null-text pass of an adapter whose hooks read the text (dual
  // context, the ControlNet adapter) gets hooks computed on the null text, not the
  // caption's. Set for the rows whose adapter reads the text.
  bool adapter_null_text_hooks = false;
  void visit(FieldVisitor& v) override {
    v("adapter_null_text_hooks", adapter_null_text_hooks,
      "anchorroute rows with an adapter: the CFG null-text pass's hooks are computed on the null text");
  }
  bool omitted_from_dump() const override { return !adapter_null_text_hooks; }
};

// Reads the config of the adapter run the row resolved to (the profile's swaps applied).
static RowRevisions row_revisions(const Component& generator, const RowComponents& components) {
  RowRevisions r;
  if (generator.type != "anchorroute") return r;
  for (const auto& d : components.all) {
    if (d.what != "adapter") continue;
    const auto job = load_job<TrainJobConfig>((fs::path(d.run) / "config.yaml").string(), {});
    if (job.model.type != "anchor_adapter") continue;
    const auto& a = job.model.as<AnchorAdapterConfig>();
    r.adapter_null_text_hooks =
        a.adapter == "controlnet" || a.dual_context || (a.adapter == "anchorkv" && a.anchorkv.text_slots.enabled);
  }
  return r;
}

// The key that decides whether a finished row run can be reused.
struct RowRunKey : Config {
  std::string generator, protocol, data, evaluator, split;
  std::string data_content_sha1, evaluator_sha1;  // the inputs by content: other clips or weights are a new key
  std::vector<std::string> trained_configs;
  int num_samples = 0, repeats = 0, mm_texts = 0, mm_generations = 0;
  int64_t seed = 0;
  EvalProtocol eval;
  RowRevisions revisions;
  // What a finished run holds: 2 = samples.h5 with per-sample records (paired tests),
  // group-mean headline values, both foot-skating conventions, KID and the GT floor;
  // 3 = also floor penetration, inequality violation and direction errors (issue 20).
  int record_version = 3;
  void visit(FieldVisitor& v) override {
    v("record_version", record_version, "what a finished row run holds (bumped when that changes)");
    v("generator", generator, "resolved generator");
    v("protocol", protocol, "resolved protocol");
    v("data", data, "ground-truth file");
    v("evaluator", evaluator, "evaluator config");
    v("split", split, "split");
    v("data_content_sha1", data_content_sha1, "SHA-1 of what the ground-truth file holds (RowEvaluator::data_content_sha1)");
    v("evaluator_sha1", evaluator_sha1, "SHA-1 of the evaluator checkpoint's bytes");
    v("trained_configs", trained_configs, "training-config swaps");
    v("num_samples", num_samples, "tasks");
    v("repeats", repeats, "replications");
    v("mm_texts", mm_texts, "multimodality texts");
    v("mm_generations", mm_generations, "multimodality generations per text");
    v("seed", seed, "base seed");
    v("eval", eval, "metric protocol");
    v("revisions", revisions, "generator changes that void the rows they touch");
  }
};

// Frames of an item resolved against T (the compile() rules for camera items: default all).
static std::vector<int> item_frames(const FrameSelection& f, int T) {
  std::vector<int> out;
  switch (f.kind) {
    case FrameSelection::Kind::list:
      for (int t : f.list) out.push_back(t < 0 ? T + t : t);
      break;
    case FrameSelection::Kind::range:
      for (int t = f.start; t < (f.stop < 0 ? T : std::min(f.stop, T)); t += f.step) out.push_back(t);
      break;
    default:
      for (int t = 0; t < T; ++t) out.push_back(t);
  }
  return out;
}

// Per-sample metrics of one replicate (the record paired tests resample):
// control errors (avg_err, traj_err, loc_err per threshold, control_error with its
// entry count), foot skating under both frame conventions, the lifting errors, and
// the T2M per-sample quantities (matching, R-precision hits in the replicate's pools).
// NaN where a metric does not apply to a sample (a task without that control).
std::map<std::string, std::vector<double>> row_sample_metrics(const MotionSet& gen, const EvalEmbeddings& emb,
                                                             const std::vector<ControlTask>& tasks,
                                                             const EvalProtocol& proto, uint64_t seed) {
  const size_t n = tasks.size();
  const Skeleton& skel = gen.skeleton;
  const int J = gen.num_joints();
  const double nan = std::nan("");
  std::map<std::string, std::vector<double>> out = per_sample_t2m(emb.text, emb.motion, proto.r_precision_pool, seed);
  auto col = [&](const std::string& k) -> std::vector<double>& {
    auto& v = out[k];
    if (v.empty()) v.assign(n, nan);
    return v;
  };
  FootSkatingOptions valid, padded;
  valid.fps = padded.fps = gen.fps;
  padded.padded_196 = true;
  const std::vector<int>& toes = skel.role("toes");
  for (size_t i = 0; i < n; ++i) {
    const JointsView clip = joints_view(gen, i);
    col("foot_skating_valid")[i] = foot_skating_ratio(clip, toes, valid);
    // The published convention needs 196 stored frames; shorter stores score their own frames.
    col("foot_skating_padded")[i] = clip.frames >= padded.padded_length ? foot_skating_ratio(clip, toes, padded)
                                                                        : col("foot_skating_valid")[i];
  }
  for (size_t i = 0; i < n; ++i) {
    // Toes under the floor (y = 0): depth in metres, and the fraction of frames with a
    // toe more than 1e-6 m below it (the precision a hard floor row is met to; float32
    // world coordinates round at ~1e-7 m, so "strictly below" would count rounding).
    const JointsView clip = joints_view(gen, i);
    double lowest = INFINITY;
    int below = 0;
    for (int t = 0; t < clip.length; ++t) {
      bool any = false;
      for (int j : toes) {
        const double y = clip.at(t, j).y();
        lowest = std::min(lowest, y);
        any = any || y < -1e-6;
      }
      below += any;
    }
    if (clip.length > 0) {
      col("floor_penetration")[i] = std::max(0.0, -lowest);
      col("floor_frames")[i] = static_cast<double>(below) / clip.length;
    }
  }
  const double th0 = proto.control_thresholds.front();
  for (size_t i = 0; i < n; ++i) {
    const ControlTask& task = tasks[i];
    if (task.spec.items.empty()) continue;
    const int T = gen.lengths[i];
    LinearObservation obs = compile(task.spec, T, skel, task.source.empty() ? nullptr : task.source.data());
    if (obs.inequalities() > 0) col("inequality_violation")[i] = max_inequality_violation(obs, gen.clip(i));
    if (!obs.directions.empty()) {
      double sum = 0;
      auto angles = direction_errors(obs, gen.clip(i));
      for (double a : angles) sum += a;
      col("direction_error")[i] = sum / angles.size();
    }
    std::vector<double> e = observation_entry_errors(obs, gen.clip(i));
    if (!e.empty()) {
      double sum = 0;
      for (double x : e) sum += x;
      col("avg_err")[i] = sum / e.size();
      col("control_error")[i] = sum / e.size();
      col("control_entries")[i] = static_cast<double>(e.size());
      for (double th : proto.control_thresholds) {
        size_t over = 0;
        for (double x : e) over += x > th;
        const double traj = over > 0 ? 1.0 : 0.0, loc = static_cast<double>(over) / e.size();
        if (th == th0) col("traj_err")[i] = traj, col("loc_err")[i] = loc;
        col(fmt::format("traj_err_{:g}cm", th * 100))[i] = traj;
        col(fmt::format("loc_err_{:g}cm", th * 100))[i] = loc;
      }
    }
    // 2D-to-3D lifting: MPJPE on the keypose item's frames (the first camera item), the
    // Avg.Err over the controlled entries of every camera item (keypose and 2D trajectory).
    const ConstraintItem* first = nullptr;
    std::vector<uint8_t> mask;
    for (const auto& item : task.spec.items) {
      if (item.type != "camera_2d" || task.source.empty()) continue;
      if (!first) {
        first = &item;
        mask.assign(static_cast<size_t>(T) * J, 0);
      } else if (item.camera.scale != first->camera.scale || item.camera.pitch_deg != first->camera.pitch_deg ||
                 item.camera.yaw_deg != first->camera.yaw_deg || item.camera.roll_deg != first->camera.roll_deg) {
        fail("task '{}': its camera items use different cameras; the lifting metrics need one camera per task",
             task.id);
      }
      std::vector<int> joints;
      if (item.joints.empty())
        for (int j = 0; j < J; ++j) joints.push_back(j);
      else
        for (const auto& r : item.joints) joints.push_back(r.name.empty() ? r.index : skel.joint_index(r.name));
      for (int t : item_frames(item.frames, T))
        for (int j : joints) mask[static_cast<size_t>(t) * J + j] = 1;
    }
    if (first) {
      LiftingSample s;
      s.prediction = JointsView{gen.clip(i), T, J, T};  // the valid frames only
      s.ground_truth = joints_view(task.source, T, J);
      s.camera = OrthoCamera{first->camera.scale, first->camera.pitch_deg * M_PI / 180.0,
                             first->camera.yaw_deg * M_PI / 180.0, first->camera.roll_deg * M_PI / 180.0};
      s.target_2d = project_motion(s.camera, s.ground_truth);
      s.keyframes = item_frames(first->frames, T);
      s.controlled = mask_view(mask, T, J, 1);
      LiftingMetrics lm = lifting_metrics({s}, skel.root());
      col("mpjpe_2d")[i] = lm.mpjpe_2d;
      col("mpjpe_3d")[i] = lm.mpjpe_3d;
      col("avg_err_2d")[i] = lm.avg_err_2d;
      col("avg_err_3d")[i] = lm.avg_err_3d;
    }
  }
  return out;
}

// Table numbers of one replicate: the evaluator's T2M metrics, KID and the ground-truth
// FID/KID floor at the same N, and every per-sample metric averaged as the papers do
// (headline_value: mean over task groups of group means) with the pooled mean as an
// extra `<metric>_pooled`; control metrics also per task group and group component.
static std::map<std::string, double> replicate_metrics(RowEvaluator& ev, const EvalEmbeddings& emb,
                                                       const std::map<std::string, std::vector<double>>& per_sample,
                                                       const std::vector<ControlTask>& tasks,
                                                       const EvalProtocol& proto, uint64_t seed) {
  std::map<std::string, double> out = ev.t2m(emb, proto, seed);
  out["kid"] = ev.realism().kid(emb.motion);
  auto [fid_floor, kid_floor] = ev.realism_floor(static_cast<int>(tasks.size()));
  out["fid_floor"] = fid_floor;
  out["kid_floor"] = kid_floor;
  std::vector<std::string> groups;
  std::set<std::string> filters;
  for (const auto& t : tasks) {
    groups.push_back(t.group);
    if (t.group.empty()) continue;
    filters.insert(t.group);
    size_t start = 0;
    while (true) {
      size_t slash = t.group.find('/', start);
      filters.insert(t.group.substr(start, slash == std::string::npos ? std::string::npos : slash - start));
      if (slash == std::string::npos) break;
      start = slash + 1;
    }
  }
  for (const auto& [k, _] : per_sample) {
    if (!group_averaged_metric(k)) continue;
    if (auto v = headline_value(per_sample, groups, k)) out[k] = *v;
    if (auto v = headline_value(per_sample, groups, k, true)) out[k + "_pooled"] = *v;
  }
  for (const std::string& f : filters)
    for (const char* k : {"traj_err", "loc_err", "avg_err", "control_error"})
      if (auto v = headline_value(per_sample, groups, std::string(k) + "@" + f)) out[std::string(k) + "@" + f] = *v;
  return out;
}

// The foot_skating column and per-sample metric under the table's frame convention.
static void alias_foot_skating(RowResult& r, const std::string& convention) {
  const std::string src = convention == "valid_frames" ? "foot_skating_valid" : "foot_skating_padded";
  if (r.values.count(src)) r.values["foot_skating"] = r.values.at(src);
  for (auto& m : r.samples.metrics)
    if (m.count(src)) m["foot_skating"] = m.at(src);
}

// The first `k` samples of a replicate with what figures need to draw them
// against their tasks: target clip, hard 3D point constraints, cameras. Sealed like
// the row's other files (core/h5_seal.h), so report.cpp's copy into results.h5
// refuses a damaged one naming it instead of copying garbage or crashing.
void write_examples(const std::string& path, const MotionSet& gen, const std::vector<ControlTask>& tasks,
                           size_t k) {
  k = std::min(k, tasks.size());
  const int J = gen.num_joints(), T = gen.t_max;
  const size_t per = static_cast<size_t>(T) * J * 3;
  std::vector<float> joints(k * per, 0.f), target(k * per, 0.f);
  std::vector<uint8_t> controlled(k * per, 0), controlled_2d(k * static_cast<size_t>(T) * J, 0);
  std::vector<double> camera(k * 4, 0.0);
  std::vector<int32_t> lengths(k);
  bool any_camera = false;
  std::string captions, ids;
  for (size_t i = 0; i < k; ++i) {
    const int len = gen.lengths[i];
    lengths[i] = len;
    std::copy(gen.clip(i), gen.clip(i) + static_cast<size_t>(len) * J * 3, joints.begin() + i * per);
    const ControlTask& t = tasks[i];
    std::copy(t.source.begin(), t.source.begin() + std::min(t.source.size(), static_cast<size_t>(len) * J * 3),
              target.begin() + i * per);
    captions += (i ? "\n" : "") + t.caption;
    ids += (i ? "\n" : "") + t.id;
    if (t.spec.items.empty()) continue;
    LinearObservation obs = compile(t.spec, len, gen.skeleton, t.source.empty() ? nullptr : t.source.data());
    for (int r = 0; r < obs.rows(); ++r) {
      if (!obs.is_hard(r) || obs.A.outerIndexPtr()[r + 1] - obs.A.outerIndexPtr()[r] != 1) continue;
      Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(obs.A, r);
      controlled[i * per + it.col()] = 1;
    }
    for (const auto& item : t.spec.items) {
      if (item.type != "camera_2d") continue;
      if (!any_camera || camera[i * 4] == 0.0) {
        camera[i * 4 + 0] = item.camera.scale;
        camera[i * 4 + 1] = item.camera.pitch_deg;
        camera[i * 4 + 2] = item.camera.yaw_deg;
        camera[i * 4 + 3] = item.camera.roll_deg;
      }
      any_camera = true;
      std::vector<int> js;
      if (item.joints.empty())
        for (int j = 0; j < J; ++j) js.push_back(j);
      else
        for (const auto& r : item.joints) js.push_back(r.name.empty() ? r.index : gen.skeleton.joint_index(r.name));
      for (int f : item_frames(item.frames, len))
        for (int j : js) controlled_2d[(i * T + f) * J + j] = 1;
    }
  }
  AtomicOutput out(path);
  {
    H5::Exception::dontPrint();
    H5::FileCreatPropList fcpl;
    fcpl.setUserblock(kH5SealBlock);  // the seal, written once the file is closed
    H5::H5File f(out.tmp_path().string(), H5F_ACC_TRUNC, fcpl);
    hsize_t d4[4] = {k, static_cast<hsize_t>(T), static_cast<hsize_t>(J), 3};
    H5::DataSpace s4(4, d4);
    f.createDataSet("joints", H5::PredType::NATIVE_FLOAT, s4).write(joints.data(), H5::PredType::NATIVE_FLOAT);
    f.createDataSet("target", H5::PredType::NATIVE_FLOAT, s4).write(target.data(), H5::PredType::NATIVE_FLOAT);
    f.createDataSet("controlled", H5::PredType::NATIVE_UINT8, s4).write(controlled.data(), H5::PredType::NATIVE_UINT8);
    hsize_t d1 = k;
    H5::DataSpace s1(1, &d1);
    f.createDataSet("lengths", H5::PredType::NATIVE_INT32, s1).write(lengths.data(), H5::PredType::NATIVE_INT32);
    if (any_camera) {
      hsize_t dc[2] = {k, 4};
      H5::DataSpace sc(2, dc);
      f.createDataSet("camera", H5::PredType::NATIVE_DOUBLE, sc).write(camera.data(), H5::PredType::NATIVE_DOUBLE);
      hsize_t d3[3] = {k, static_cast<hsize_t>(T), static_cast<hsize_t>(J)};
      H5::DataSpace s3(3, d3);
      f.createDataSet("controlled_2d", H5::PredType::NATIVE_UINT8, s3)
          .write(controlled_2d.data(), H5::PredType::NATIVE_UINT8);
    }
    H5::DataSpace scalar(H5S_SCALAR);
    for (auto [name, value] : {std::pair<const char*, std::string>{"captions", captions}, {"task_ids", ids}}) {
      H5::StrType type(H5::PredType::C_S1, std::max<size_t>(1, value.size()));
      f.createAttribute(name, type, scalar).write(type, value.empty() ? std::string(" ") : value);
    }
  }  // closed (flushed) here, before the seal covers its bytes
  seal_h5_file(out.tmp_path().string(), fmt::format("row examples file '{}'", path));
  out.commit();
}

// The directory a row's numbers are cached in. A row's directory is named
// `<row id>-<hash of its key>`, and the key (generator, protocol, data and evaluator
// content, weights, seeds) holds everything the numbers depend on, but not the row id.
// So a row whose own directory is not finished reuses a finished one with the same
// hash and the same config.yaml under another id (the same row shared by two tables
// under two ids, or a renamed row): the same computation is not run twice. The first
// such directory by name, so the choice does not depend on the file system's order.
static std::string content_twin(const RunConfig& rc, const std::string& own_name, const std::string& hash,
                                const std::string& yaml) {
  const fs::path own = RunDir::path_of(rc, own_name);
  if (fs::exists(own / "DONE")) return own_name;
  const std::string suffix = "-" + hash;
  std::vector<std::string> twins;
  std::error_code ec;
  for (fs::directory_iterator it(own.parent_path(), ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name == own_name || name.size() <= suffix.size() ||
        name.compare(name.size() - suffix.size(), suffix.size(), suffix) != 0)
      continue;
    if (!fs::exists(it->path() / "DONE") || !fs::exists(it->path() / "config.yaml")) continue;
    try {
      if (read_file(it->path() / "config.yaml") == yaml) twins.push_back(name);
    } catch (const UserError&) {
      // unreadable: not a twin; its own row recomputes or reports it
    }
  }
  if (twins.empty()) return own_name;
  std::sort(twins.begin(), twins.end());
  return twins.front();
}

RowResult run_row(const ProfileFile& pf, const TableSpec& table, const RowConfig& row, RowEvaluator& ev) {
  const ProfileConfig& profile = pf.profile;
  RowResult result;
  result.row_id = row.id;
  result.label = row.label.empty() ? row.id : row.label;
  ResolvedRow rr = resolve_row(profile, table, row);

  RowRunKey key;
  key.generator = rr.generator_yaml;
  key.protocol = rr.protocol_yaml;
  key.data = profile.data;
  key.evaluator = profile.evaluator;
  key.split = profile.split;
  key.data_content_sha1 = ev.data_content_sha1();
  key.evaluator_sha1 = file_sha1(fs::path(ev.evaluator_run()) / "checkpoints" / "final.pt");
  key.trained_configs = profile.trained_configs;
  key.num_samples = table_tasks(profile, table.table);
  key.repeats = row.repeats > 0 ? row.repeats : profile.repeats;
  key.mm_texts = table.table.multimodality_texts;
  key.mm_generations = table.table.multimodality_texts > 0 ? table.table.multimodality_generations : 0;
  key.seed = profile.seed;
  key.eval = pf.protocol;
  // The trained components the row uses as they are now (what is missing or stale is
  // trained first), each with its weights' SHA-1: the directory's name covers the
  // row's config, not weights retrained in place.
  const RowComponents components = resolve_row_components(rr.generator);
  key.revisions = row_revisions(rr.generator, components);
  RunConfig rc;
  rc.root = profile.runs_root;
  rc.experiment = sanitize_name(profile.name) + "/rows";
  rc.seed = profile.seed;
  rc.threads = profile.threads;
  rc.device = profile.device;
  std::string yaml = dump_config(key);
  const std::string own_name = sanitize_name(row.id) + "-" + config_hash(key);
  const std::string run_name = content_twin(rc, own_name, config_hash(key), yaml);
  RunDir run = RunDir::open(rc, yaml, {}, run_name);
  if (run_name != own_name)
    run.log().info(fmt::format("row {}: the same computation as this row (same key, {}); reused under its name",
                               row.id, config_hash(key)));
  result.run_dir = run.path().string();
  const ResolvedDependency evaluator = evaluator_component(ev.evaluator_run(), profile.evaluator);
  const std::string record_note =
      "a table row: the trained components and the evaluator it was computed with; a replay recomputes it when "
      "they differ (docs/choices.md, \"Table replay: rows keyed by their weights\")";
  bool cached = run.finished();
  // A damaged cache (metrics.h5 or samples.h5 missing, seal mismatch, unreadable) is a
  // miss, not a failed row: the row is deterministic, so it is recomputed in place.
  CachedRowRecords records;
  if (cached) {
    records = read_cached_row_records(run.path().string());
    if (!records.usable()) {
      const std::string warning =
          fmt::format("warning: row {}: its cache cannot be used, recomputing it: {}", row.id, records.damage);
      std::cerr << warning << "\n";
      RunConfig again = rc;
      again.force = true;
      run = RunDir::open(again, yaml, {}, run_name);
      run.log().info(warning);
      cached = false;
    }
  }
  if (cached) {
    const RowReuse reuse = check_row(run.path(), components, evaluator);
    if (reuse.state == RowReuse::State::recompute) {
      // Redone where it is, from a cleared directory: an interrupted recomputation
      // leaves an unfinished row, never the old numbers beside a new record.
      RunConfig again = rc;
      again.force = true;
      run = RunDir::open(again, yaml, {}, run_name);
      run.log().info(fmt::format("row {}: {} was computed on {}: recomputing it", row.id, run.path().string(),
                                 fmt::join(reuse.reasons, "; ")));
      cached = false;
    } else if (reuse.state == RowReuse::State::adopt) {
      write_row_record(run.path(), components, evaluator,
                       fmt::format("adopted {}: {}; the row predates row records, and every component finished "
                                   "before it did, so it is taken as computed on the weights they had then",
                                   utc_timestamp(), record_note));
      run.log().info(fmt::format(
          "warning: row {}: {} has no record of the weights it was computed with (computed before rows kept one); "
          "every component it uses finished before it did, so it is taken as computed on today's {}; if one of them "
          "was retrained to other weights in between, delete {} to recompute the row",
          row.id, run.path().string(), describe_dependencies(components.all), run.path().string()));
    } else if (!fs::exists(run.path() / kDependencyRecord)) {
      write_row_record(run.path(), components, evaluator, record_note);  // a legacy row with no component
    }
  }
  if (cached) {
    result.values = std::move(records.values);
    result.samples = std::move(records.samples);
    alias_foot_skating(result, table.table.foot_skating);
    result.cached = true;
    if (fs::exists(run.path() / "notes.txt")) {
      std::ifstream in(run.path() / "notes.txt");
      std::string line;
      std::getline(in, result.generator_description);
      while (std::getline(in, line)) result.notes.push_back(line);
    }
    result.components = read_row_components(run.path());
    return result;
  }

  std::vector<ControlTask> tasks = ev.tasks(as_protocol(rr.protocol), key.num_samples, profile.seed);
  GeneratorContext ctx;
  ctx.device = setup_torch(rc);
  std::unique_ptr<MotionGenerator> gen = as_generator(rr.generator).make(ctx);
  result.components = components.trained;
  result.generator_description = gen->describe();
  run.log().info(fmt::format("row {}: {} on {} tasks x {} replicates", row.id, result.generator_description,
                             tasks.size(), key.repeats));
  for (const auto& t : tasks) {
    result.samples.task_ids.push_back(t.id + "|" + t.clip_id);
    result.samples.groups.push_back(t.group);
  }
  for (int r = 0; r < key.repeats; ++r) {
    const uint64_t seed = static_cast<uint64_t>(profile.seed) + 1000ull * r;
    GeneratedMotions g = gen->generate(tasks, seed);
    MotionSet m = generated_motion_set(g, tasks, ev.data());
    if (r == 0) {
      result.notes = g.notes;
      write_examples((run.path() / "examples.h5").string(), m, tasks, kExamplesPerRow);
    }
    m.provenance = Provenance{"motionctl reproduce", MOTIONCTL_VERSION, static_cast<int64_t>(seed), yaml, utc_timestamp()};
    // Each sample's spec with its targets written out (/control), as `generate` stores
    // it: `motionctl score samples_r<r>.h5` then scores a row's motions with no spec.
    std::vector<ConstraintSpec> stored;
    std::vector<int> stored_frames;
    for (size_t i = 0; i < tasks.size(); ++i) {
      stored.push_back(with_explicit_targets(tasks[i].spec, m.lengths[i], m.skeleton,
                                             tasks[i].source.empty() ? nullptr : tasks[i].source.data()));
      stored_frames.push_back(m.lengths[i]);
    }
    const std::string samples_path = (run.path() / fmt::format("samples_r{}.h5", r)).string();
    write_motion_file(samples_path, m,
                      [&](int64_t f) { write_sample_constraints(f, stored, stored_frames, samples_path); });
    EvalEmbeddings emb = ev.embed(m);
    auto per_sample = row_sample_metrics(m, emb, tasks, pf.protocol, seed);
    auto metrics = replicate_metrics(ev, emb, per_sample, tasks, pf.protocol, seed);
    result.samples.motion.push_back(emb.motion);
    result.samples.text.push_back(emb.text);
    result.samples.seeds.push_back(seed);
    result.samples.metrics.push_back(std::move(per_sample));
    metrics["time_per_sample"] = g.seconds / std::max<size_t>(1, tasks.size());
    metrics["throughput"] = static_cast<double>(tasks.size()) / std::max(g.seconds, 1e-9);
    for (auto& [k, v] : g.stats) metrics[k] = v;
    if (key.mm_texts > 0) {
      // T2M's multimodality pass: the first texts, each generated mm_generations times.
      const int texts = std::min<int>(key.mm_texts, static_cast<int>(tasks.size()));
      std::vector<ControlTask> mm;
      for (int i = 0; i < texts; ++i)
        for (int k = 0; k < key.mm_generations; ++k) {
          mm.push_back(tasks[i]);
          mm.back().id += fmt::format("#mm{}", k);
        }
      GeneratedMotions gm = gen->generate(mm, seed + 7);
      metrics["multimodality"] =
          ev.multimodality(generated_motion_set(gm, mm, ev.data()), texts, key.mm_generations, pf.protocol.multimodality_pairs,
                           seed + 7);
    }
    for (auto& [k, v] : metrics) {
      if (!std::isfinite(v)) fail("row '{}': metric {} is not finite in replicate {}", row.id, k, r);
      result.values[k].push_back(v);
    }
    run.log().info(fmt::format("  replicate {}: {:.2f} s/sample", r, metrics["time_per_sample"]));
  }
  std::string notes = result.generator_description + "\n";
  for (auto& n : result.notes) notes += n + "\n";
  write_file_atomic(run.path() / "notes.txt", notes);
  std::string comps;
  for (auto& c : result.components) comps += c + "\n";
  write_file_atomic(run.path() / "components.txt", comps);
  write_row_record(run.path(), components, evaluator, record_note);  // before DONE: a finished row has one
  write_metric_results(run.path().string(), result.values);
  write_row_samples((run.path() / "samples.h5").string(), result.samples);
  alias_foot_skating(result, table.table.foot_skating);
  std::map<std::string, double> summary;
  for (auto& [k, v] : result.values) summary[k] = summarize(v).mean;
  run.mark_finished(summary);
  return result;
}

}  // namespace mc
