// Evaluation protocol: embeddings, one replication of the T2M metrics,
// evaluator-free metrics, and the CSV/HDF5 result files.
#include "eval/evaluation.h"
#include "eval/eval_outputs.h"
#include "eval/h5_arrays.h"

#include <H5Cpp.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>

#include "control/constraint_spec.h"
#include "control/linear_observation.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/h5_seal.h"
#include "eval/observation_errors.h"

namespace mc {

EvalEmbeddings embed_for_eval(const T2MEvaluator& ev, const MotionSet& reference, const std::string& reference_source,
                              const MotionSet& motions, const std::string& motions_source) {
  EvalEmbeddings e;
  e.gt_motion = ev.embed_motions(reference, reference_source);
  e.motion = ev.embed_motions(motions, motions_source);
  for (size_t i = 0; i < motions.size(); ++i) e.captions.push_back(motions.captions[i].at(0));
  e.text = ev.embed_texts(e.captions);
  return e;
}

std::map<std::string, double> t2m_metrics(const EvalEmbeddings& e, const EvalProtocol& p, uint64_t seed) {
  const int n = static_cast<int>(e.motion.rows());
  if (n < 2) fail("evaluation needs at least 2 motions, got {}", n);
  std::mt19937_64 rng(seed);
  // Each replication draws fresh R-precision pools (a permutation of the pairs).
  std::vector<int> perm(n);
  std::iota(perm.begin(), perm.end(), 0);
  for (int i = n - 1; i > 0; --i) std::swap(perm[i], perm[uniform_index(rng, i + 1)]);
  Embeddings text(n, e.text.cols()), motion(n, e.motion.cols());
  for (int i = 0; i < n; ++i) {
    text.row(i) = e.text.row(perm[i]);
    motion.row(i) = e.motion.row(perm[i]);
  }
  std::map<std::string, double> out;
  const int pool = p.r_precision_pool;
  if (n >= pool) {
    auto r = r_precision(text, motion, pool, 3);
    out["r_precision_top1"] = r[0];
    out["r_precision_top2"] = r[1];
    out["r_precision_top3"] = r[2];
    const int full = n / pool * pool;  // T2M's matching score covers the full pools only
    out["matching"] = matching_score(text.topRows(full), motion.topRows(full));
  } else {
    out["matching"] = matching_score(text, motion);
  }
  if (e.gt_motion.rows() >= 2) out["fid"] = fid(motion, e.gt_motion);
  out["diversity"] = diversity(motion, std::min(p.diversity_pairs, n), rng);
  // Multimodality: captions with several generations.
  std::map<std::string, std::vector<int>> by_caption;
  for (int i = 0; i < n; ++i) by_caption[e.captions[i]].push_back(i);
  // Groups are cut to the smallest group size (the metric needs equal sizes).
  int smallest = 0;
  for (auto& [_, rows] : by_caption)
    if (rows.size() >= 2) smallest = smallest == 0 ? static_cast<int>(rows.size()) : std::min<int>(smallest, rows.size());
  std::vector<Embeddings> groups;
  for (auto& [_, rows] : by_caption)
    if (smallest > 0 && static_cast<int>(rows.size()) >= smallest) {
      Embeddings g(smallest, e.motion.cols());
      for (int k = 0; k < smallest; ++k) g.row(k) = e.motion.row(rows[k]);
      groups.push_back(g);
    }
  if (!groups.empty()) out["multimodality"] = multimodality(groups, std::min(p.multimodality_pairs, smallest), rng);
  return out;
}

// traj_err/loc_err at each threshold, avg_err, control_error from per-sample entry errors.
static void add_control_metrics(const std::vector<std::vector<double>>& errors, const EvalProtocol& p,
                                std::map<std::string, double>& out) {
  // Specs of inequality or direction items only (a floor) have no control entries.
  if (std::none_of(errors.begin(), errors.end(), [](const auto& e) { return !e.empty(); })) return;
  ControlOptions co;
  co.thresholds = p.control_thresholds;
  ControlMetrics cm = control_metrics_from_errors(errors, co);
  for (auto& rate : cm.rates) {
    out[fmt::format("traj_err@{}", rate.threshold)] = rate.traj_err;
    out[fmt::format("loc_err@{}", rate.threshold)] = rate.loc_err;
  }
  out["avg_err"] = cm.avg_err;
  out["control_error"] = cm.control_error;
}

std::map<std::string, double> evaluator_free_metrics(const MotionSet& motions, const std::string& motions_source,
                                                     const EvalProtocol& p, const std::string& constraints,
                                                     const MotionSet* source) {
  std::map<std::string, double> out;
  if (motions.size() == 0)
    fail("{}: holds no clips (its dataset 'lengths' is empty); there are no motions to score", motions_source);
  FootSkatingOptions fo;
  fo.fps = motions.fps;
  fo.padded_196 = p.foot_skating_padded_196;
  // What foot skating needs of a valid motion file, said here with the file, clip
  // and dataset: the metric itself knows only "the clip" (eval/foot_skating.cpp).
  if (fo.padded_196 && motions.t_max < fo.padded_length)
    fail("{}: foot skating over the padded {} frames (--padded-196, protocol.foot_skating_padded_196) needs {} "
         "stored frames per clip, but dataset 'joints' holds {} (T_max); score over each clip's own length instead",
         motions_source, fo.padded_length, fo.padded_length, motions.t_max);
  if (!fo.padded_196)
    for (size_t i = 0; i < motions.size(); ++i)
      if (motions.lengths[i] < 2)
        fail("{}: clip {} ('{}') has 'lengths' {}; foot skating needs at least 2 frames (one transition) per clip, "
             "so drop the clip or give it more frames",
             motions_source, i, motions.ids[i], motions.lengths[i]);
  std::vector<JointsView> clips;
  for (size_t i = 0; i < motions.size(); ++i) clips.push_back(joints_view(motions, i));
  out["foot_skating"] = foot_skating_ratio(clips, motions.skeleton, fo);
  if (constraints.empty()) return out;

  std::vector<std::vector<double>> errors = control_entry_errors(motions, motions_source, constraints, source);
  add_control_metrics(errors, p, out);
  return out;
}

std::map<std::string, double> free_metrics_of_selection(const std::vector<JointsView>& clips,
                                                        const std::vector<std::vector<double>>* errors,
                                                        const std::vector<size_t>& idx, const Skeleton& skeleton,
                                                        double fps, const EvalProtocol& p) {
  if (idx.empty()) fail("free_metrics_of_selection: no samples selected");
  if (errors && errors->size() != clips.size())
    fail("free_metrics_of_selection: {} error lists for {} clips", errors->size(), clips.size());
  FootSkatingOptions fo;
  fo.fps = fps;
  fo.padded_196 = p.foot_skating_padded_196;
  std::vector<JointsView> sel;
  std::vector<std::vector<double>> sel_err;
  for (size_t i : idx) {
    if (i >= clips.size()) fail("free_metrics_of_selection: index {} out of {} clips", i, clips.size());
    sel.push_back(clips[i]);
    if (errors && !(*errors)[i].empty()) sel_err.push_back((*errors)[i]);
  }
  std::map<std::string, double> out;
  out["foot_skating"] = foot_skating_ratio(sel, skeleton, fo);
  if (!sel_err.empty()) add_control_metrics(sel_err, p, out);
  return out;
}

std::map<std::string, double> evaluator_free_metrics(const MotionSet& motions, const std::string& motions_source,
                                                     const EvalProtocol& p, const std::vector<ConstraintSpec>& specs) {
  std::map<std::string, double> out = evaluator_free_metrics(motions, motions_source, p, "", nullptr);
  std::vector<std::vector<double>> errors;
  for (auto& e : control_entry_errors(motions, motions_source, specs))
    if (!e.empty()) errors.push_back(std::move(e));  // unconstrained samples, as generate's error line skips them
  if (!errors.empty()) add_control_metrics(errors, p, out);
  return out;
}

std::vector<std::vector<double>> control_entry_errors(const MotionSet& motions, const std::string& motions_source,
                                                      const std::string& constraints, const MotionSet* source) {
  ConstraintSpec spec = load_constraint_spec(constraints);
  if (source && source->size() != motions.size())
    fail("constraint source has {} clips but {} has {}; give one source clip per motion", source->size(),
         motions_source, motions.size());
  std::vector<std::vector<double>> errors;
  const int J = motions.num_joints();
  for (size_t i = 0; i < motions.size(); ++i) {
    const int T = motions.lengths[i];
    std::vector<float> src;
    if (source) {
      if (source->lengths[i] < T)
        fail("constraint source clip {} has {} frames, fewer than motion {} ({})", i, source->lengths[i], i, T);
      src.assign(source->clip(i), source->clip(i) + static_cast<size_t>(T) * J * 3);
    }
    LinearObservation obs = compile(spec, T, motions.skeleton, source ? src.data() : nullptr);
    errors.push_back(observation_entry_errors(obs, motions.clip(i)));
  }
  return errors;
}

std::vector<std::vector<double>> control_entry_errors(const MotionSet& motions, const std::string& motions_source,
                                                      const std::vector<ConstraintSpec>& specs) {
  if (specs.size() != motions.size())
    fail("{}: {} constraint specs for {} motions; give one spec per motion", motions_source, specs.size(),
         motions.size());
  std::vector<std::vector<double>> errors(motions.size());
  for (size_t i = 0; i < motions.size(); ++i)
    if (!specs[i].items.empty())
      errors[i] = observation_entry_errors(compile(specs[i], motions.lengths[i], motions.skeleton, nullptr),
                                           motions.clip(i));
  return errors;
}

// Metric keys may hold '/' (task groups such as "control_error@family=root3d/K=8"),
// which HDF5 reads as a path: it is stored as '|'.
static std::string h5_metric_name(std::string k) {
  std::replace(k.begin(), k.end(), '/', '|');
  return k;
}

// metrics.h5 is sealed (core/h5_seal.h): a changed byte is refused before libhdf5
// reads it; one written before seals is read in a forked child first. Either way a
// damaged file is a UserError naming it, never a crash or silently wrong numbers.
static std::string metrics_file_path(const std::string& dir) { return (fs::path(dir) / "metrics.h5").string(); }

static std::string metrics_file_fix(const std::string& dir) {
  return fmt::format("delete the run directory '{}' and run the command again to recompute it", dir);
}

static void guard_metrics_file(const std::string& dir, const std::function<void()>& probe) {
  const std::string path = metrics_file_path(dir);
  std::error_code ec;
  if (!fs::is_regular_file(path, ec))
    fail("metrics file '{}' does not exist; {}", path, metrics_file_fix(dir));
  guard_h5_read(path, "metrics file", metrics_file_fix(dir), probe);
}

static std::map<std::string, std::vector<double>> read_metric_results_unchecked(const std::string& dir) {
  const std::string path = metrics_file_path(dir);
  std::map<std::string, std::vector<double>> out;
  try {
    H5::Exception::dontPrint();
    H5::H5File f(path, H5F_ACC_RDONLY);
    H5::Group g = f.openGroup("replicates");
    for (hsize_t i = 0; i < g.getNumObjs(); ++i) {
      std::string name = g.getObjnameByIdx(i);
      H5::DataSet ds = g.openDataSet(name);
      H5::DataSpace space = ds.getSpace();
      if (space.getSimpleExtentNdims() != 1)  // one value per replicate (getSimpleExtentDims would overrun n)
        fail("{}: dataset 'replicates/{}' is not one-dimensional; {}", path, name, metrics_file_fix(dir));
      hsize_t n = 0;
      space.getSimpleExtentDims(&n);
      std::vector<double> v(n);
      ds.read(v.data(), H5::PredType::NATIVE_DOUBLE);
      std::replace(name.begin(), name.end(), '|', '/');
      out[name] = v;
    }
  } catch (const H5::Exception& e) {
    fail("{}: cannot read metric results ({}); {}", path, e.getDetailMsg(), metrics_file_fix(dir));
  }
  return out;
}

std::map<std::string, std::vector<double>> read_metric_results(const std::string& dir) {
  guard_metrics_file(dir, [&] { read_metric_results_unchecked(dir); });
  return read_metric_results_unchecked(dir);
}

static void write_metric_results_impl(const std::string& dir, const std::map<std::string, std::vector<double>>& values,
                                      const std::map<std::string, Replicated>& summaries,
                                      const EvalSampleRecord* record);

namespace {

void write_string_attr(H5::H5Object& o, const std::string& name, const std::string& value) {
  H5::StrType type(H5::PredType::C_S1, H5T_VARIABLE);
  type.setCset(H5T_CSET_UTF8);
  const char* p = value.c_str();
  o.createAttribute(name, type, H5::DataSpace(H5S_SCALAR)).write(type, &p);
}

void write_record(H5::H5File& f, const EvalSampleRecord& r) {
  for (auto& [k, v] : r.attrs) write_string_attr(f, k, v);
  if (r.embeddings) {
    H5::Group g = f.createGroup("embeddings");
    write_matrix(g, "motion", r.embeddings->motion);
    write_matrix(g, "text", r.embeddings->text);
    write_matrix(g, "gt_motion", r.embeddings->gt_motion);
    write_strings(g, "captions", r.embeddings->captions);
    write_strings(g, "gt_ids", r.reference_ids);
  }
  H5::Group g = f.createGroup("samples");
  write_strings(g, "ids", r.ids);
  hsize_t n = r.lengths.size();
  H5::DataSpace space(1, &n);
  g.createDataSet("lengths", H5::PredType::STD_I32LE, space).write(r.lengths.data(), H5::PredType::NATIVE_INT);
  for (auto& [k, v] : r.metrics) {
    if (v.size() != r.lengths.size())
      throw std::logic_error(fmt::format("per-sample metric {} has {} values for {} samples", k, v.size(), n));
    g.createDataSet(h5_metric_name(k), H5::PredType::IEEE_F64LE, space).write(v.data(), H5::PredType::NATIVE_DOUBLE);
  }
}

}  // namespace

static EvalEmbeddings read_eval_embeddings_unchecked(const std::string& dir) {
  const std::string path = metrics_file_path(dir);
  EvalEmbeddings e;
  try {
    H5::Exception::dontPrint();
    H5::H5File f(path, H5F_ACC_RDONLY);
    if (!f.nameExists("embeddings"))
      fail("{}: no /embeddings group (written by `motionctl eval` since metrics.h5 format_version 2); re-run the "
           "evaluation with run.force=true",
           path);
    H5::Group g = f.openGroup("embeddings");
    e.motion = read_matrix(g, "motion");
    e.text = read_matrix(g, "text");
    e.gt_motion = read_matrix(g, "gt_motion");
    e.captions = read_strings(g, "captions");
  } catch (const H5::Exception& ex) {
    fail("{}: cannot read the embeddings ({}); {}", path, ex.getDetailMsg(), metrics_file_fix(dir));
  }
  return e;
}

EvalEmbeddings read_eval_embeddings(const std::string& dir) {
  guard_metrics_file(dir, [&] { read_eval_embeddings_unchecked(dir); });
  return read_eval_embeddings_unchecked(dir);
}

void write_metric_results(const std::string& dir, const std::map<std::string, std::vector<double>>& values) {
  std::map<std::string, Replicated> summaries;
  for (auto& [k, v] : values) summaries[k] = summarize(v);
  write_metric_results_impl(dir, values, summaries, nullptr);
}

void write_eval_results(const std::string& dir, const std::map<std::string, std::vector<double>>& values,
                        const std::map<std::string, Replicated>& summaries, const EvalSampleRecord& record) {
  write_metric_results_impl(dir, values, summaries, &record);
}

static void write_metric_results_impl(const std::string& dir, const std::map<std::string, std::vector<double>>& values,
                                      const std::map<std::string, Replicated>& summaries,
                                      const EvalSampleRecord* record) {
  for (auto& [k, v] : values)
    if (!summaries.count(k)) fail("{}: metric '{}' has values but no summary", dir, k);
  std::string csv = "metric,mean,std,ci95,n\n";
  for (auto& [k, v] : values) {
    const Replicated& r = summaries.at(k);
    csv += fmt::format("{},{:.8g},{:.8g},{:.8g},{}\n", k, r.mean, r.std, r.ci95, r.n);
  }
  write_file_atomic(fs::path(dir) / "metrics.csv", csv);

  AtomicOutput out(metrics_file_path(dir));
  {
    H5::Exception::dontPrint();
    // The user block holds the checksum seal (core/h5_seal.h), written once the file is closed.
    H5::FileCreatPropList fcpl;
    fcpl.setUserblock(kH5SealBlock);
    H5::H5File f(out.tmp_path().string(), H5F_ACC_TRUNC, fcpl);
    H5::Group g = f.createGroup("replicates");
    for (auto& [k, v] : values) {
      hsize_t n = v.size();
      H5::DataSpace space(1, &n);
      auto ds = g.createDataSet(h5_metric_name(k), H5::PredType::NATIVE_DOUBLE, space);
      ds.write(v.data(), H5::PredType::NATIVE_DOUBLE);
      const Replicated& r = summaries.at(k);
      H5::DataSpace scalar(H5S_SCALAR);
      for (auto [name, val] : {std::pair<const char*, double>{"mean", r.mean}, {"std", r.std}, {"ci95", r.ci95}})
        ds.createAttribute(name, H5::PredType::NATIVE_DOUBLE, scalar).write(H5::PredType::NATIVE_DOUBLE, &val);
    }
    // Version 1 files (no attributes) held /replicates only; 2 adds these attributes and,
    // from `motionctl eval`, /embeddings and /samples.
    write_string_attr(f, "format", "motionctl.metrics");
    // How mean/std/ci95 relate to /replicates: fresh replications, or bootstrap
    // resamples of fixed samples around the full set's value (bootstrap_summary).
    write_string_attr(f, "interval", record ? "bootstrap" : "replications");
    const int64_t version = 2;
    f.createAttribute("format_version", H5::PredType::STD_I64LE, H5::DataSpace(H5S_SCALAR))
        .write(H5::PredType::NATIVE_INT64, &version);
    if (record) write_record(f, *record);
  }  // closed (flushed) here, before the seal covers its bytes
  seal_h5_file(out.tmp_path().string(), fmt::format("metrics file '{}'", metrics_file_path(dir)));
  out.commit();
}

std::string format_metric_table(const std::map<std::string, std::vector<double>>& values) {
  std::map<std::string, Replicated> summaries;
  for (auto& [k, v] : values) summaries[k] = summarize(v);
  return format_metric_table(summaries);
}

std::string format_metric_table(const std::map<std::string, Replicated>& summaries) {
  std::string s = fmt::format("{:<22} {:>12} {:>12} {:>4}\n", "metric", "mean", "±95% CI", "n");
  for (auto& [k, r] : summaries) s += fmt::format("{:<22} {:>12.5f} {:>12.5f} {:>4}\n", k, r.mean, r.ci95, r.n);
  return s;
}

Replicated bootstrap_summary(double full_set_value, const std::vector<double>& resamples) {
  if (!std::isfinite(full_set_value)) fail("bootstrap_summary: full-set value {} is not finite", full_set_value);
  Replicated r;
  r.mean = full_set_value;
  r.n = static_cast<int>(resamples.size());
  if (r.n < 2) return r;
  double m = 0;
  for (double v : resamples) {
    if (!std::isfinite(v)) fail("bootstrap_summary: resample value {} is not finite", v);
    m += v;
  }
  m /= r.n;
  double ss = 0;
  for (double v : resamples) ss += (v - m) * (v - m);
  r.std = std::sqrt(ss / (r.n - 1));  // the bootstrap standard error
  r.ci95 = 1.96 * r.std;               // not / sqrt(n): each resample is a whole-set estimate
  return r;
}

EvalEmbeddings select_rows(const EvalEmbeddings& e, const std::vector<size_t>& idx) {
  EvalEmbeddings out;
  out.gt_motion = e.gt_motion;
  out.motion.resize(static_cast<Eigen::Index>(idx.size()), e.motion.cols());
  out.text.resize(static_cast<Eigen::Index>(idx.size()), e.text.cols());
  for (size_t r = 0; r < idx.size(); ++r) {
    if (idx[r] >= static_cast<size_t>(e.motion.rows()))
      fail("select_rows: index {} out of {} motions", idx[r], e.motion.rows());
    out.motion.row(static_cast<Eigen::Index>(r)) = e.motion.row(static_cast<Eigen::Index>(idx[r]));
    out.text.row(static_cast<Eigen::Index>(r)) = e.text.row(static_cast<Eigen::Index>(idx[r]));
    out.captions.push_back(e.captions.at(idx[r]));
  }
  return out;
}

}  // namespace mc
